#!/usr/bin/env python3
"""Writes the furnished room: one OBJ per wall and per piece of furniture, as a user models
a room (a floor, a ceiling and four walls facing in; tables, chairs, a bookcase and its
books, columns, a sofa, lamps' shades), and `furnished-room.json` beside them.

    python3 examples/scenes/furnished-room/make.py

Metres (`unit_mm` 1000). The files it writes are kept in the repository; run it again only
to change the room. Each OBJ is a union of boxes wound outward (counter-clockwise seen from
outside), or a quad wound towards the room.
"""
import json
import math
import os
import random

HERE = os.path.dirname(os.path.abspath(__file__))
W, H, D = 8.0, 3.0, 6.0  # the room: x from 0 to W, y (up) 0 to H, z 0 to D


def quad_obj(a, b, c, d):
    """One quad a, b, c, d, counter-clockwise seen from its front."""
    return [a, b, c, d], [(1, 2, 3), (1, 3, 4)]


def box(lo, hi, rot_y=0.0, pivot=None):
    """A box from corner lo to hi, faces outward, turned rot_y degrees about y at pivot."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
         (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    if rot_y:
        px, _, pz = pivot or ((x0 + x1) / 2, 0, (z0 + z1) / 2)
        c, s = math.cos(math.radians(rot_y)), math.sin(math.radians(rot_y))
        v = [(px + (x - px) * c + (z - pz) * s, y, pz - (x - px) * s + (z - pz) * c) for x, y, z in v]
    # Counter-clockwise seen from outside.
    f = [(1, 4, 3), (1, 3, 2),  # z0 (faces -z)
         (5, 6, 7), (5, 7, 8),  # z1 (+z)
         (1, 5, 8), (1, 8, 4),  # x0 (-x)
         (2, 3, 7), (2, 7, 6),  # x1 (+x)
         (1, 2, 6), (1, 6, 5),  # y0 (-y)
         (4, 8, 7), (4, 7, 3)]  # y1 (+y)
    return v, f


def union(*parts):
    verts, faces = [], []
    for v, f in parts:
        base = len(verts)
        verts += v
        faces += [tuple(i + base for i in t) for t in f]
    return verts, faces


def write_obj(name, mesh):
    v, f = mesh
    with open(os.path.join(HERE, name + ".obj"), "w") as out:
        out.write(f"# {name}: furnished-room/make.py\n")
        for x, y, z in v:
            out.write(f"v {x:.4f} {y:.4f} {z:.4f}\n")
        for t in f:
            out.write("f " + " ".join(str(i) for i in t) + "\n")


def table(x, z, rot):
    top = box((x - 0.8, 0.72, z - 0.45), (x + 0.8, 0.76, z + 0.45), rot, (x, 0, z))
    legs = [box((x + sx * 0.72 - 0.03, 0, z + sz * 0.37 - 0.03),
                (x + sx * 0.72 + 0.03, 0.72, z + sz * 0.37 + 0.03), rot, (x, 0, z))
            for sx in (-1, 1) for sz in (-1, 1)]
    return union(top, *legs)


def chair(x, z, rot):
    seat = box((x - 0.22, 0.44, z - 0.22), (x + 0.22, 0.48, z + 0.22), rot, (x, 0, z))
    back = box((x - 0.22, 0.48, z + 0.19), (x + 0.22, 0.92, z + 0.22), rot, (x, 0, z))
    legs = [box((x + sx * 0.19 - 0.02, 0, z + sz * 0.19 - 0.02),
                (x + sx * 0.19 + 0.02, 0.44, z + sz * 0.19 + 0.02), rot, (x, 0, z))
            for sx in (-1, 1) for sz in (-1, 1)]
    return union(seat, back, *legs)


def main():
    rng = random.Random(7)
    objects = []

    def add(name, mesh, albedo, orientation=None):
        write_obj(name, mesh)
        o = {"name": name, "mesh": name + ".obj",
             "material": {"type": "diffuse", "albedo": [round(a, 3) for a in albedo]}}
        if orientation:
            o["orientation"] = orientation
        objects.append(o)

    # The shell: six quads facing into the room.
    p = lambda x, y, z: (x, y, z)
    add("floor", quad_obj(p(0, 0, 0), p(0, 0, D), p(W, 0, D), p(W, 0, 0)), (0.55, 0.45, 0.35))
    add("ceiling", quad_obj(p(0, H, 0), p(W, H, 0), p(W, H, D), p(0, H, D)), (0.85, 0.85, 0.85))
    add("wall_north", quad_obj(p(0, 0, 0), p(W, 0, 0), p(W, H, 0), p(0, H, 0)), (0.75, 0.72, 0.65))
    add("wall_south", quad_obj(p(0, 0, D), p(0, H, D), p(W, H, D), p(W, 0, D)), (0.75, 0.72, 0.65))
    add("wall_west", quad_obj(p(0, 0, 0), p(0, H, 0), p(0, H, D), p(0, 0, D)), (0.6, 0.7, 0.8))
    add("wall_east", quad_obj(p(W, 0, 0), p(W, 0, D), p(W, H, D), p(W, H, 0)), (0.8, 0.6, 0.55))

    # Four tables with four chairs each.
    wood = (0.5, 0.33, 0.2)
    for t, (x, z) in enumerate([(2.2, 2.0), (5.4, 2.0), (2.2, 4.2), (5.4, 4.2)]):
        rot = rng.uniform(-10, 10)
        add(f"table_{t}", table(x, z, rot), wood)
        for c, (dx, dz, r) in enumerate([(-0.45, -0.7, 180), (0.45, -0.7, 180),
                                         (-0.45, 0.7, 0), (0.45, 0.7, 0)]):
            add(f"chair_{t}_{c}", chair(x + dx, z + dz, r + rng.uniform(-15, 15)),
                (0.3 + 0.1 * c, 0.25, 0.2))

    # A bookcase against the west wall: sides, back and five boards, then its books.
    bx0, bx1, bz0, bz1 = 0.02, 0.37, 1.0, 3.4
    boards = [box((bx0, y, bz0), (bx1, y + 0.025, bz1)) for y in (0.0, 0.45, 0.9, 1.35, 1.8, 2.2)]
    sides = [box((bx0, 0, bz0), (bx1, 2.225, bz0 + 0.025)), box((bx0, 0, bz1 - 0.025), (bx1, 2.225, bz1))]
    add("bookcase", union(*boards, *sides), (0.45, 0.3, 0.2))
    b = 0
    for shelf in range(5):
        y = shelf * 0.45 + 0.025
        z = bz0 + 0.04
        while z < bz1 - 0.08 and b < 72:
            thick = rng.uniform(0.025, 0.06)
            tall = rng.uniform(0.2, 0.38)
            deep = rng.uniform(0.15, 0.25)
            lean = rng.choice([0, 0, 0, 4, -4])
            add(f"book_{b:02d}", box((0.05, y, z), (0.05 + deep, y + tall, z + thick), lean),
                [rng.uniform(0.1, 0.8) for _ in range(3)])
            z += thick + rng.uniform(0.002, 0.03)
            b += 1
            if rng.random() < 0.07:
                z += 0.15  # a gap on the shelf

    # Columns, a sofa and a low table by the east wall.
    for k, (x, z) in enumerate([(1.2, 1.2), (6.8, 1.2), (1.2, 4.8), (6.8, 4.8)]):
        add(f"column_{k}", box((x - 0.15, 0, z - 0.15), (x + 0.15, H, z + 0.15)), (0.8, 0.8, 0.78))
    sofa = union(box((7.1, 0, 2.0), (7.9, 0.42, 4.0)), box((7.7, 0.42, 2.0), (7.95, 0.85, 4.0)),
                 box((7.1, 0.42, 2.0), (7.7, 0.62, 2.2)), box((7.1, 0.42, 3.8), (7.7, 0.62, 4.0)))
    add("sofa", sofa, (0.25, 0.35, 0.6))
    add("low_table", union(box((6.3, 0.35, 2.6), (6.9, 0.4, 3.4)),
                           box((6.35, 0, 2.65), (6.85, 0.35, 3.35))), (0.4, 0.28, 0.18))

    lights = [
        {"type": "point", "position": [2.2, 2.6, 2.0], "intensity": [6, 5.6, 5]},
        {"type": "point", "position": [5.4, 2.6, 4.2], "intensity": [6, 5.6, 5]},
        {"type": "spot", "position": [6.5, 2.8, 3.0], "direction": [0.4, -1, 0],
         "intensity": [8, 8, 8], "inner_deg": 25, "outer_deg": 40},
    ]
    scene = {
        "name": "furnished-room",
        "unit_mm": 1000,
        "patches": {"target": 50000},
        "objects": objects,
        "lights": lights,
        "camera": {"position": [4.0, 1.7, 5.8], "target": [3.0, 0.8, 1.5], "fov_deg": 60},
    }
    with open(os.path.join(HERE, "furnished-room.json"), "w") as out:
        json.dump(scene, out, indent=1)
        out.write("\n")
    print(f"{len(objects)} objects")


if __name__ == "__main__":
    main()
