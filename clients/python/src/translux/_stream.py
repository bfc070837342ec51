"""The relight stream: ``GET /api/v1/scenes/{id}/stream`` as a WebSocket (docs/stream.md)."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence
from urllib.parse import urlencode

import numpy as np
import numpy.typing as npt
import websocket

from ._errors import TransluxError

#: The binary frame's magic bytes and its format byte per format name.
MAGIC = b"TLXF"
FORMATS = {0: "f32", 1: "f16", 2: "srgb8"}
_DTYPES: Dict[str, "np.dtype[Any]"] = {
    "f32": np.dtype("<f4"),
    "f16": np.dtype("<f2"),
    "srgb8": np.dtype("u1"),
}


@dataclass
class Frame:
    """One computed relight of a stream.

    Attributes:
        seq: the ``seq`` of the request it answers.
        format: ``f32``, ``f16`` or ``srgb8``.
        radiance: (vertices, 3), in the mesh's vertex order: ``float32`` linear radiance B/pi
            for ``f32`` and ``f16`` (halves widened), ``uint8`` display values for ``srgb8``.
        stats: the relight's stats, as the REST route answers them.
        dropped: this connection's requests superseded before being computed, so far.
    """

    seq: int
    format: str
    radiance: npt.NDArray[Any]
    stats: Dict[str, Any] = field(default_factory=dict)
    dropped: int = 0


def decode_frame(data: bytes) -> Frame:
    """A binary stream frame: the 16-byte ``TLXF`` header, then r, g, b per vertex."""
    if len(data) < 16 or data[:4] != MAGIC:
        raise TransluxError("a binary stream frame without the TLXF header", code="bad_frame")
    (seq,) = struct.unpack_from("<Q", data, 4)
    fmt = FORMATS.get(data[12])
    if fmt is None:
        raise TransluxError(f"a stream frame with unknown format {data[12]}", code="bad_frame")
    values = np.frombuffer(data, _DTYPES[fmt], offset=16)
    if values.size % 3:
        raise TransluxError("a stream frame whose values are not r, g, b triples",
                            code="bad_frame")
    colours = values.reshape(-1, 3)
    if fmt != "srgb8":
        colours = colours.astype(np.float32)
    return Frame(seq=int(seq), format=fmt, radiance=colours)


class Stream:
    """A WebSocket relight stream of one scene; ``Scene.stream()`` opens it.

    Send relight requests with :meth:`relight` (each gets a ``seq``), then iterate: each
    item is a :class:`Frame`, in the order computed. The server is *latest wins*: a request
    superseded while it waited is never answered (``Frame.dropped`` counts them), but the
    last one sent always is. Iteration stops once the last request sent has been answered,
    so ``for frame in stream`` after a burst of requests ends with the newest one's frame.
    A request the server refuses raises :class:`TransluxError` (with ``seq``) from the
    iteration; the stream stays open and iteration can go on.

    Use it as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        url: str,
        *,
        headers: Sequence[str],
        timeout: Optional[float],
    ) -> None:
        try:
            self._ws = websocket.create_connection(url, header=list(headers), timeout=timeout)
        except websocket.WebSocketBadStatusException as e:
            body = getattr(e, "resp_body", None) or b""
            if isinstance(body, str):
                body = body.encode()
            raise TransluxError.from_answer(
                e.status_code, body, getattr(e, "resp_headers", None) or {}
            ) from None
        hello = self._next_text()
        if hello.get("type") != "ready":
            raise TransluxError(f"the stream opened with {hello!r}, not ready",
                                code="bad_frame")
        #: The server's ``ready`` message: ``scene``, ``vertex_count``, ``format``.
        self.ready: Dict[str, Any] = hello
        self._seq = 0
        self._last_sent: Optional[int] = None
        self._last_answered: Optional[int] = None

    @property
    def vertex_count(self) -> int:
        """Vertices of the scene's mesh (frame 0), from the ``ready`` message."""
        return int(self.ready["vertex_count"])

    @property
    def pending(self) -> bool:
        """Whether a request sent has not been answered (nor superseded by one answered)."""
        return self._last_sent is not None and self._last_sent != self._last_answered

    def _next_text(self) -> Dict[str, Any]:
        op, data = self._recv()
        if op != websocket.ABNF.OPCODE_TEXT:
            raise TransluxError("expected a text message on the stream", code="bad_frame")
        message: Dict[str, Any] = json.loads(data)
        return message

    def _recv(self) -> "tuple[int, bytes]":
        while True:
            try:
                op, data = self._ws.recv_data(control_frame=True)
            except websocket.WebSocketConnectionClosedException:
                raise TransluxError("the server closed the stream",
                                    code="stream_closed") from None
            except websocket.WebSocketTimeoutException:
                raise TransluxError("no answer on the stream within the timeout",
                                    code="timeout") from None
            if op == websocket.ABNF.OPCODE_CLOSE:
                code = struct.unpack(">H", data[:2])[0] if len(data) >= 2 else None
                reason = data[2:].decode("utf-8", "replace")
                raise TransluxError(
                    f"the server closed the stream ({code}): {reason}", code="stream_closed"
                )
            if op in (websocket.ABNF.OPCODE_TEXT, websocket.ABNF.OPCODE_BINARY):
                return op, data

    def relight(
        self,
        lights: Optional[Sequence[Mapping[str, Any]]] = None,
        materials: Optional[Mapping[str, Any]] = None,
        *,
        seq: Optional[int] = None,
        **fields: Any,
    ) -> int:
        """Sends a relight request (the fields of ``POST /relight``: ``lights``,
        ``materials``, ``components``, ``solver``, ``frame``, ...; ``None`` leaves a field
        out, so the scene's defaults apply). Returns its ``seq``: ``seq`` if given (it must
        be larger than every earlier one for the iteration's ordering), else one more than
        the last."""
        request: Dict[str, Any] = {k: v for k, v in fields.items() if v is not None}
        if lights is not None:
            request["lights"] = list(lights)
        if materials is not None:
            request["materials"] = dict(materials)
        self._seq = self._seq + 1 if seq is None else int(seq)
        self._ws.send(json.dumps({"type": "relight", "seq": self._seq, "request": request}))
        self._last_sent = self._seq
        return self._seq

    def config(
        self,
        format: Optional[str] = None,
        exposure: Optional[float] = None,
        tone_map: Optional[str] = None,
    ) -> None:
        """Changes the format of the frames sent after it (``f32``, ``f16``, ``srgb8``), and
        for ``srgb8`` the exposure (EV) and tone curve (``srgb`` or ``filmic``)."""
        message: Dict[str, Any] = {"type": "config"}
        for key, value in (("format", format), ("exposure", exposure), ("tone_map", tone_map)):
            if value is not None:
                message[key] = value
        self._ws.send(json.dumps(message))

    def recv(self) -> Frame:
        """Waits for the next computed frame (its colours and stats). Raises
        :class:`TransluxError` for an ``error`` message (``.seq`` names the request), for a
        closed stream, and when nothing arrives within the stream's timeout."""
        while True:
            op, data = self._recv()
            if op == websocket.ABNF.OPCODE_BINARY:
                frame = decode_frame(data)
                message = self._next_text()
                if message.get("type") != "stats" or message.get("seq") != frame.seq:
                    raise TransluxError(
                        f"expected the stats of frame {frame.seq}, got {message!r}",
                        code="bad_frame",
                    )
                frame.stats = dict(message.get("stats") or {})
                frame.dropped = int(message.get("dropped", 0))
                self._last_answered = frame.seq
                return frame
            message = json.loads(data)
            if message.get("type") == "error":
                err = message.get("error") or {}
                seq = message.get("seq")
                if seq is not None:
                    self._last_answered = int(seq)
                raise TransluxError(
                    str(err.get("message", message)),
                    code=str(err.get("code", "error")),
                    seq=None if seq is None else int(seq),
                )
            # Any other text message (a future kind) is passed over.

    def frames(self) -> List[Frame]:
        """Every frame until the last request sent is answered (see :meth:`__next__`)."""
        return list(self)

    def __iter__(self) -> Iterator[Frame]:
        return self

    def __next__(self) -> Frame:
        """The next frame; ``StopIteration`` once nothing sent is waiting for an answer."""
        if not self.pending:
            raise StopIteration
        return self.recv()

    def close(self) -> None:
        """Closes the WebSocket (normal closure)."""
        self._ws.close()

    def __enter__(self) -> "Stream":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def stream_url(base: str, scene: str, query: Mapping[str, Any]) -> str:
    """The ``ws://`` (or ``wss://``) URL of a scene's stream under the HTTP base URL."""
    if base.startswith("https://"):
        ws = "wss://" + base[len("https://"):]
    elif base.startswith("http://"):
        ws = "ws://" + base[len("http://"):]
    else:
        ws = base
    url = f"{ws}/api/v1/scenes/{scene}/stream"
    q = {k: v for k, v in query.items() if v is not None}
    return url + ("?" + urlencode(q) if q else "")
