"""translux: a Python client of ``translux-server``.

>>> from translux import Client
>>> client = Client("http://127.0.0.1:8080")            # token="tlx_..." for a team server
>>> cornell = client.scene("cornell")
>>> result = cornell.relight([{"type": "point", "position": [0, 0.5, 0], "intensity": [1, 1, 1]}])
>>> result.radiance.shape                                # (vertices, 3) float32, linear B/pi
(998, 3)

See ``clients/python/README.md`` and ``docs/api.md`` for the routes behind each method.
"""

from ._client import Client, Job, Mesh, RelightResult, Scene
from ._errors import JobFailed, TransluxError
from ._images import decode_exr, decode_png
from ._stream import Frame, Stream

__all__ = [
    "Client",
    "Frame",
    "Job",
    "JobFailed",
    "Mesh",
    "RelightResult",
    "Scene",
    "Stream",
    "TransluxError",
    "decode_exr",
    "decode_png",
]

__version__ = "0.1.0"
