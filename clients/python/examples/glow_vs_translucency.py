"""Plot the glow on a translucent object's far side against its translucency.

A translucent object lit from one side glows on the other: light enters, scatters inside
and leaves elsewhere. This script relights the scene with the object's dipole profile at
several mean-free-path scales (``"scale": s``, larger is more translucent), takes the mean
radiance of the object's vertices that face away from the light (the far side) and of those
that face it (the lit side), and plots both against the scale with matplotlib.

    translux-server --bundles demo-bundles &          # serves builtin:cornell as "cornell"
    pip install ./clients/python matplotlib
    python3 clients/python/examples/glow_vs_translucency.py --out glow.png

Options: ``--url`` (default http://127.0.0.1:8080), ``--token`` (a team server's token,
or ``TRANSLUX_TOKEN``), ``--scene`` (default cornell), ``--object`` (default tall_block: it
must have been precomputed translucent), ``--scales`` (default 0.25 0.5 1 2 4 8), ``--out``
(a picture file; without it the plot opens in a window).
"""

from __future__ import annotations

import argparse
import os
from typing import Any, Dict, List

import numpy as np

from translux import Client


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--token", default=os.environ.get("TRANSLUX_TOKEN"))
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--object", default="tall_block")
    ap.add_argument("--scales", type=float, nargs="+", default=[0.25, 0.5, 1, 2, 4, 8])
    ap.add_argument("--out", help="write the plot to this file instead of showing it")
    args = ap.parse_args()

    client = Client(args.url, token=args.token)
    scene = client.scene(args.scene)
    detail = scene.detail()
    obj = next(o for o in detail["objects"] if o["name"] == args.object)
    material: Dict[str, Any] = obj["material"]
    if material.get("type") != "translucent":
        raise SystemExit(f"{args.object} is {material.get('type')}, not translucent")
    profile = dict(material["profile"])

    # One point light: the scene's first point light, else one above the scene's centre.
    lights: List[Dict[str, Any]] = [lt for lt in detail["lights"] if lt["type"] == "point"][:1]
    mesh = scene.mesh()
    if not lights:
        top = mesh.positions.max(axis=0)
        centre = mesh.positions.mean(axis=0)
        lights = [{"type": "point", "position": [float(centre[0]), float(top[1]) * 0.9,
                                                 float(centre[2])], "intensity": [1, 1, 1]}]
    light = np.asarray(lights[0]["position"], np.float32)

    # The object's vertices, split by whether their normal faces the light.
    vertices = mesh.vertices_of(args.object)
    to_light = light - mesh.positions[vertices]
    facing = np.einsum("ij,ij->i", mesh.normals[vertices], to_light) > 0
    far, lit = vertices[~facing], vertices[facing]
    print(f"{args.object}: {len(vertices)} vertices, {len(far)} on the far side")

    def luminance(rgb: np.ndarray) -> float:
        return float((rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)).mean())

    far_glow, lit_side = [], []
    for s in args.scales:
        materials = {args.object: {"type": "translucent", "profile": dict(profile, scale=s)}}
        out = scene.relight(lights, materials, binary=False)
        far_glow.append(luminance(out.radiance[far]))
        lit_side.append(luminance(out.radiance[lit]))
        print(f"scale {s:g}: far side {far_glow[-1]:.4f}, lit side {lit_side[-1]:.4f}"
              f" ({out.stats.get('solver')}, {out.stats.get('iterations')} iterations,"
              f" {out.stats.get('ms', 0):.0f} ms)")

    import matplotlib  # only the example needs it

    if args.out:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(args.scales, far_glow, "o-", label="far side (glow)")
    ax.plot(args.scales, lit_side, "s--", label="lit side")
    ax.set_xscale("log", base=2)
    ax.set_xlabel(f"mean free path scale of {profile.get('preset', 'the profile')}")
    ax.set_ylabel("mean luminance of B/π (W·m⁻²·sr⁻¹)")
    ax.set_title(f"{args.scene}: glow on {args.object} against its translucency")
    ax.legend()
    fig.tight_layout()
    if args.out:
        fig.savefig(args.out, dpi=120)
        print(f"wrote {args.out}")
    else:
        plt.show()


if __name__ == "__main__":
    main()
