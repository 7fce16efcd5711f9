"""Compiled code and the machine it runs on: the one builder of the C++ extensions (:mod:`.build`, used by
the rasterizer and by the field ops), CPU feature detection and timing (:mod:`.cpu`), and the OpenMP
threading environment the entry points set before torch loads (:mod:`.threads`).

Importing this package imports nothing else (no torch), so :func:`.threads.configure_openmp` can run
first.
"""
