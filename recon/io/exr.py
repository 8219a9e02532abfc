"""A minimal OpenEXR reader for depth maps, for OpenCV builds without an EXR codec.

Owns decoding the EXR files depth sensors export (Record3D's ``depth/N.exr``): single-part
scanline images, uncompressed or zlib-compressed (NONE, ZIPS, ZIP), with HALF, FLOAT or
UINT channels, none subsampled, after OpenEXR's "file layout" document; anything else gives
a one-line ReconInputError. :func:`recon.io.depth_maps.read_depth_file` tries OpenCV first
and falls back to this decoder. More: docs/input.md#record3d
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError

MAGIC = b"\x76\x2f\x31\x01"
# pixel type -> little-endian dtype
PIXEL_TYPES = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}
# compression id -> (name, scanlines per chunk); only the first three are decoded here.
COMPRESSIONS = {0: ("NONE", 1), 1: ("RLE", 1), 2: ("ZIPS", 1), 3: ("ZIP", 16), 4: ("PIZ", 32), 5: ("PXR24", 16),
                6: ("B44", 32), 7: ("B44A", 32), 8: ("DWAA", 32), 9: ("DWAB", 256)}
# Channel a depth map is stored in when there are several (Z: OpenEXR's depth convention).
DEPTH_CHANNELS = ("Z", "depth", "R", "Y")
_TILED, _LONG_NAMES, _NON_IMAGE, _MULTIPART = 0x200, 0x400, 0x800, 0x1000


def read_exr(path: Path) -> np.ndarray:
    """(H, W) float32 of the depth channel of a scanline EXR (see the module docstring)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ReconInputError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None
    try:
        return _decode(path, data)
    except (struct.error, IndexError, ValueError, zlib.error) as exc:
        raise ReconInputError(f"{path}: corrupt or truncated EXR ({type(exc).__name__}: {exc})") from None


def _decode(path: Path, data: bytes) -> np.ndarray:
    if data[:4] != MAGIC:
        raise ReconInputError(f"{path}: not an OpenEXR file")
    flags = struct.unpack_from("<I", data, 4)[0]
    if flags & (_TILED | _NON_IMAGE | _MULTIPART):
        raise ReconInputError(f"{path}: tiled, deep or multi-part EXR is not supported (scanline images only)")
    header, pos = _header(data, 8)
    for key in ("channels", "compression", "dataWindow"):
        if key not in header:
            raise ReconInputError(f"{path}: EXR header lacks {key!r}")
    channels = header["channels"]
    x0, y0, x1, y1 = header["dataWindow"]
    width, height = x1 - x0 + 1, y1 - y0 + 1
    name, lines_per_chunk = COMPRESSIONS.get(header["compression"], (str(header["compression"]), 0))
    if name not in ("NONE", "ZIPS", "ZIP"):
        raise ReconInputError(f"{path}: EXR compression {name} is not supported here (NONE, ZIPS or ZIP); "
                              "convert to .npy, .pfm or float .tiff")
    if any(sampling != (1, 1) for _, _, sampling in channels):
        raise ReconInputError(f"{path}: subsampled EXR channels are not supported")
    names = [c[0] for c in channels]
    wanted = names[0] if len(names) == 1 else next((c for c in DEPTH_CHANNELS if c in names), None)
    if wanted is None:
        raise ReconInputError(f"{path}: EXR channels {names}: none is a depth channel ({', '.join(DEPTH_CHANNELS)})")
    # Byte range of the wanted channel's row within one scanline.
    start, dtype = 0, None
    for cname, ptype, _ in channels:
        if cname == wanted:
            dtype = ptype
            break
        start += width * ptype.itemsize
    line_bytes = width * sum(ptype.itemsize for _, ptype, _ in channels)

    chunks = -(-height // lines_per_chunk)
    offsets = np.frombuffer(data, "<u8", chunks, pos)
    out = np.zeros((height, width), np.float32)
    for offset in offsets.tolist():
        y, size = struct.unpack_from("<ii", data, offset)
        first = y - y0
        lines = min(lines_per_chunk, height - first)
        if not 0 <= first < height:
            raise ReconInputError(f"{path}: EXR chunk at byte {offset} starts at line {y}, outside the data window")
        raw = data[offset + 8: offset + 8 + size]
        expected = lines * line_bytes
        if name != "NONE" and size < expected:
            raw = _unzip(zlib.decompress(raw), expected)
        if len(raw) != expected:
            raise ReconInputError(f"{path}: EXR chunk at line {y} holds {len(raw)} bytes, expected {expected}")
        rows = np.frombuffer(raw, np.uint8).reshape(lines, line_bytes)[:, start: start + width * dtype.itemsize]
        out[first: first + lines] = np.ascontiguousarray(rows).view(dtype).astype(np.float32)
    return out


def _unzip(inflated: bytes, expected: int) -> bytes:
    """Undo the predictor and the even/odd byte split that OpenEXR applies before zlib."""
    if len(inflated) != expected:
        raise ValueError(f"inflated chunk has {len(inflated)} bytes, expected {expected}")
    t = np.frombuffer(inflated, np.uint8).astype(np.int64)
    # Each byte was stored as (b[i] - b[i-1] + 128) mod 256: a running sum undoes it.
    t[1:] -= 128
    t = (np.cumsum(t) & 0xFF).astype(np.uint8)
    out = np.empty_like(t)
    half = (len(t) + 1) // 2
    out[0::2], out[1::2] = t[:half], t[half:]
    return out.tobytes()


def _header(data: bytes, pos: int) -> tuple[dict, int]:
    """The attributes this reader uses, and the position after the header."""
    header: dict = {}
    while True:
        name, pos = _cstring(data, pos)
        if not name:
            return header, pos
        kind, pos = _cstring(data, pos)
        size = struct.unpack_from("<i", data, pos)[0]
        value = data[pos + 4: pos + 4 + size]
        pos += 4 + size
        if name == "channels" and kind == "chlist":
            header[name] = _channels(value)
        elif name == "compression" and kind == "compression":
            header[name] = value[0]
        elif name == "dataWindow" and kind == "box2i":
            header[name] = struct.unpack("<4i", value)


def _channels(value: bytes) -> list[tuple[str, np.dtype, tuple[int, int]]]:
    """(name, dtype, (x sampling, y sampling)) of each channel of a chlist attribute."""
    out, pos = [], 0
    while True:
        name, pos = _cstring(value, pos)
        if not name:
            return out
        ptype, _, xs, ys = struct.unpack_from("<iB3xii", value, pos)
        pos += 16
        if ptype not in PIXEL_TYPES:
            raise ValueError(f"channel {name!r} has unknown pixel type {ptype}")
        out.append((name, PIXEL_TYPES[ptype], (xs, ys)))


def _cstring(data: bytes, pos: int) -> tuple[str, int]:
    end = data.index(b"\0", pos)
    return data[pos:end].decode("latin-1"), end + 1
