"""The HTTP client: scenes, relights, renders, exports, uploads and jobs (docs/api.md)."""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import (
    IO,
    Any,
    Callable,
    Dict,
    Iterable,
    List,
    Mapping,
    Optional,
    Sequence,
    Tuple,
    Union,
)
from urllib.parse import quote

import numpy as np
import numpy.typing as npt
import requests

from . import _export, _images
from ._errors import JobFailed, TransluxError
from ._stream import Stream, stream_url

Json = Dict[str, Any]
Lights = Sequence[Mapping[str, Any]]
Materials = Mapping[str, Any]
#: A file to upload: a path, or ``(name, bytes)``.
FileLike = Union[str, "os.PathLike[str]", Tuple[str, bytes]]
ProgressArg = Union[None, bool, Callable[[Json], None]]

_FINAL = ("done", "failed", "cancelled")


def _body(lights: Optional[Lights], materials: Optional[Materials], fields: Mapping[str, Any]) -> Json:
    """A relight/render body: the given fields, those left ``None`` left out."""
    body: Json = {k: v for k, v in fields.items() if v is not None}
    if lights is not None:
        body["lights"] = [dict(light) for light in lights]
    if materials is not None:
        body["materials"] = dict(materials)
    return body


def _server_timing(value: Optional[str]) -> Dict[str, float]:
    """``Server-Timing: queue;dur=0.1, solve;dur=2.3`` as ``{"queue": 0.1, "solve": 2.3}``."""
    out: Dict[str, float] = {}
    for item in (value or "").split(","):
        name, _, rest = item.strip().partition(";")
        for param in rest.split(";"):
            key, _, number = param.strip().partition("=")
            if key == "dur" and name:
                try:
                    out[name] = float(number)
                except ValueError:
                    pass
    return out


@dataclass
class RelightResult:
    """The answer of ``POST /api/v1/scenes/{id}/relight``.

    Attributes:
        radiance: ``float32`` (vertices, 3): linear outgoing radiance B/pi (W m^-2 sr^-1)
            per vertex of the scene's mesh (``Scene.mesh()``), in its vertex order.
        stats: the relight's statistics. From a JSON answer (``binary=False``), the server's
            whole ``stats`` object (``solver``, ``iterations``, ``residual``, ``converged``,
            ``ms``, ...; docs/api.md). From a binary answer (the default), what its headers
            carry: ``ms``, ``direct_ms``, ``solve_ms``, ``queue_ms`` from ``Server-Timing``
            and ``auto_exposure`` from ``X-Auto-Exposure`` when present.
        timing: the ``Server-Timing`` durations in milliseconds by name (``queue``,
            ``direct``, ``solve``, ``total``).
    """

    radiance: npt.NDArray[np.float32]
    stats: Json
    timing: Dict[str, float] = field(default_factory=dict)

    @property
    def vertex_count(self) -> int:
        """Vertices answered."""
        return int(self.radiance.shape[0])


@dataclass
class Mesh:
    """The viewer mesh of a scene (``GET /api/v1/scenes/{id}/mesh``).

    Attributes:
        positions: ``float32`` (vertices, 3), scene units.
        normals: ``float32`` (vertices, 3), unit vectors.
        indices: ``int64`` (triangles, 3); triangle k is patch k.
        objects: ``name``, ``first_triangle``, ``triangle_count`` of each object.
    """

    positions: npt.NDArray[np.float32]
    normals: npt.NDArray[np.float32]
    indices: npt.NDArray[np.int64]
    objects: List[Json]

    def triangles_of(self, name: str) -> npt.NDArray[np.int64]:
        """The (triangles, 3) vertex indices of object ``name``."""
        for obj in self.objects:
            if obj["name"] == name:
                first, count = int(obj["first_triangle"]), int(obj["triangle_count"])
                return self.indices[first : first + count]
        names = ", ".join(str(o["name"]) for o in self.objects)
        raise KeyError(f"no object {name!r} in the mesh (its objects are {names})")

    def vertices_of(self, name: str) -> npt.NDArray[np.int64]:
        """The sorted indices of the vertices object ``name``'s triangles use: index a
        relight's ``radiance`` with them for that object's colours."""
        return np.unique(self.triangles_of(name).reshape(-1))


