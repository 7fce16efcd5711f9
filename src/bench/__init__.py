"""Benchmarks: ``python -m src.bench <subcommand> ...`` (see ``src/bench/__main__.py``)."""
