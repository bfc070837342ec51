"""Relit meshes as files: binary glTF 2.0 (``.glb``) and binary PLY, written with numpy.

The layout follows ``translux-server export`` (docs/viewer.md, ``engine/src/export.rs``):

- colours are ``tone(L * 2**exposure)`` per channel (``srgb``: clamp to [0, 1]; ``filmic``:
  the ACES fit of the render route);
- ``.glb``: one mesh and one node per object, named after it, each with its own vertices
  (those its triangles use, in ascending order); positions in metres (scene units times
  ``unit_mm / 1000``); ``COLOR_0`` float RGB in linear space (no sRGB encoding); a white,
  fully rough, unlit (``KHR_materials_unlit``) material;
- ``.ply``: the whole mesh in scene units, ``uchar`` colours sRGB-encoded (the pixel values a
  render shows).
"""

from __future__ import annotations

import json
import struct
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]


def tone_curve(x: F32, tone: str) -> F32:
    """Exposed linear radiance to linear display values in [0, 1]: ``srgb`` clamps,
    ``filmic`` is the ACES fit x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14)."""
    x = np.where(x > 0, x, 0).astype(np.float32)
    if tone == "srgb":
        return np.minimum(x, 1).astype(np.float32)
    if tone == "filmic":
        x = np.minimum(x, 1e4)
        y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
        return np.clip(y, 0, 1).astype(np.float32)
    raise ValueError(f"tone must be 'srgb' or 'filmic' (got {tone!r})")


def srgb_encode(v: F32) -> F32:
    """The sRGB transfer function (IEC 61966-2-1) on values clamped to [0, 1]."""
    v = np.clip(v, 0, 1)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055).astype(
        np.float32
    )


def _unit_normals(n: F32) -> F32:
    length = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.where(length > 0, n / np.where(length > 0, length, 1), [0.0, 0.0, 1.0])
    return out.astype(np.float32)


def glb_bytes(
    positions: F32,
    normals: F32,
    indices: npt.NDArray[Any],
    colours: F32,
    objects: Sequence[Dict[str, Any]],
    unit_mm: float,
) -> bytes:
    """A ``.glb`` of the mesh with linear ``colours`` (already exposed and tone mapped)."""
    scale = np.float32(unit_mm / 1000.0)
    normals = _unit_normals(normals)
    chunks: Dict[str, List[bytes]] = {"pos": [], "nrm": [], "col": [], "idx": []}
    parts: List[Optional[Tuple[int, int, Any, Any]]] = []
    for obj in objects:
        first, count = int(obj["first_triangle"]), int(obj["triangle_count"])
        tris = indices[first : first + count].astype(np.int64)
        if count == 0:
            parts.append(None)
            continue
        used, rebased = np.unique(tris.reshape(-1), return_inverse=True)
        pos = (positions[used] * scale).astype("<f4")
        chunks["pos"].append(pos.tobytes())
        chunks["nrm"].append(normals[used].astype("<f4").tobytes())
        chunks["col"].append(colours[used].astype("<f4").tobytes())
        chunks["idx"].append(rebased.astype("<u4").tobytes())
        parts.append((len(used), 3 * count, pos.min(axis=0), pos.max(axis=0)))

    views: List[Dict[str, Any]] = []
    accessors: List[Dict[str, Any]] = []
    blob = bytearray()
    offsets: Dict[str, List[int]] = {}
    for key in ("pos", "nrm", "col", "idx"):
        offsets[key] = []
        for c in chunks[key]:
            offsets[key].append(len(views))
            target = 34963 if key == "idx" else 34962
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(c),
                          "target": target})
            blob += c
    meshes: List[Dict[str, Any]] = []
    nodes: List[Dict[str, Any]] = []
    k = 0
    for obj, part in zip(objects, parts):
        name = str(obj["name"])
        if part is None:
            nodes.append({"name": name})
            continue
        nv, ni, lo, hi = part
        a = len(accessors)
        accessors += [
            {"bufferView": offsets["pos"][k], "componentType": 5126, "count": nv,
             "type": "VEC3", "min": [float(x) for x in lo], "max": [float(x) for x in hi]},
            {"bufferView": offsets["nrm"][k], "componentType": 5126, "count": nv,
             "type": "VEC3"},
            {"bufferView": offsets["col"][k], "componentType": 5126, "count": nv,
             "type": "VEC3"},
            {"bufferView": offsets["idx"][k], "componentType": 5125, "count": ni,
             "type": "SCALAR"},
        ]
        meshes.append({"name": name, "primitives": [{
            "attributes": {"POSITION": a, "NORMAL": a + 1, "COLOR_0": a + 2},
            "indices": a + 3, "material": 0, "mode": 4}]})
        nodes.append({"name": name, "mesh": len(meshes) - 1})
        k += 1
    doc: Dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "translux Python client"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes)))}],
        "nodes": nodes,
        "materials": [{
            "name": "baked",
            "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                     "roughnessFactor": 1.0},
            "doubleSided": False,
            "extensions": {"KHR_materials_unlit": {}},
        }],
    }
    if meshes:
        doc.update(meshes=meshes, accessors=accessors, bufferViews=views,
                   buffers=[{"byteLength": len(blob)}])
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    out = bytearray()
    total = 12 + 8 + len(text) + (8 + len(blob) if meshes else 0)
    out += struct.pack("<4sII", b"glTF", 2, total)
    out += struct.pack("<I4s", len(text), b"JSON") + text
    if meshes:
        out += struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob)
    return bytes(out)


def ply_bytes(
    positions: F32,
    normals: F32,
    indices: npt.NDArray[Any],
    colours: F32,
    exposure: float,
    tone: str,
    unit_mm: float,
) -> bytes:
    """A binary PLY with ``uchar`` sRGB-encoded colours, positions in scene units."""
    n, f = len(positions), len(indices)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment translux: colours are sRGB-encoded B/pi, exposure {exposure} EV, tone {tone}\n"
        f"comment translux: positions in scene units, 1 unit = {unit_mm} mm\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {f}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertex = np.zeros(n, [("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
    vertex["p"] = positions
    vertex["n"] = normals
    vertex["c"] = np.floor(np.clip(srgb_encode(colours), 0, 1) * 255 + 0.5).astype(np.uint8)
    face = np.zeros(f, [("k", "u1"), ("i", "<i4", 3)])
    face["k"] = 3
    face["i"] = indices
    return header.encode() + vertex.tobytes() + face.tobytes()
