"""Decoders for the two picture formats the render route answers, with numpy only.

- PNG (``image/png``): 8-bit, non-interlaced greyscale, RGB or RGBA, every filter type
  (the server writes 8-bit RGB with adaptive filtering).
- OpenEXR (``image/x-exr``): one part, scan lines or one-level tiles, uncompressed, RLE,
  ZIPS or ZIP compression, half, float or uint channels (the server writes 32-bit float
  R, G, B in RLE-compressed 64 x 64 tiles).
"""

from __future__ import annotations

import struct
import zlib
from typing import Any, Dict, List, Tuple

import numpy as np
import numpy.typing as npt

from ._errors import TransluxError

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_EXR_MAGIC = 20000630


def _bad(what: str) -> TransluxError:
    return TransluxError(what, code="bad_image")


def _paeth_row(line: bytearray, prev: bytes, bpp: int) -> None:
    for i in range(len(line)):
        a = line[i - bpp] if i >= bpp else 0
        b = prev[i]
        c = prev[i - bpp] if i >= bpp else 0
        p = a + b - c
        pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
        if pa <= pb and pa <= pc:
            pred = a
        elif pb <= pc:
            pred = b
        else:
            pred = c
        line[i] = (line[i] + pred) & 0xFF


def _average_row(line: bytearray, prev: bytes, bpp: int) -> None:
    for i in range(len(line)):
        a = line[i - bpp] if i >= bpp else 0
        line[i] = (line[i] + ((a + prev[i]) >> 1)) & 0xFF


def decode_png(data: bytes) -> npt.NDArray[np.uint8]:
    """The pixels of an 8-bit PNG as ``uint8`` (height, width, channels)."""
    if not data.startswith(_PNG_MAGIC):
        raise _bad("not a PNG file")
    pos = len(_PNG_MAGIC)
    header = None
    idat: List[bytes] = []
    while pos + 8 <= len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise _bad("PNG without IHDR")
    width, height, depth, colour, _, _, interlace = header
    channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(colour)
    if depth != 8 or channels is None or interlace != 0:
        raise _bad(
            f"PNG with bit depth {depth}, colour type {colour}, interlace {interlace}:"
            " only 8-bit non-interlaced grey, grey+alpha, RGB and RGBA are read"
        )
    raw = zlib.decompress(b"".join(idat))
    stride = width * channels
    if len(raw) != height * (stride + 1):
        raise _bad(f"PNG data is {len(raw)} bytes, expected {height * (stride + 1)}")
    rows = np.frombuffer(raw, np.uint8).reshape(height, stride + 1)
    out = np.empty((height, stride), np.uint8)
    prev = np.zeros(stride, np.uint8)
    for y in range(height):
        filt = int(rows[y, 0])
        line = rows[y, 1:]
        if filt == 0:
            cur = line.copy()
        elif filt == 1:  # Sub: a running sum along each channel, modulo 256
            sums = np.cumsum(line.reshape(width, channels).astype(np.uint32), axis=0)
            cur = (sums & 0xFF).astype(np.uint8).reshape(stride)
        elif filt == 2:  # Up
            cur = line + prev
        elif filt == 3:
            buf = bytearray(line.tobytes())
            _average_row(buf, prev.tobytes(), channels)
            cur = np.frombuffer(bytes(buf), np.uint8)
        elif filt == 4:
            buf = bytearray(line.tobytes())
            _paeth_row(buf, prev.tobytes(), channels)
            cur = np.frombuffer(bytes(buf), np.uint8)
        else:
            raise _bad(f"PNG row {y} has unknown filter type {filt}")
        out[y] = cur
        prev = out[y]
    return out.reshape(height, width, channels)


def _exr_attributes(data: bytes) -> Tuple[Dict[str, Tuple[str, bytes]], int]:
    pos = 8
    attrs: Dict[str, Tuple[str, bytes]] = {}
    while True:
        end = data.index(b"\0", pos)
        name = data[pos:end].decode("latin-1")
        pos = end + 1
        if not name:
            return attrs, pos
        end = data.index(b"\0", pos)
        kind = data[pos:end].decode("latin-1")
        (size,) = struct.unpack_from("<i", data, end + 1)
        value = data[end + 5 : end + 5 + size]
        attrs[name] = (kind, value)
        pos = end + 5 + size


