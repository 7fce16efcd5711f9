"""Held-out static scenes: rendered on demand, never shipped, never used to choose a setting.

They stand in for "a scene the project has never seen": the same camera rig, resolution and layout as
the shipped static scenes (``static_scenes.render_static``), different objects, materials and lights.

    .venv-datagen/bin/python tools/datagen/render_all.py --only heldout/totem heldout/teaset --out /tmp/heldout
"""

from __future__ import annotations

import math

import common as C
import geometry as G
import materials as M


def build_totem(scene):
    """A striped star column under a checker cone, a photo ball, a copper helix and two Voronoi blocks."""
    C.setup_world(scene, hdri="forest.exr", rot_z=2.6, sun_strength=3.0, sun_dir=(0.5, 0.3, 0.7))
    col = G.star_column(0.32, 0.2, 7, 1.1, 24, z0=-0.95, name="totem")
    M.assign(col, M.stripes("totem_stripes", (0.85, 0.35, 0.05), (0.1, 0.1, 0.3), scale=7.0, roughness=0.3))
    hat = G.cone(radius1=0.42, radius2=0.0, depth=0.5, location=(0.0, 0.0, 0.42))
    M.assign(hat, M.checker("hat", (0.9, 0.9, 0.2), (0.2, 0.5, 0.1), scale=10.0, roughness=0.4, coord="Generated"))
    ball = G.uv_sphere(radius=0.28, location=(0.6, -0.35, -0.7))
    M.assign(ball, M.image("ball", "coffee.png", roughness=0.3))
    wire = G.tube(G.helix(0.62, 0.14, 5.0, n=500, center=(0.0, 0.0, -0.95)), radius=0.018, name="wire")
    M.assign(wire, M.plain("copper", (0.95, 0.6, 0.4), roughness=0.15, metallic=1.0))
    for i, loc in enumerate([(-0.6, 0.4, -0.85), (-0.45, -0.55, -0.85)]):
        b = G.cube(size=0.22, location=loc, rotation=(0.0, 0.0, 0.4 * (i + 1)))
        M.assign(b, M.voronoi(f"block{i}", (0.6, 0.05, 0.1), (0.95, 0.85, 0.8), scale=9.0))


def build_teaset(scene):
    """A checker cup with a torus handle on a saucer, a noisy egg, a torus knot and a photo tile."""
    C.setup_world(scene, hdri="city.exr", rot_z=0.7, sun_strength=3.2, sun_dir=(-0.5, -0.3, 0.6))
    cup = G.cylinder(radius=0.36, depth=0.6, location=(0.0, 0.1, -0.45), vertices=48)
    M.assign(cup, M.checker("cup", (0.95, 0.95, 0.95), (0.1, 0.3, 0.7), scale=8.0, roughness=0.2, coord="Generated"))
    handle = G.torus(major=0.17, minor=0.04, location=(0.4, 0.1, -0.42), rotation=(math.radians(90), 0.0, 0.0))
    M.assign(handle, M.plain("handle", (0.1, 0.3, 0.7), roughness=0.2))
    saucer = G.cylinder(radius=0.7, depth=0.05, location=(0.0, 0.1, -0.78), vertices=64)
    M.assign(saucer, M.noise("saucer", (0.85, 0.8, 0.7), (0.5, 0.4, 0.3), scale=20.0))
    egg = G.uv_sphere(radius=0.22, location=(-0.55, -0.45, -0.55))
    egg.scale = (1.0, 1.0, 1.35)
    M.assign(egg, M.noise("egg", (0.9, 0.5, 0.2), (0.3, 0.1, 0.05), scale=12.0, bump=0.3))
    knot = G.tube(G.torus_knot(3, 4, R=0.25, r=0.08, n=500, center=(0.0, 0.0, 0.0)), radius=0.025, name="knot")
    knot.location = (0.1, -0.6, 0.25)
    M.assign(knot, M.plain("knot", (0.8, 0.1, 0.5), roughness=0.3, coat=0.5))
    tile = G.cube(size=1.0, location=(-0.2, 0.75, -0.3), rotation=(0.2, 0.0, 0.1), scale=(0.6, 0.02, 0.5))
    M.assign(tile, M.image("tile", "astronaut.png", roughness=0.4, coord="BOX", scale=(1.0, 1.0)))


HELDOUT_SCENES = {
    "totem": build_totem,
    "teaset": build_teaset,
}
