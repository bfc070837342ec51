"""The exceptions of the client: every failure the server reports becomes a `TransluxError`."""

from __future__ import annotations

import json
from typing import Any, Mapping, Optional


class TransluxError(Exception):
    """An error answered by the server, or a failure to talk to it.

    The server answers every 4xx/5xx with ``{"error": {"code": ..., "message": ...}}``
    (docs/api.md, *Errors*); this exception carries those fields as they came.

    Attributes:
        status: the HTTP status (401, 404, ...); ``None`` for errors that did not come with
            one (a stream's ``error`` message, a closed stream, a failed job).
        code: the server's stable machine-readable code (``unauthorized``, ``invalid``,
            ``not_found``, ...); for answers without a JSON body, ``http_<status>``; for a
            failed job ``job_failed`` or ``job_cancelled``; for a stream the server closed,
            ``stream_closed``.
        message: the server's message, naming what was wrong and where.
        retry_after: seconds from the ``Retry-After`` header (429, 503), when given.
        seq: for an error on a stream, the ``seq`` of the relight it answers.
    """

    def __init__(
        self,
        message: str,
        *,
        status: Optional[int] = None,
        code: str = "error",
        retry_after: Optional[float] = None,
        seq: Optional[int] = None,
    ) -> None:
        self.status = status
        self.code = code
        self.message = message
        self.retry_after = retry_after
        self.seq = seq
        prefix = f"{status} {code}" if status is not None else code
        super().__init__(f"{prefix}: {message}")

    @classmethod
    def from_answer(
        cls, status: int, body: bytes, headers: Optional[Mapping[str, str]] = None
    ) -> "TransluxError":
        """The error of an HTTP answer with status ``status`` and body ``body``.

        A body in the server's JSON error format gives its code and message; any other body
        (hyper's empty 414/431, a proxy's HTML page) keeps its text as the message.
        """
        code = f"http_{status}"
        message = body.decode("utf-8", "replace").strip()
        try:
            parsed: Any = json.loads(body)
            err = parsed["error"]
            code = str(err["code"])
            message = str(err["message"])
        except (ValueError, KeyError, TypeError):
            if not message:
                message = f"the server answered {status} with no body"
        retry: Optional[float] = None
        if headers is not None:
            value = headers.get("Retry-After")
            if value is not None:
                try:
                    retry = float(value)
                except ValueError:
                    retry = None
        return cls(message, status=status, code=code, retry_after=retry)


class JobFailed(TransluxError):
    """A precompute job that ended ``failed`` or ``cancelled``; ``job`` is its last record."""

    def __init__(self, message: str, *, code: str, job: Mapping[str, Any]) -> None:
        super().__init__(message, code=code)
        self.job = dict(job)