def _exr_channels(value: bytes) -> List[Tuple[str, int]]:
    out = []
    pos = 0
    while pos < len(value) and value[pos] != 0:
        end = value.index(b"\0", pos)
        name = value[pos:end].decode("latin-1")
        pixel_type, _, xs, ys = struct.unpack_from("<iB3xii", value, end + 1)
        if xs != 1 or ys != 1:
            raise _bad(f"EXR channel {name} is subsampled; not supported")
        out.append((name, pixel_type))
        pos = end + 1 + 16
    return out


def _exr_unpack(data: bytes, compression: int, expected: int) -> bytes:
    if compression == 0 or len(data) == expected:
        return data
    if compression == 1:
        src = data
        buf = bytearray()
        i = 0
        while i < len(src):
            count = struct.unpack_from("b", src, i)[0]
            i += 1
            if count < 0:
                buf += src[i : i + -count]
                i += -count
            else:
                buf += bytes([src[i]]) * (count + 1)
                i += 1
        raw = bytes(buf)
    elif compression in (2, 3):
        raw = zlib.decompress(data)
    else:
        raise _bad(f"EXR compression {compression} is not supported (none, RLE, ZIPS, ZIP)")
    if len(raw) != expected:
        raise _bad(f"EXR block decompresses to {len(raw)} bytes, expected {expected}")
    t = np.frombuffer(raw, np.uint8).astype(np.int64)
    t[1:] -= 128
    t = (np.cumsum(t) & 0xFF).astype(np.uint8)
    half = (len(t) + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def decode_exr(data: bytes) -> Tuple[npt.NDArray[np.float32], List[str]]:
    """The pixels of a one-part OpenEXR file as ``float32`` (height, width, channels) and the
    channel names in the order of the last axis: R, G, B (then A) first when present, the
    others after them in the file's order."""
    magic, version = struct.unpack_from("<ii", data, 0)
    if magic != _EXR_MAGIC:
        raise _bad("not an OpenEXR file")
    if version & 0x1000 or version & 0x800:
        raise _bad("multi-part or deep OpenEXR files are not supported")
    attrs, pos = _exr_attributes(data)
    channels = _exr_channels(attrs["channels"][1])
    compression = attrs["compression"][1][0]
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"][1])
    width, height = x1 - x0 + 1, y1 - y0 + 1
    sizes = {0: 4, 1: 2, 2: 4}
    dtypes: Dict[int, "np.dtype[Any]"] = {
        0: np.dtype("<u4"),
        1: np.dtype("<f2"),
        2: np.dtype("<f4"),
    }
    pixel_bytes = sum(sizes[t] for _, t in channels)
    image = np.zeros((height, width, len(channels)), np.float32)

    def fill(block: bytes, bx: int, by: int, bw: int, bh: int) -> None:
        off = 0
        for line in range(bh):
            for c, (_, t) in enumerate(channels):
                n = bw * sizes[t]
                values = np.frombuffer(block, dtypes[t], bw, off)
                image[by + line, bx : bx + bw, c] = values.astype(np.float32)
                off += n

    if "tiles" in attrs:
        tx, ty, mode = struct.unpack("<IIB", attrs["tiles"][1])
        if mode & 0xF != 0:
            raise _bad("mip-mapped or rip-mapped OpenEXR tiles are not supported")
        count = -(-width // tx) * -(-height // ty)
        offsets = struct.unpack_from(f"<{count}Q", data, pos)
        for offset in offsets:
            cx, cy, _, _, size = struct.unpack_from("<iiiii", data, offset)
            bx, by = cx * tx, cy * ty
            bw, bh = min(tx, width - bx), min(ty, height - by)
            block = _exr_unpack(data[offset + 20 : offset + 20 + size], compression,
                                bw * bh * pixel_bytes)
            fill(block, bx, by, bw, bh)
    else:
        lines = {0: 1, 1: 1, 2: 1, 3: 16}.get(compression, 1)
        count = -(-height // lines)
        offsets = struct.unpack_from(f"<{count}Q", data, pos)
        for offset in offsets:
            y, size = struct.unpack_from("<ii", data, offset)
            by = y - y0
            bh = min(lines, height - by)
            block = _exr_unpack(data[offset + 8 : offset + 8 + size], compression,
                                width * bh * pixel_bytes)
            fill(block, 0, by, width, bh)

    names = [n for n, _ in channels]
    order = [names.index(n) for n in ("R", "G", "B", "A") if n in names]
    order += [i for i in range(len(names)) if i not in order]
    return image[:, :, order], [names[i] for i in order]
