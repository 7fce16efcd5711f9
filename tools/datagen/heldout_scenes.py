"""Static scenes beyond the shipped ones: rendered on demand, never shipped.

They stand in for "a scene the project has never seen": the same camera rig, resolution and layout as
the shipped static scenes (``static_scenes.render_static``), different objects, materials and lights.
``totem``, ``teaset``, ``mosaic``, ``library``, ``kettle`` and ``trophy`` are development scenes (their
validation views take part in choosing the main job's settings, docs/results.md; ``mosaic`` and
``library`` are built with high-contrast checkers, stripes and text photos, ``kettle`` and ``trophy``
from polished metal and coated plastic, so that settings for finely textured and for strongly
view-dependent scenes can be chosen without the held-out pair); ``lantern`` and ``robot`` have never been
used to choose a setting and are the held-out check, with ``windmill``, ``chess``, ``snowman`` and
``toybox`` (built before any run on them, never used to choose a setting).

    .venv-datagen/bin/python tools/datagen/render_all.py --only heldout/lantern heldout/robot --out /tmp/heldout
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


def build_lantern(scene):
    """A striped hexagonal lantern under a cone roof with a copper ring, a spring, two photo crates and a disc."""
    C.setup_world(scene, hdri="courtyard.exr", rot_z=1.9, sun_strength=2.8, sun_dir=(-0.3, 0.6, 0.7))
    body = G.cylinder(radius=0.34, depth=0.8, location=(0.0, 0.0, -0.4), vertices=6)
    M.assign(body, M.stripes("lantern_stripes", (0.95, 0.8, 0.3), (0.5, 0.1, 0.1), scale=9.0, roughness=0.35))
    roof = G.cone(radius1=0.48, radius2=0.05, depth=0.35, location=(0.0, 0.0, 0.17), vertices=6)
    M.assign(roof, M.voronoi("roof", (0.1, 0.25, 0.2), (0.6, 0.75, 0.5), scale=14.0))
    ring = G.torus(major=0.12, minor=0.03, location=(0.0, 0.0, 0.45), rotation=(math.radians(90), 0.0, 0.0))
    M.assign(ring, M.plain("ring", (0.95, 0.6, 0.4), roughness=0.2, metallic=1.0))
    spring = G.tube(G.helix(0.1, 0.05, 6.0, n=400, center=(0.62, 0.3, -0.85)), radius=0.015, name="spring")
    M.assign(spring, M.plain("spring", (0.2, 0.4, 0.9), roughness=0.3, coat=0.5))
    for i, (loc, photo) in enumerate([((-0.6, 0.35, -0.72), "rocket.jpg"), ((0.3, -0.62, -0.75), "horse.png")]):
        crate = G.cube(size=0.3, location=loc, rotation=(0.0, 0.0, 0.5 * (i + 1)))
        M.assign(crate, M.image(f"crate{i}", photo, roughness=0.5, coord="BOX", scale=(1.0, 1.0)))
    disc = G.cylinder(radius=0.8, depth=0.04, location=(0.0, 0.0, -0.9), vertices=64)
    M.assign(disc, M.checker("disc", (0.3, 0.3, 0.3), (0.85, 0.85, 0.8), scale=6.0, roughness=0.6, coord="Generated"))


def build_robot(scene):
    """A photo-faced box robot with a noisy head, two arms, a knot antenna, on a chessboard plinth."""
    C.setup_world(scene, hdri="sunset.exr", rot_z=0.4, sun_strength=3.0, sun_dir=(0.6, -0.2, 0.65))
    torso = G.cube(size=0.5, location=(0.0, 0.0, -0.4), scale=(1.0, 0.7, 1.2))
    M.assign(torso, M.image("torso", "camera.png", roughness=0.45, coord="BOX", scale=(1.0, 1.0), tint=(0.9, 0.7, 0.5)))
    head = G.uv_sphere(radius=0.2, location=(0.0, 0.0, 0.1))
    M.assign(head, M.noise("head", (0.7, 0.75, 0.8), (0.2, 0.25, 0.35), scale=10.0, roughness=0.25, metallic=0.6))
    for side in (-1.0, 1.0):
        arm = G.cylinder(radius=0.06, depth=0.55, location=(0.36 * side, 0.0, -0.4), rotation=(0.0, 0.35 * side, 0.0))
        M.assign(arm, M.plain(f"arm{side:+.0f}", (0.85, 0.15, 0.1), roughness=0.3))
    antenna = G.tube(G.torus_knot(2, 5, R=0.1, r=0.04, n=400, center=(0.0, 0.0, 0.0)), radius=0.012, name="antenna")
    antenna.location = (0.0, 0.0, 0.42)
    M.assign(antenna, M.plain("antenna", (0.95, 0.85, 0.2), roughness=0.2, metallic=1.0))
    plinth = G.cube(size=1.0, location=(0.0, 0.0, -0.88), scale=(1.3, 1.1, 0.08))
    M.assign(plinth, M.image("plinth", "chessboard_RGB.png", roughness=0.5, coord="BOX", scale=(1.0, 1.0)))


def build_mosaic(scene):
    """A checker ball on a text-photo drum, a striped cone, a coin-photo cube, a voronoi ring and a checker slab."""
    C.setup_world(scene, hdri="forest.exr", rot_z=4.1, sun_strength=3.0, sun_dir=(-0.4, 0.5, 0.7))
    ball = G.uv_sphere(radius=0.3, location=(0.0, 0.0, 0.05))
    M.assign(ball, M.checker("mosaic_ball", (0.95, 0.9, 0.8), (0.05, 0.05, 0.25), scale=8.0, roughness=0.3,
                             coord="Generated"))
    drum = G.cylinder(radius=0.32, depth=0.55, location=(0.0, 0.0, -0.55), vertices=48)
    M.assign(drum, M.image("drum", "text.png", roughness=0.5, coord="BOX", scale=(1.0, 1.0)))
    spire = G.cone(radius1=0.16, radius2=0.0, depth=0.45, location=(0.55, 0.35, -0.62))
    M.assign(spire, M.stripes("spire", (0.9, 0.75, 0.1), (0.1, 0.05, 0.05), scale=7.0, roughness=0.35))
    box = G.cube(size=0.3, location=(-0.55, -0.35, -0.72), rotation=(0.0, 0.0, 0.6))
    M.assign(box, M.image("coins", "coins.png", roughness=0.4, coord="BOX", scale=(1.5, 1.5), tint=(0.9, 0.8, 0.6)))
    ring = G.torus(major=0.42, minor=0.05, location=(0.0, 0.0, -0.25))
    M.assign(ring, M.voronoi("ring", (0.7, 0.1, 0.15), (0.95, 0.9, 0.85), scale=9.0))
    slab = G.cube(size=1.0, location=(0.0, 0.0, -0.88), scale=(1.2, 1.2, 0.08))
    M.assign(slab, M.checker("slab", (0.95, 0.9, 0.7), (0.03, 0.03, 0.05), scale=9.0, roughness=0.5, coord="Generated"))


def build_library(scene):
    """A striped shelf of page- and text-photo books, a cat-photo globe on a stand, a noisy vase and a checker mat."""
    C.setup_world(scene, hdri="city.exr", rot_z=2.2, sun_strength=3.1, sun_dir=(0.4, 0.4, 0.7))
    shelf = G.cube(size=1.0, location=(0.0, 0.25, -0.55), scale=(0.9, 0.25, 0.06))
    M.assign(shelf, M.stripes("shelf", (0.8, 0.55, 0.3), (0.2, 0.1, 0.05), scale=8.0))
    photos = ["page.png", "text.png", "page.png", "text.png", "page.png"]
    tints = [(0.9, 0.8, 0.6), (0.6, 0.7, 0.9), (0.9, 0.6, 0.6), (0.7, 0.9, 0.6), (0.9, 0.9, 0.9)]
    for i, (photo, tint) in enumerate(zip(photos, tints, strict=True)):
        book = G.cube(size=1.0, location=(-0.34 + 0.17 * i, 0.25, -0.3), rotation=(0.0, 0.08 * (i - 2), 0.0),
                      scale=(0.07, 0.2, 0.22 + 0.03 * (i % 3)))
        M.assign(book, M.image(f"book{i}", photo, roughness=0.5, coord="BOX", scale=(1.0, 1.0), tint=tint))
    globe = G.uv_sphere(radius=0.22, location=(0.1, -0.4, -0.2))
    M.assign(globe, M.image("globe", "chelsea.png", roughness=0.4, scale=(2.0, 1.0)))
    stand = G.cylinder(radius=0.04, depth=0.5, location=(0.1, -0.4, -0.62))
    M.assign(stand, M.plain("stand", (0.8, 0.65, 0.3), roughness=0.25, metallic=1.0))
    vase = G.uv_sphere(radius=0.17, location=(-0.5, -0.3, -0.68))
    vase.scale = (1.0, 1.0, 1.4)
    M.assign(vase, M.noise("vase", (0.1, 0.4, 0.6), (0.9, 0.85, 0.7), scale=10.0, detail=8.0, bump=0.2))
    mat = G.cube(size=1.0, location=(0.0, 0.0, -0.9), scale=(1.25, 1.1, 0.05))
    M.assign(mat, M.checker("mat", (0.05, 0.1, 0.3), (0.95, 0.95, 0.9), scale=8.0, roughness=0.5, coord="Generated"))


def build_kettle(scene):
    """A chrome kettle with a gold spout and lid knob, a glossy lacquered box, a steel spring and a brushed tray."""
    C.setup_world(scene, hdri="interior.exr", rot_z=1.1, sun_strength=3.0, sun_dir=(0.3, -0.6, 0.7))
    body = G.uv_sphere(radius=0.36, location=(0.0, 0.0, -0.45))
    body.scale = (1.0, 1.0, 0.85)
    M.assign(body, M.plain("chrome", (0.9, 0.9, 0.92), roughness=0.08, metallic=1.0))
    spout = G.cone(radius1=0.08, radius2=0.03, depth=0.4, location=(0.42, 0.0, -0.3), rotation=(0.0, 0.9, 0.0))
    M.assign(spout, M.plain("gold", (1.0, 0.78, 0.35), roughness=0.15, metallic=1.0))
    knob = G.uv_sphere(radius=0.06, location=(0.0, 0.0, -0.1))
    M.assign(knob, M.plain("knob", (1.0, 0.78, 0.35), roughness=0.15, metallic=1.0))
    box = G.cube(size=0.28, location=(-0.55, 0.4, -0.72), rotation=(0.0, 0.0, 0.5))
    M.assign(box, M.plain("lacquer", (0.6, 0.05, 0.08), roughness=0.1, coat=1.0))
    spring = G.tube(G.helix(0.09, 0.05, 7.0, n=420, center=(-0.45, -0.5, -0.85)), radius=0.014, name="spring")
    M.assign(spring, M.plain("steel", (0.8, 0.82, 0.85), roughness=0.2, metallic=1.0))
    tray = G.cylinder(radius=0.8, depth=0.04, location=(0.0, 0.0, -0.9), vertices=64)
    M.assign(tray, M.noise("tray", (0.75, 0.75, 0.78), (0.55, 0.55, 0.6), scale=6.0, roughness=0.3, metallic=1.0))


def build_trophy(scene):
    """A gold cup on a marble column, silver handles, a glass-coated blue orb, a copper wire crown and a dark plinth."""
    C.setup_world(scene, hdri="studio.exr", rot_z=0.3, sun_strength=2.6, sun_dir=(-0.5, 0.4, 0.7))
    cup = G.cone(radius1=0.12, radius2=0.32, depth=0.4, location=(0.0, 0.0, 0.0), vertices=48)
    M.assign(cup, M.plain("trophy_gold", (1.0, 0.76, 0.3), roughness=0.12, metallic=1.0))
    column = G.cylinder(radius=0.14, depth=0.7, location=(0.0, 0.0, -0.55), vertices=32)
    M.assign(column, M.noise("marble", (0.92, 0.92, 0.9), (0.55, 0.55, 0.6), scale=4.0, roughness=0.2, bump=0.0))
    for side in (-1.0, 1.0):
        handle = G.torus(major=0.12, minor=0.025, location=(0.33 * side, 0.0, 0.05),
                         rotation=(math.radians(90), 0.0, 0.0))
        M.assign(handle, M.plain(f"silver{side:+.0f}", (0.95, 0.95, 0.97), roughness=0.1, metallic=1.0))
    orb = G.uv_sphere(radius=0.18, location=(0.5, -0.4, -0.72))
    M.assign(orb, M.plain("orb", (0.1, 0.25, 0.8), roughness=0.05, coat=1.0))
    crown = G.tube(G.torus_knot(2, 7, R=0.5, r=0.05, n=500, center=(0.0, 0.0, -0.82)), radius=0.012, name="crown")
    M.assign(crown, M.plain("crown", (0.95, 0.6, 0.4), roughness=0.15, metallic=1.0))
    plinth = G.cube(size=1.0, location=(0.0, 0.0, -0.9), scale=(1.1, 1.1, 0.06))
    M.assign(plinth, M.plain("plinth", (0.12, 0.12, 0.14), roughness=0.25, coat=0.6))


def build_windmill(scene):
    """An octagonal voronoi tower under a cone roof, four striped sails, a photo banner, a brick well, a grass disc."""
    C.setup_world(scene, hdri="sunrise.exr", rot_z=0.9, sun_strength=3.0, sun_dir=(0.4, -0.5, 0.7))
    tower = G.cylinder(radius=0.26, depth=0.9, location=(0.0, 0.0, -0.4), vertices=8)
    M.assign(tower, M.voronoi("tower", (0.85, 0.8, 0.7), (0.35, 0.25, 0.2), scale=11.0))
    roof = G.cone(radius1=0.34, radius2=0.0, depth=0.35, location=(0.0, 0.0, 0.22), vertices=8)
    M.assign(roof, M.plain("roof", (0.55, 0.12, 0.08), roughness=0.4))
    for i in range(4):
        a = i * math.pi / 2 + 0.3
        sail = G.cube(size=1.0, location=(0.21 * math.sin(a), -0.3, 0.05 + 0.21 * math.cos(a)), rotation=(0.0, a, 0.0),
                      scale=(0.08, 0.015, 0.42))
        M.assign(sail, M.stripes(f"sail{i}", (0.95, 0.95, 0.9), (0.2, 0.3, 0.6), scale=12.0, roughness=0.5))
    banner = G.cube(size=1.0, location=(0.0, 0.3, -0.55), scale=(0.35, 0.02, 0.25))
    M.assign(banner, M.image("banner", "astronaut.png", roughness=0.5, coord="BOX", scale=(1.0, 1.0)))
    well = G.cylinder(radius=0.16, depth=0.22, location=(0.55, 0.35, -0.8), vertices=24)
    M.assign(well, M.image("well", "brick.png", roughness=0.6, coord="BOX", scale=(1.5, 1.5), tint=(0.9, 0.6, 0.5)))
    disc = G.cylinder(radius=0.85, depth=0.04, location=(0.0, 0.0, -0.9), vertices=64)
    M.assign(disc, M.image("meadow", "grass.png", roughness=0.7, coord="BOX", scale=(2.0, 2.0), tint=(0.5, 0.8, 0.4)))


def build_chess(scene):
    """Chessmen (plain and metallic cones, spheres, a torus) on a chessboard-photo board, a striped rim, a clock."""
    C.setup_world(scene, hdri="interior.exr", rot_z=2.9, sun_strength=2.8, sun_dir=(-0.4, -0.4, 0.75))
    board = G.cube(size=1.0, location=(0.0, 0.0, -0.85), scale=(1.3, 1.3, 0.06))
    M.assign(board, M.image("board", "chessboard_RGB.png", roughness=0.35, coord="BOX", scale=(1.0, 1.0)))
    rim = G.torus(major=0.9, minor=0.05, location=(0.0, 0.0, -0.86), major_seg=4, minor_seg=8)
    M.assign(rim, M.stripes("rim", (0.55, 0.35, 0.15), (0.3, 0.15, 0.05), scale=20.0, roughness=0.5))
    pieces = [((-0.35, -0.3), (0.95, 0.93, 0.85), 0.0), ((0.1, -0.4), (0.1, 0.1, 0.12), 0.0),
              ((0.4, 0.2), (0.95, 0.93, 0.85), 0.0), ((-0.2, 0.35), (0.1, 0.1, 0.12), 0.0),
              ((0.3, -0.05), (0.8, 0.6, 0.3), 1.0)]
    for i, ((x, y), col, metal) in enumerate(pieces):
        h = 0.3 + 0.08 * (i % 3)
        body = G.cone(radius1=0.11, radius2=0.04, depth=h, location=(x, y, -0.82 + h / 2), vertices=24)
        M.assign(body, M.plain(f"piece{i}", col, roughness=0.25, metallic=metal))
        top = G.uv_sphere(radius=0.07, location=(x, y, -0.82 + h + 0.04))
        M.assign(top, M.plain(f"top{i}", col, roughness=0.25, metallic=metal))
    crown = G.torus(major=0.07, minor=0.02, location=(0.3, -0.05, -0.82 + 0.46 + 0.1))
    M.assign(crown, M.plain("crown_gold", (1.0, 0.78, 0.35), roughness=0.15, metallic=1.0))
    clock = G.cylinder(radius=0.22, depth=0.05, location=(-0.1, 0.62, -0.55), rotation=(math.radians(80), 0.0, 0.0))
    M.assign(clock, M.image("clockface", "clock_motion.png", roughness=0.4, coord="BOX", scale=(1.0, 1.0)))


def build_snowman(scene):
    """Three noisy snow spheres, a carrot cone, a striped scarf, a top hat, coal buttons and a photo sign."""
    C.setup_world(scene, hdri="courtyard.exr", rot_z=3.6, sun_strength=3.2, sun_dir=(0.2, 0.6, 0.7))
    for i, (r, z) in enumerate([(0.38, -0.55), (0.28, -0.05), (0.2, 0.33)]):
        ball = G.uv_sphere(radius=r, location=(0.0, 0.0, z))
        M.assign(ball, M.noise(f"snow{i}", (0.95, 0.96, 0.98), (0.75, 0.8, 0.88), scale=14.0, roughness=0.6, bump=0.2))
    carrot = G.cone(radius1=0.04, radius2=0.0, depth=0.25, location=(0.0, -0.28, 0.35),
                    rotation=(math.radians(90), 0.0, 0.0))
    M.assign(carrot, M.plain("carrot", (0.95, 0.45, 0.05), roughness=0.4))
    scarf = G.torus(major=0.22, minor=0.05, location=(0.0, 0.0, 0.16))
    M.assign(scarf, M.stripes("scarf", (0.8, 0.1, 0.1), (0.95, 0.85, 0.2), scale=14.0, roughness=0.6))
    hat = G.cylinder(radius=0.13, depth=0.22, location=(0.0, 0.0, 0.6))
    M.assign(hat, M.plain("hat", (0.05, 0.05, 0.06), roughness=0.3, coat=0.4))
    brim = G.cylinder(radius=0.22, depth=0.02, location=(0.0, 0.0, 0.5))
    M.assign(brim, M.plain("brim", (0.05, 0.05, 0.06), roughness=0.3))
    for i, z in enumerate((-0.15, -0.02, 0.1)):
        coal = G.uv_sphere(radius=0.03, location=(0.0, -0.27 + 0.02 * abs(i - 1), z - 0.05))
        M.assign(coal, M.plain(f"coal{i}", (0.08, 0.08, 0.08), roughness=0.7))
    sign = G.cube(size=1.0, location=(0.55, 0.3, -0.6), rotation=(0.0, 0.0, -0.6), scale=(0.3, 0.02, 0.22))
    M.assign(sign, M.image("sign", "coffee.png", roughness=0.5, coord="BOX", scale=(1.0, 1.0)))
    ground = G.cylinder(radius=0.85, depth=0.04, location=(0.0, 0.0, -0.92), vertices=64)
    M.assign(ground, M.noise("ground", (0.9, 0.92, 0.95), (0.6, 0.65, 0.75), scale=5.0, roughness=0.7))


def build_toybox(scene):
    """Photo blocks (rocket, horse, cat, moon) in a stack, a coated torus knot, a steel spring and a checker mat."""
    C.setup_world(scene, hdri="sunset.exr", rot_z=5.1, sun_strength=3.0, sun_dir=(-0.6, 0.2, 0.65))
    blocks = [((-0.3, -0.2, -0.7), "rocket.jpg", 0.3), ((0.3, -0.25, -0.7), "horse.png", -0.2),
              ((0.0, 0.3, -0.7), "chelsea.png", 0.7), ((0.0, 0.0, -0.38), "moon.png", 0.1)]
    for i, (loc, photo, rot) in enumerate(blocks):
        b = G.cube(size=0.32, location=loc, rotation=(0.0, 0.0, rot))
        M.assign(b, M.image(f"block_{i}", photo, roughness=0.45, coord="BOX", scale=(1.0, 1.0)))
    knot = G.tube(G.torus_knot(2, 3, R=0.18, r=0.07, n=500, center=(0.0, 0.0, 0.0)), radius=0.03, name="toyknot")
    knot.location = (0.0, 0.0, 0.05)
    M.assign(knot, M.plain("toyknot", (0.1, 0.6, 0.3), roughness=0.2, coat=0.8))
    spring = G.tube(G.helix(0.1, 0.05, 6.0, n=400, center=(0.6, 0.4, -0.85)), radius=0.015, name="toyspring")
    M.assign(spring, M.plain("toysteel", (0.8, 0.82, 0.85), roughness=0.2, metallic=1.0))
    ball = G.uv_sphere(radius=0.14, location=(-0.6, 0.45, -0.76))
    M.assign(ball, M.checker("toyball", (0.95, 0.2, 0.2), (0.95, 0.95, 0.9), scale=6.0, roughness=0.3,
                             coord="Generated"))
    mat = G.cube(size=1.0, location=(0.0, 0.0, -0.9), scale=(1.2, 1.2, 0.05))
    M.assign(mat, M.checker("toymat", (0.2, 0.4, 0.8), (0.9, 0.9, 0.85), scale=5.0, roughness=0.5, coord="Generated"))


HELDOUT_SCENES = {
    "totem": build_totem,
    "teaset": build_teaset,
    "lantern": build_lantern,
    "robot": build_robot,
    "mosaic": build_mosaic,
    "library": build_library,
    "kettle": build_kettle,
    "trophy": build_trophy,
    "windmill": build_windmill,
    "chess": build_chess,
    "snowman": build_snowman,
    "toybox": build_toybox,
}
