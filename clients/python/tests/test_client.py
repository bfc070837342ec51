"""Tests of the translux client against a running server.

Run by ``tests/tests/it/python_client.rs`` (``cargo test``), which starts a team server on a
copy of the small Cornell bundle and sets:

- ``TRANSLUX_URL``: the server's base URL;
- ``TRANSLUX_VIEWER_TOKEN``, ``TRANSLUX_EDITOR_TOKEN``: tokens of those roles;
- ``TRANSLUX_SCENE``: the Cornell scene's id.

By hand: ``TRANSLUX_URL=... python3 -m unittest -v clients/python/tests/test_client.py``.
The reference answers are fetched with plain ``requests``, not through the client.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
import unittest
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import requests

import translux
from translux import Client, TransluxError

URL = os.environ.get("TRANSLUX_URL", "http://127.0.0.1:8080")
VIEWER = os.environ.get("TRANSLUX_VIEWER_TOKEN")
EDITOR = os.environ.get("TRANSLUX_EDITOR_TOKEN")
SCENE = os.environ.get("TRANSLUX_SCENE", "cornell")

LIGHT = {"type": "point", "position": [0.05, 0.5, 0.1], "intensity": [1.0, 0.9, 0.8]}
MARBLE_X2 = {
    "tall_block": {
        "type": "translucent",
        "profile": {"type": "dipole", "preset": "marble", "scale": 2},
    }
}


def raw(method: str, path: str, token: str | None = VIEWER, **kw: Any) -> requests.Response:
    """A request with plain ``requests``: the reference the client is compared with."""
    headers = dict(kw.pop("headers", {}))
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    return requests.request(method, URL + path, headers=headers, timeout=120, **kw)


def json_relight(body: Dict[str, Any]) -> Dict[str, Any]:
    r = raw("POST", f"/api/v1/scenes/{SCENE}/relight", json=body,
            headers={"Accept": "application/json"})
    assert r.status_code == 200, r.text
    answer: Dict[str, Any] = r.json()
    return answer


class ClientTest(unittest.TestCase):
    client: Client

    @classmethod
    def setUpClass(cls) -> None:
        cls.client = Client(URL, token=VIEWER)

    def test_scenes_and_scene_detail(self) -> None:
        scenes = self.client.scenes()
        listed = raw("GET", "/api/v1/scenes").json()["scenes"]
        self.assertEqual([s.id for s in scenes], [s["id"] for s in listed])
        scene = self.client.scene(SCENE)
        self.assertEqual(scene.id, SCENE)
        self.assertIn("tall_block", scene.objects)
        mesh = scene.mesh()
        self.assertEqual(mesh.positions.shape, (scene.info["vertices"], 3))
        self.assertEqual(mesh.indices.shape, (scene.info["triangles"], 3))
        with self.assertRaises(TransluxError) as e:
            self.client.scene("kitchen")
        self.assertEqual((e.exception.status, e.exception.code), (404, "not_found"))
        self.assertIn('no scene "kitchen"', e.exception.message)

    def test_relight_arrays_equal_the_json_route(self) -> None:
        scene = self.client.scene(SCENE)
        # Direct light: no solve, so every answer to the request is the same numbers, and the
        # JSON's shortest decimal forms read back to the same f32 values.
        body: Dict[str, Any] = {"lights": [LIGHT], "components": "direct"}
        want = np.asarray(json_relight(body)["radiance"], np.float32).reshape(-1, 3)
        got = scene.relight([LIGHT], components="direct")
        self.assertEqual(got.radiance.dtype, np.float32)
        self.assertEqual(got.radiance.shape, (scene.info["vertices"], 3))
        self.assertGreater(float(want.max()), 0.0)
        np.testing.assert_array_equal(got.radiance, want)
        self.assertIn("ms", got.stats)
        as_json = scene.relight([LIGHT], components="direct", binary=False)
        np.testing.assert_array_equal(as_json.radiance, want)
        self.assertEqual(as_json.stats["components"], "direct")

        # Full transport with a material override: the iterative solve warm-starts from the
        # last answer for the same request, which already meets the tolerance, so asking
        # again answers the same solution.
        body = {"lights": [LIGHT], "materials": MARBLE_X2, "solver": "iterative"}
        json_relight(body)
        reference = json_relight(body)
        self.assertEqual(reference["stats"]["iterations"], 0, reference["stats"])
        want = np.asarray(reference["radiance"], np.float32).reshape(-1, 3)
        got = scene.relight([LIGHT], MARBLE_X2, solver="iterative")
        np.testing.assert_allclose(got.radiance, want, rtol=1e-6, atol=1e-7)
        full = scene.relight([LIGHT], MARBLE_X2, solver="iterative", binary=False)
        self.assertEqual(full.stats["solver"] in ("jacobi", "gauss_seidel", "bicgstab"), True)
        np.testing.assert_allclose(full.radiance, want, rtol=1e-6, atol=1e-7)

    def test_server_errors_carry_the_servers_message(self) -> None:
        bad = {"type": "point", "position": [0, 0.5, 0], "intensity": [1, -1, 1]}
        r = raw("POST", f"/api/v1/scenes/{SCENE}/relight", json={"lights": [bad]})
        self.assertEqual(r.status_code, 400)
        with self.assertRaises(TransluxError) as e:
            self.client.scene(SCENE).relight([bad])
        self.assertEqual(e.exception.status, 400)
        self.assertEqual(e.exception.code, r.json()["error"]["code"])
        self.assertEqual(e.exception.message, r.json()["error"]["message"])
        self.assertIn("lights[0].intensity[1]", str(e.exception))

    def test_an_unknown_or_missing_token_raises_the_401s_message(self) -> None:
        for token in ("tlx_expired_99999999999999999999999999999", None):
            r = raw("GET", "/api/v1/scenes", token=token)
            self.assertEqual(r.status_code, 401)
            message = r.json()["error"]["message"]
            client = Client(URL, token=token)
            with self.assertRaises(TransluxError) as e:
                client.scenes()
            self.assertEqual(e.exception.status, 401)
            self.assertEqual(e.exception.code, "unauthorized")
            self.assertEqual(e.exception.message, message)
            # The stream is refused before the upgrade, with the same answer.
            with self.assertRaises(TransluxError) as e:
                translux.Scene(client, {"id": SCENE}).stream()
            self.assertEqual((e.exception.status, e.exception.message), (401, message))
        # A viewer may not upload: 403 naming the role.
        with self.assertRaises(TransluxError) as e:
            self.client.upload(scene={"objects": []}, id="nope")
        self.assertEqual((e.exception.status, e.exception.code), (403, "forbidden"))
        self.assertIn("editor", e.exception.message)

    def test_a_stream_yields_frames_in_order(self) -> None:
        scene = self.client.scene(SCENE)
        sent: List[Dict[str, Any]] = []
        with scene.stream() as stream:
            self.assertEqual(stream.vertex_count, scene.info["vertices"])
            for k in range(8):
                light = dict(LIGHT, position=[-0.2 + 0.05 * k, 0.5, 0.1])
                sent.append(light)
                self.assertEqual(stream.relight([light], components="direct"), k + 1)
            frames = list(stream)
        seqs = [f.seq for f in frames]
        self.assertEqual(seqs, sorted(set(seqs)), f"frames out of order: {seqs}")
        self.assertEqual(seqs[-1], 8, seqs)
        # Every request was answered or superseded, and the last frame counts the dropped.
        self.assertEqual(len(frames) + frames[-1].dropped, 8, (seqs, frames[-1].dropped))
        for f in frames:
            self.assertEqual(f.radiance.shape, (scene.info["vertices"], 3))
            self.assertEqual(f.radiance.dtype, np.float32)
            self.assertEqual(f.stats["components"], "direct")
            want = scene.relight([sent[f.seq - 1]], components="direct").radiance
            np.testing.assert_array_equal(f.radiance, want, err_msg=f"frame {f.seq}")

    def test_a_stream_reports_errors_and_goes_on(self) -> None:
        scene = self.client.scene(SCENE)
        with scene.stream(format="f16") as stream:
            bad = dict(LIGHT, intensity=[1, -1, 1])
            seq = stream.relight([bad])
            with self.assertRaises(TransluxError) as e:
                next(stream)
            self.assertEqual((e.exception.seq, e.exception.code), (seq, "invalid"))
            self.assertIn("lights[0].intensity[1]", e.exception.message)
            stream.relight([LIGHT], components="direct")
            (frame,) = list(stream)
        self.assertEqual((frame.seq, frame.format), (seq + 1, "f16"))
        want = scene.relight([LIGHT], components="direct").radiance
        np.testing.assert_allclose(frame.radiance, want, rtol=1e-3, atol=1e-4)

    def test_render_returns_the_asked_size(self) -> None:
        scene = self.client.scene(SCENE)
        png = scene.render([LIGHT], width=64, height=48, exposure=-1.0)
        self.assertEqual((png.shape, png.dtype), ((48, 64, 3), np.uint8))
        self.assertGreater(int(png.max()), 0)
        # The PNG decoder against the server's own bytes: the IHDR size and a plain decode of
        # the first row (filter 0 or 1 or 2 rows only; adaptive filters may pick any).
        data, headers = scene.render_bytes([LIGHT], width=64, height=48, exposure=-1.0)
        self.assertEqual(headers["Content-Type"], "image/png")
        self.assertEqual(struct.unpack(">II", data[16:24]), (64, 48))
        np.testing.assert_array_equal(translux.decode_png(data), png)
        # The linear EXR of the same picture, encoded as the PNG is, gives its pixels.
        exr = scene.render([LIGHT], width=64, height=48, exposure=-1.0, format="exr")
        self.assertEqual((exr.shape, exr.dtype), ((48, 64, 3), np.float32))
        v = np.clip(exr, 0, 1)
        srgb = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
        encoded = np.floor(srgb * 255 + 0.5)
        diff = np.abs(encoded - png.astype(np.float64))
        self.assertLessEqual(float(diff.max()), 1.0)
        with self.assertRaises(TransluxError) as e:
            scene.render(width=0, height=48)
        self.assertEqual((e.exception.status, e.exception.code), (400, "invalid"))

    def test_export_writes_glb_and_ply(self) -> None:
        scene = self.client.scene(SCENE)
        mesh = scene.mesh()
        radiance = scene.relight([LIGHT], components="direct").radiance
        with tempfile.TemporaryDirectory() as tmp:
            glb = scene.export(Path(tmp) / "cornell.glb", [LIGHT], components="direct",
                               exposure=-1.0)
            data = glb.read_bytes()
            magic, version, length = struct.unpack_from("<4sII", data, 0)
            self.assertEqual((magic, version, length), (b"glTF", 2, len(data)))
            (json_len,) = struct.unpack_from("<I", data, 12)
            doc = json.loads(data[20 : 20 + json_len])
            self.assertEqual([n["name"] for n in doc["nodes"]], scene.objects)
            # tall_block's colours: its vertices' radiance, halved, clamped.
            k = scene.objects.index("tall_block")
            prim = doc["meshes"][doc["nodes"][k]["mesh"]]["primitives"][0]
            acc = doc["accessors"][prim["attributes"]["COLOR_0"]]
            view = doc["bufferViews"][acc["bufferView"]]
            start = 20 + json_len + 8 + view["byteOffset"]
            colours = np.frombuffer(data, "<f4", 3 * acc["count"], start).reshape(-1, 3)
            want = np.minimum(radiance[mesh.vertices_of("tall_block")] * 0.5, 1)
            np.testing.assert_allclose(colours, want, rtol=1e-6)
            ply = scene.export(Path(tmp) / "cornell.ply", [LIGHT], components="direct")
            head = ply.read_bytes().split(b"end_header\n")[0].decode()
            self.assertIn(f"element vertex {len(mesh.positions)}", head)
            self.assertIn(f"element face {len(mesh.indices)}", head)

    def test_upload_and_wait_for_the_job(self) -> None:
        editor = Client(URL, token=EDITOR)
        scene_file = {
            "objects": [
                {"name": "floor", "mesh": {"shape": "quad", "size": [2, 2]},
                 "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
                {"name": "cube", "mesh": "cube.obj",
                 "transform": {"scale": 0.2, "translate": [0, 0.2, 0]},
                 "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}},
            ],
            "lights": [{"type": "point", "position": [0, 1.5, 0], "intensity": [5, 5, 5]}],
        }
        cube = "\n".join(
            [f"v {x} {y} {z}" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
            + ["f 1 2 4 3", "f 5 7 8 6", "f 1 5 6 2", "f 3 4 8 7", "f 1 3 7 5", "f 2 6 8 4"]
        ) + "\n"
        # A fresh id per run, so the script can be rerun against one server.
        scene_id = f"pycube{os.getpid()}"
        job = editor.upload([("cube.obj", cube.encode())], scene=scene_file, id=scene_id,
                            patches=150)
        self.assertIn(job.state, ("queued", "running"))
        seen: List[Dict[str, Any]] = []
        job.wait(progress=seen.append, timeout=240)
        self.assertEqual(job.state, "done", job.record)
        self.assertTrue(seen, "wait() showed no progress")
        percents = [float(r["percent"]) for r in seen]
        self.assertEqual(percents, sorted(percents), percents)
        self.assertEqual(seen[-1]["state"], "done")
        served = job.scene()
        self.assertEqual(served.objects, ["floor", "cube"])
        out = served.relight()
        self.assertEqual(out.radiance.shape, (served.info["vertices"], 3))
        self.assertGreater(float(out.radiance.max()), 1e-3)
        # The same id again: the server's 409.
        with self.assertRaises(TransluxError) as e:
            editor.upload([("cube.obj", cube.encode())], scene=scene_file, id=scene_id)
        self.assertEqual((e.exception.status, e.exception.code), (409, "conflict"))

    def test_a_failed_job_raises_with_its_error(self) -> None:
        editor = Client(URL, token=EDITOR)
        job = editor.upload(
            scene={"objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 0.1},
                                "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}]},
            id=f"pyball{os.getpid()}", patches=5000)
        # Cancelled within milliseconds: queued, or running (stopped at its next check,
        # long before a 5000-patch precompute could end).
        job.cancel()
        with self.assertRaises(translux.JobFailed) as e:
            job.wait(progress=False, timeout=60)
        self.assertEqual(e.exception.code, "job_cancelled")
        self.assertEqual(e.exception.job["state"], "cancelled")


if __name__ == "__main__":
    unittest.main()