class Job:
    """A precompute job (an upload's, or a re-simulation's): ``GET /api/v1/jobs/{id}``.

    ``record`` is the server's last known record: ``state`` (``queued``, ``running``,
    ``done``, ``failed``, ``cancelled``), ``stage``, ``stage_percent``, ``percent``,
    ``error``, ``result``, ... (docs/team.md).
    """

    def __init__(self, client: "Client", record: Json) -> None:
        self.client = client
        self.record: Json = dict(record)

    @property
    def id(self) -> str:
        """The job's id (``j`` and 20 hex digits)."""
        return str(self.record["id"])

    @property
    def state(self) -> str:
        """``queued``, ``running``, ``done``, ``failed`` or ``cancelled``."""
        return str(self.record["state"])

    @property
    def percent(self) -> float:
        """Percent of the whole job done."""
        return float(self.record.get("percent") or 0.0)

    @property
    def done(self) -> bool:
        """Whether the job has ended (done, failed or cancelled)."""
        return self.state in _FINAL

    def refresh(self) -> "Job":
        """Reads the record again."""
        self.record = self.client.get_json(f"/api/v1/jobs/{quote(self.id, safe='')}")
        return self

    def cancel(self) -> "Job":
        """Cancels the job (``DELETE /api/v1/jobs/{id}``): a queued one at once, a running one
        at its next check."""
        r = self.client.request("DELETE", f"/api/v1/jobs/{quote(self.id, safe='')}",
                                accept="application/json")
        self.record = r.json()
        return self

    def wait(self, progress: ProgressArg = True, timeout: Optional[float] = None) -> "Job":
        """Follows the job to its end and returns it; shows its progress on the way.

        The progress comes from the job's Server-Sent Events
        (``GET /api/v1/jobs/{id}/events``), one per change of stage or whole stage percent.
        ``progress``: ``True`` (the default) prints a line per change to standard error
        (``job j01...: form factors 40% (whole job 35%)``); a callable is called with each
        record instead; ``False`` or ``None`` shows nothing.

        Raises :class:`JobFailed` (``code`` ``job_failed`` or ``job_cancelled``, ``message``
        the job's ``error``) when it does not end ``done``, and :class:`TransluxError`
        (``code`` ``timeout``) after ``timeout`` seconds.
        """
        show: Optional[Callable[[Json], None]]
        if progress is True:
            show = _print_progress
        elif callable(progress):
            show = progress
        else:
            show = None
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.done:
            self._follow_events(show, deadline)
            if not self.done:
                # The event stream ended early (a proxy, a restart): read the record.
                self.refresh()
                if show is not None:
                    show(self.record)
                if not self.done:
                    if deadline is not None and time.monotonic() > deadline:
                        raise TransluxError(f"job {self.id} did not end within {timeout} s",
                                            code="timeout")
                    time.sleep(0.5)
        if self.state != "done":
            why = self.record.get("error") or f"the job ended {self.state}"
            raise JobFailed(f"job {self.id} {self.state}: {why}", code=f"job_{self.state}",
                            job=self.record)
        return self

    def _follow_events(self, show: Optional[Callable[[Json], None]],
                       deadline: Optional[float]) -> None:
        read_timeout = None if deadline is None else max(1.0, deadline - time.monotonic())
        r = self.client.request(
            "GET", f"/api/v1/jobs/{quote(self.id, safe='')}/events",
            accept="text/event-stream", stream=True, timeout=read_timeout,
        )
        try:
            event: Optional[str] = None
            data: List[str] = []
            for raw in r.iter_lines(decode_unicode=False):
                line = raw.decode("utf-8", "replace")
                if line == "":
                    if data:
                        record = json.loads("\n".join(data))
                        if isinstance(record, dict) and "state" in record:
                            self.record = record
                            if show is not None:
                                show(record)
                    if event in _FINAL:
                        return
                    event, data = None, []
                elif line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].lstrip(" "))
                if deadline is not None and time.monotonic() > deadline:
                    raise TransluxError(f"job {self.id} did not end in time", code="timeout")
        except requests.exceptions.RequestException:
            return  # the stream broke off or went quiet: the caller reads the record
        finally:
            r.close()

    def scene(self) -> "Scene":
        """The scene the finished job serves."""
        return self.client.scene(str(self.record["scene"]))

    def __repr__(self) -> str:
        return f"Job({self.id!r}, state={self.state!r}, percent={self.percent:.0f})"


def _print_progress(record: Json) -> None:
    stage = record.get("stage") or record.get("state")
    print(
        f"job {record.get('id')}: {stage} {float(record.get('stage_percent') or 0):.0f}%"
        f" (whole job {float(record.get('percent') or 0):.0f}%, {record.get('state')})",
        file=sys.stderr,
        flush=True,
    )


class Scene:
    """One served scene; :meth:`Client.scene` and :meth:`Client.scenes` make them.

    ``info`` is the scene's entry in the list (``id``, ``name``, ``patches``, ``vertices``,
    ``objects``, ``frames``) or its detail (``GET /api/v1/scenes/{id}``: objects and their
    materials, default lights and camera, ``unit_mm``, ...), whichever was read last.
    """

    def __init__(self, client: "Client", info: Json) -> None:
        self.client = client
        self.info: Json = dict(info)
        self._detail: Optional[Json] = None
        self._meshes: Dict[Optional[int], Mesh] = {}

    @property
    def id(self) -> str:
        """The scene id (its bundle's folder name)."""
        return str(self.info["id"])

    @property
    def name(self) -> str:
        """The scene's name in its manifest."""
        return str(self.info.get("name", self.id))

    @property
    def _path(self) -> str:
        return f"/api/v1/scenes/{quote(self.id, safe='')}"

    def detail(self, frame: Optional[int] = None, refresh: bool = False) -> Json:
        """The scene's detail (``GET /api/v1/scenes/{id}``; ``frame`` for an animated scene's
        frame), read once and kept unless ``refresh``."""
        if frame is not None:
            return self.client.get_json(self._path, params={"frame": frame})
        if self._detail is None or refresh:
            self._detail = self.client.get_json(self._path)
            self.info = dict(self._detail)
        return self._detail

    @property
    def objects(self) -> List[str]:
        """The objects' names: the keys of a relight's ``materials``."""
        return [str(o["name"]) for o in self.detail()["objects"]]

    @property
    def lights(self) -> List[Json]:
        """The lights a relight without ``lights`` uses."""
        return list(self.detail()["lights"])

    def mesh(self, frame: Optional[int] = None) -> Mesh:
        """The viewer mesh (kept after the first call): vertex order of every relight."""
        if frame not in self._meshes:
            params = None if frame is None else {"frame": frame}
            m = self.client.get_json(self._path + "/mesh", params=params)
            self._meshes[frame] = Mesh(
                positions=np.asarray(m["positions"], np.float32).reshape(-1, 3),
                normals=np.asarray(m["normals"], np.float32).reshape(-1, 3),
                indices=np.asarray(m["indices"], np.int64).reshape(-1, 3),
                objects=list(m["objects"]),
            )
        return self._meshes[frame]

    def relight(
        self,
        lights: Optional[Lights] = None,
        materials: Optional[Materials] = None,
        *,
        components: Optional[str] = None,
        solver: Optional[str] = None,
        frame: Optional[int] = None,
        lamp_walks: Optional[int] = None,
        direct_at: Optional[str] = None,
        binary: bool = True,
        **extra: Any,
    ) -> RelightResult:
        """Relights the scene: ``POST /api/v1/scenes/{id}/relight``.

        Args:
            lights: the lights (``{"type": "point", "position": [x, y, z], "intensity":
                [r, g, b]}``, spot, directional, environment; docs/api.md); ``None``: the
                scene's default lights; ``[]``: none (only emitters shine).
            materials: overrides by object name, e.g. ``{"tall_block": {"type":
                "translucent", "profile": {"type": "dipole", "preset": "marble", "scale": 2}}}``.
            components, solver, frame, lamp_walks, direct_at: as in the API; ``None`` leaves
                the field out (the server's default).
            binary: ask for the binary f32 answer (the default: smaller and faster to read;
                ``stats`` then holds only what the headers say) or the JSON one (``False``:
                the full ``stats``).
            extra: further body fields, sent as given (the server refuses unknown ones).
        """
        body = _body(lights, materials, dict(components=components, solver=solver,
                                             frame=frame, lamp_walks=lamp_walks,
                                             direct_at=direct_at, **extra))
        accept = "application/octet-stream" if binary else "application/json"
        r = self.client.request("POST", self._path + "/relight", json=body, accept=accept)
        timing = _server_timing(r.headers.get("Server-Timing"))
        if not binary:
            answer = r.json()
            radiance = np.asarray(answer["radiance"], np.float32).reshape(-1, 3)
            return RelightResult(radiance=radiance, stats=dict(answer["stats"]), timing=timing)
        count = int(r.headers.get("X-Vertex-Count", len(r.content) // 12))
        if len(r.content) != 12 * count:
            raise TransluxError(
                f"the binary answer is {len(r.content)} bytes, not 12 x {count} vertices",
                code="bad_answer",
            )
        radiance = np.frombuffer(r.content, "<f4").astype(np.float32).reshape(count, 3)
        stats: Json = {}
        for name, key in (("total", "ms"), ("direct", "direct_ms"), ("solve", "solve_ms"),
                          ("queue", "queue_ms")):
            if name in timing:
                stats[key] = timing[name]
        if "X-Auto-Exposure" in r.headers:
            stats["auto_exposure"] = float(r.headers["X-Auto-Exposure"])
        return RelightResult(radiance=radiance, stats=stats, timing=timing)

    def render_bytes(
        self,
        lights: Optional[Lights] = None,
        materials: Optional[Materials] = None,
        *,
        format: str = "png",
        **fields: Any,
    ) -> Tuple[bytes, Mapping[str, str]]:
        """The render route's file and headers as they come (``format``: ``png`` or
        ``exr``; the headers' names case-insensitive); the fields as in :meth:`render`."""
        accept = {"png": "image/png", "exr": "image/x-exr"}.get(format)
        if accept is None:
            raise ValueError(f"format must be 'png' or 'exr' (got {format!r})")
        body = _body(lights, materials, fields)
        r = self.client.request("POST", self._path + "/render", json=body, accept=accept)
        return r.content, r.headers

    def render(
        self,
        lights: Optional[Lights] = None,
        materials: Optional[Materials] = None,
        *,
        width: Optional[int] = None,
        height: Optional[int] = None,
        camera: Optional[Mapping[str, Any]] = None,
        exposure: Union[None, float, str] = None,
        tone: Optional[str] = None,
        background: Optional[Sequence[float]] = None,
        format: str = "png",
        **fields: Any,
    ) -> npt.NDArray[Any]:
        """Renders a picture: ``POST /api/v1/scenes/{id}/render``, decoded into an array.

        ``format="png"`` (the default) gives ``uint8`` (height, width, 3), sRGB display
        values after ``exposure`` (EV, or ``"auto"``, the server's default) and ``tone``
        (``srgb`` or ``filmic``). ``format="exr"`` gives ``float32`` (height, width, 3) linear
        radiance B/pi (scaled by 2**exposure only for a numeric exposure). ``width`` and
        ``height`` default to the server's 800 x 600; ``camera`` to the scene's. Other
        fields (``components``, ``solver``, ``frame``, ``direct_at``, ``cull_backfaces``,
        ``specular``, ...) go into the body as given.
        """
        data, _ = self.render_bytes(
            lights, materials, format=format,
            **dict(width=width, height=height, camera=None if camera is None else dict(camera),
                   exposure=exposure, tone=tone,
                   background=None if background is None else list(background), **fields),
        )
        if format == "png":
            pixels = _images.decode_png(data)
            return pixels[:, :, :3] if pixels.shape[2] >= 3 else pixels
        image, _names = _images.decode_exr(data)
        return image[:, :, :3]

    def stream(
        self,
        format: str = "f32",
        *,
        timeout: Optional[float] = 60.0,
    ) -> Stream:
        """Opens the scene's WebSocket relight stream (docs/stream.md) with frames in
        ``format`` (``f32``, ``f16`` or ``srgb8``); see :class:`Stream`. ``timeout``: seconds
        to wait for any one message."""
        url = stream_url(self.client.url, quote(self.id, safe=""), {"format": format})
        return Stream(url, headers=self.client._ws_headers(), timeout=timeout)

    def export(
        self,
        path: Union[str, "os.PathLike[str]"],
        lights: Optional[Lights] = None,
        materials: Optional[Materials] = None,
        *,
        exposure: Union[float, str] = 0.0,
        tone: str = "srgb",
        frame: Optional[int] = None,
        **fields: Any,
    ) -> Path:
        """Relights the scene and writes the mesh with baked colours to ``path``: ``.glb``
        (binary glTF: linear colours after exposure and tone curve, metres, one node per
        object) or ``.ply`` (8-bit sRGB colours, scene units), the layout of
        ``translux-server export``. The server has no export route: the file is written
        here from the mesh and the binary relight.

        ``exposure``: EV stops (default 0), or ``"auto"``: the server's automatic exposure
        for this relight (asked with ``direct_at="pixel"``, which reports it). Other fields
        as in :meth:`relight`. Returns the path written.
        """
        out = Path(path)
        kind = out.suffix.lower()
        if kind not in (".glb", ".ply"):
            raise ValueError(f"export writes .glb or .ply files (got {out.name!r})")
        result = self.relight(lights, materials, frame=frame, **fields)
        if exposure == "auto":
            probe = dict(fields, direct_at="pixel")
            ev = self.relight(lights, materials, frame=frame, **probe).stats.get("auto_exposure")
            exposure = float(ev if ev is not None else 0.0)
        elif isinstance(exposure, str):
            raise ValueError(f"exposure must be a number or 'auto' (got {exposure!r})")
        ev = float(exposure)
        colours = _export.tone_curve(result.radiance * np.float32(2.0 ** ev), tone)
        mesh = self.mesh(frame)
        unit_mm = float(self.detail(frame).get("unit_mm", 1000.0))
        if kind == ".glb":
            data = _export.glb_bytes(mesh.positions, mesh.normals, mesh.indices, colours,
                                     mesh.objects, unit_mm)
        else:
            data = _export.ply_bytes(mesh.positions, mesh.normals, mesh.indices, colours,
                                     ev, tone, unit_mm)
        out.write_bytes(data)
        return out

    def __repr__(self) -> str:
        return f"Scene({self.id!r})"


class Client:
    """A connection to a translux server.

    Args:
        url: the server's base URL, e.g. ``http://127.0.0.1:8080``.
        token: a bearer token (docs/team.md), sent as ``Authorization: Bearer TOKEN`` on every
            request and on the stream's WebSocket; ``None`` for a server without tokens.
        timeout: seconds to wait for an answer (relights of large scenes can take a while).
        client_id: sent as ``X-Client-Id`` so all your scripts share one turn in the server's
            fair queue (ignored by a server with tokens: there the token counts).
        session: a ``requests.Session`` to use (proxies, certificates, retries).

    Every method raises :class:`TransluxError` with the server's ``status``, ``code`` and
    ``message`` when the server answers an error.
    """

    def __init__(
        self,
        url: str,
        token: Optional[str] = None,
        *,
        timeout: Optional[float] = 300.0,
        client_id: Optional[str] = None,
        session: Optional[requests.Session] = None,
    ) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.client_id = client_id
        self.session = session if session is not None else requests.Session()

    def _headers(self, accept: Optional[str]) -> Dict[str, str]:
        h: Dict[str, str] = {}
        if accept is not None:
            h["Accept"] = accept
        if self.token is not None:
            h["Authorization"] = f"Bearer {self.token}"
        if self.client_id is not None:
            h["X-Client-Id"] = self.client_id
        return h

    def _ws_headers(self) -> List[str]:
        return [f"{k}: {v}" for k, v in self._headers(None).items()]

    def request(
        self,
        method: str,
        path: str,
        *,
        json: Optional[Any] = None,
        accept: Optional[str] = None,
        params: Optional[Mapping[str, Any]] = None,
        files: Optional[Any] = None,
        data: Optional[Any] = None,
        stream: bool = False,
        timeout: Optional[float] = None,
    ) -> requests.Response:
        """One request to ``path`` (under the base URL) with the client's token; the raw
        ``requests.Response``. A ``json`` body is sent as ``application/json``. Raises
        :class:`TransluxError` for a 4xx/5xx answer, with ``code`` ``connection`` when the
        server cannot be reached and ``timeout`` when it does not answer in time."""
        try:
            r = self.session.request(
                method,
                self.url + path,
                json=json,
                headers=self._headers(accept),
                params=params,
                files=files,
                data=data,
                stream=stream,
                timeout=timeout if timeout is not None else self.timeout,
            )
        except requests.exceptions.Timeout as e:
            raise TransluxError(f"no answer from {self.url} in time: {e}", code="timeout") from None
        except requests.exceptions.ConnectionError as e:
            raise TransluxError(f"cannot reach {self.url}: {e}", code="connection") from None
        if r.status_code >= 400:
            body = r.content
            r.close()
            raise TransluxError.from_answer(r.status_code, body, r.headers)
        return r

    def get_json(self, path: str, params: Optional[Mapping[str, Any]] = None) -> Json:
        """``GET path`` answered as JSON."""
        answer: Json = self.request("GET", path, accept="application/json", params=params).json()
        return answer

    def scenes(self) -> List[Scene]:
        """The scenes served (``GET /api/v1/scenes``), each with its list entry as ``info``."""
        return [Scene(self, s) for s in self.get_json("/api/v1/scenes")["scenes"]]

    def scene(self, id: str) -> Scene:
        """One scene, its detail read (``GET /api/v1/scenes/{id}``): a 404
        :class:`TransluxError` naming the scenes served if there is no such scene."""
        scene = Scene(self, {"id": id})
        scene.detail()
        return scene

    def health(self) -> Json:
        """``GET /healthz``: backend, each scene's state, memory, queue."""
        return self.get_json("/healthz")

    def whoami(self) -> Json:
        """``GET /api/v1/whoami``: the token's ``name``, ``role`` and ``auth``."""
        return self.get_json("/api/v1/whoami")

    def jobs(self) -> List[Job]:
        """Your jobs, newest first (an admin sees all): ``GET /api/v1/jobs``."""
        return [Job(self, j) for j in self.get_json("/api/v1/jobs")["jobs"]]

    def job(self, id: str) -> Job:
        """One job's record."""
        return Job(self, self.get_json(f"/api/v1/jobs/{quote(id, safe='')}"))

    def upload(
        self,
        files: Iterable[FileLike] = (),
        scene: Union[None, str, "os.PathLike[str]", Mapping[str, Any], Tuple[str, bytes]] = None,
        *,
        id: Optional[str] = None,
        patches: Optional[int] = None,
        max_edge: Optional[float] = None,
    ) -> Job:
        """Uploads a scene to be precomputed and served (``POST /api/v1/scenes``, editor
        role); returns its :class:`Job` (call ``wait()``).

        Args:
            files: the mesh files the scene names (``.obj``, ``.ply``, ``.gltf`` with its
                ``.bin`` buffers, ``.glb``, ``.mtl``): paths, or ``(name, bytes)``. A single
                ``.json`` among them is taken as the scene file when ``scene`` is not given.
            scene: the scene file: a path, ``(name, bytes)``, or a dict (sent as
                ``<id or "scene">.json``).
            id: the scene id to serve it under (the server's default: the scene file's stem).
            patches, max_edge: override the scene file's density.
        """
        parts: List[Tuple[str, Tuple[str, bytes]]] = []
        scene_part: Optional[Tuple[str, bytes]] = None
        for f in files:
            name, content = _read_file(f)
            if scene is None and scene_part is None and name.lower().endswith(".json"):
                scene_part = (name, content)
            else:
                parts.append(("mesh", (name, content)))
        if scene is not None:
            if isinstance(scene, Mapping):
                scene_part = (f"{id or 'scene'}.json", json.dumps(scene).encode())
            else:
                scene_part = _read_file(scene)
        if scene_part is None:
            raise ValueError("upload needs a scene file: pass scene=... or a .json in files")
        form: Dict[str, str] = {}
        if id is not None:
            form["id"] = id
        if patches is not None:
            form["patches"] = str(int(patches))
        if max_edge is not None:
            form["max_edge"] = repr(float(max_edge))
        multipart: List[Tuple[str, Any]] = [("scene", scene_part)] + list(parts)
        r = self.request("POST", "/api/v1/scenes", files=multipart, data=form,
                         accept="application/json")
        return Job(self, r.json())

    def __repr__(self) -> str:
        return f"Client({self.url!r})"


def _read_file(f: Union[FileLike, IO[bytes]]) -> Tuple[str, bytes]:
    if isinstance(f, tuple):
        return str(f[0]), bytes(f[1])
    p = Path(os.fspath(f))  # type: ignore[arg-type]
    return p.name, p.read_bytes()
