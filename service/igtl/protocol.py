"""OpenIGTLink messages: the 58-byte header (header versions 1 and 2, i.e. protocol versions 1 to
3), the version-2 extended header and metadata, and the POLYDATA, POINT and STRING bodies.

Everything on the wire is big-endian. A message is ``header + body``; the header's CRC is the
CRC-64 (ECMA-182 polynomial, no reflection, initial 0) of the whole body. With header version 2
the body is ``extended header (12 bytes) + content + metadata header + metadata``.
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import time
from collections.abc import Sequence
from typing import overload

import numba
import numpy as np

HEADER = struct.Struct(">H12s20sIIQQ")  # version, type, device, seconds, fraction, body size, crc
HEADER_SIZE = HEADER.size  # 58
EXT_HEADER = struct.Struct(">HHII")  # ext header size, metadata header size, metadata size, msg id
POLY_HEADER = struct.Struct(">10I")
POINT_ITEM = 136  # name 64, group 32, rgba 4, xyz 12, diameter 4, owner 20
MAX_BODY = 256 << 20
ASCII, UTF8 = 3, 106  # IANA character sets used by STRING
STRING_MAX = 0xFFFF  # a STRING's length field is 16 bits
#: characters of a sender's name (an attribute's: unbounded) that an error quotes
QUOTE_MAX = 64
DEVICE_MAX = 20  # bytes of a header's device name


class ProtocolError(ValueError):
    """A message that does not follow the protocol (answered with an error, never fatal). Its
    ``code`` is the HTTP API's for the same fault: 400 a message that cannot be parsed, 422 one
    parsed but invalid, 413 one over the limit."""

    def __init__(self, detail: str, code: int = 400) -> None:
        super().__init__(detail)
        self.code = code


# -- CRC-64 ------------------------------------------------------------------------------------


def _crc_table() -> np.ndarray:
    poly = np.uint64(0x42F0E1EBA9EA3693)
    table = np.zeros(256, np.uint64)
    for i in range(256):
        c = np.uint64(i) << np.uint64(56)
        for _ in range(8):
            top = c & np.uint64(1 << 63)
            c = (c << np.uint64(1)) ^ poly if top else c << np.uint64(1)
        table[i] = c
    return table


_TABLE = _crc_table()


@numba.njit(cache=True)
def _crc64(data, table):
    crc = np.uint64(0)
    for b in data:
        crc = table[np.uint64((crc >> np.uint64(56)) ^ np.uint64(b)) & np.uint64(0xFF)] ^ (crc << np.uint64(8))
    return crc


def crc64(data: bytes) -> int:
    return int(_crc64(np.frombuffer(data, np.uint8), _TABLE))


# -- messages ----------------------------------------------------------------------------------


@dataclasses.dataclass
class Message:
    """A decoded header and its content (the body less extended header and metadata)."""

    type: str
    device: str
    version: int = 1
    timestamp: float = 0.0
    content: bytes | bytearray = b""
    metadata: dict[str, str] = dataclasses.field(default_factory=dict)
    message_id: int = 0


def quoted(name: str) -> str:
    """``name`` as an error quotes it: its first QUOTE_MAX characters, so that the error stays
    a line whatever the sender put in it."""
    return repr(name) if len(name) <= QUOTE_MAX else f"{name[:QUOTE_MAX]!r}…"


def check_device_name(name: str) -> str:
    """``name`` where a header can carry it and reads back the same (see _name): 1 to
    DEVICE_MAX printable ASCII characters, no space at either end; ValueError otherwise."""
    if not (0 < len(name) <= DEVICE_MAX and name.isascii() and name.isprintable() and name == name.strip()):
        raise ValueError(
            f"a device name is 1 to {DEVICE_MAX} printable ASCII characters, no space at either end "
            f"(OpenIGTLink's header field), got {quoted(name)}"
        )
    return name


def _name(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace").strip()


def parse_header(raw: bytes) -> tuple[int, str, str, float, int, int]:
    """(version, type, device, timestamp, body size, crc) of a 58-byte header."""
    version, mtype, device, sec, frac, size, crc = HEADER.unpack(raw)
    if version not in (1, 2):  # OpenIGTLink's headers: 1 (protocols 1 and 2), 2 (protocol 3)
        raise ProtocolError(f"header version {version} (this bridge reads 1 and 2)")
    if size > MAX_BODY:
        raise ProtocolError(f"a body of {size} bytes is over this bridge's limit of {MAX_BODY}", 413)
    return version, _name(mtype), _name(device), sec + frac / 2**32, size, crc


def parse_body(
    version: int, mtype: str, device: str, timestamp: float, body: bytes | bytearray, crc: int | None
) -> Message:
    """The message a header and its body make; ProtocolError when they do not fit. A bytearray
    body becomes the content itself, trimmed in place (a large body is not copied)."""
    if crc is not None and crc64(body) != crc:
        raise ProtocolError(f"{mtype} {device!r}: CRC mismatch (the body is corrupt)")
    msg = Message(mtype, device, version, timestamp)
    if version == 1:
        msg.content = body
        return msg
    if len(body) < EXT_HEADER.size:
        raise ProtocolError(f"{mtype} {device!r}: body shorter than the extended header")
    ext, meta_header, meta_size, msg.message_id = EXT_HEADER.unpack_from(body)
    end = len(body) - meta_header - meta_size
    if ext < EXT_HEADER.size or end < ext:
        raise ProtocolError(f"{mtype} {device!r}: extended header sizes do not fit the body")
    msg.metadata = _metadata(bytes(body[end:]), meta_header, f"{mtype} {device!r}")
    if isinstance(body, bytearray):  # bytearray drops its first bytes without moving the rest
        del body[end:]
        del body[:ext]
        msg.content = body
    else:
        msg.content = body[ext:end]
    return msg


def _metadata(raw: bytes, header_size: int, what: str) -> dict[str, str]:
    if not raw:
        return {}
    try:
        (count,) = struct.unpack_from(">H", raw)
        if header_size != 2 + 8 * count:
            raise ProtocolError(f"{what}: metadata header of {header_size} bytes for {count} entries")
        out, at = {}, header_size
        for i in range(count):
            klen, encoding, vlen = struct.unpack_from(">HHI", raw, 2 + 8 * i)
            key = raw[at : at + klen].decode("utf-8")
            value = raw[at + klen : at + klen + vlen]
            if at + klen + vlen > len(raw):
                raise ProtocolError(f"{what}: metadata entry {i} runs past the body")
            out[key] = value.decode("ascii" if encoding == ASCII else "utf-8", errors="replace")
            at += klen + vlen
        return out
    except (struct.error, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{what}: malformed metadata ({exc})") from None


def pack(
    mtype: str,
    device: str,
    content: bytes,
    *,
    version: int = 1,
    timestamp: float | None = None,
    metadata: dict[str, str] | None = None,
    message_id: int = 0,
) -> bytes:
    """A whole message (header and body) of ``content``."""
    if version >= 2:
        keys, index = [], [struct.pack(">H", len(metadata or {}))]
        for k, v in (metadata or {}).items():
            kb, vb = k.encode(), v.encode()
            index.append(struct.pack(">HHI", len(kb), UTF8, len(vb)))
            keys.append(kb + vb)
        mh, mb = b"".join(index), b"".join(keys)
        body = EXT_HEADER.pack(EXT_HEADER.size, len(mh), len(mb), message_id) + content + mh + mb
    else:
        body = content
    t = time.time() if timestamp is None else timestamp
    sec = int(t)
    frac = min(int((t - sec) * 2**32), 2**32 - 1)
    header = HEADER.pack(version, mtype.encode()[:12], device.encode()[:20], sec, frac, len(body), crc64(body))
    return header + body


# -- POLYDATA ----------------------------------------------------------------------------------


@numba.njit(cache=True)
def _word(raw, i):
    """The ``i``-th big-endian uint32 of the bytes ``raw`` (numba reads native order only)."""
    at = 4 * i
    return (
        (np.int64(raw[at]) << 24) | (np.int64(raw[at + 1]) << 16) | (np.int64(raw[at + 2]) << 8) | np.int64(raw[at + 3])
    )


@numba.njit(cache=True)
def _walk_cells(raw, count, n_points, offsets, indices):
    """Walk a section's ``count`` cells, records ``k, i_1 .. i_k`` (uint32) in the bytes ``raw``:
    0 when they fill it exactly and name only points below ``n_points``, else the fault
    (_CELL_FAULTS). Fills ``offsets`` (count + 1) and ``indices`` unless they are empty."""
    words = raw.size // 4
    fill = offsets.size > 0
    at, beyond = 0, False
    for c in range(count):
        if at >= words:
            return 1
        k = _word(raw, at)
        if k > words - at - 1:
            return 2
        for j in range(at + 1, at + 1 + k):
            i = _word(raw, j)
            beyond |= i >= n_points
            if fill:
                indices[j - c - 1] = i  # the c + 1 size words before it are no index
        if fill:
            offsets[c + 1] = offsets[c] + k
        at += 1 + k
    if at != words:
        return 3
    return 4 if beyond else 0


_CELL_FAULTS = {
    1: ("{what} section ends before its {count} cells", 400),
    2: ("a {what} cell runs past its section", 400),
    3: ("{what} section holds more than its {count} cells", 400),
    4: ("a {what} cell refers to a point beyond the {n_points} points", 422),
}
_NONE = np.empty(0, np.int64)


class Cells(Sequence[np.ndarray]):
    """One POLYDATA cell section (vertices, lines, polygons or triangle strips): cells of any
    size, checked when the message is decoded and read only when used (the bridge reads a
    cloud's points alone; its 4 M vertex cells would be 4 M arrays). ``indices`` holds every
    cell's point indices, cell ``c`` at ``offsets[c]:offsets[c + 1]``."""

    def __init__(self, raw: np.ndarray, count: int) -> None:
        self._raw = raw  # the section's bytes, a view of the message's
        self._count = count

    @classmethod
    def checked(cls, raw: np.ndarray, count: int, n_points: int, what: str) -> Cells:
        fault = _walk_cells(raw, count, n_points, _NONE, _NONE)
        if fault:
            text, code = _CELL_FAULTS[fault]
            raise ProtocolError("POLYDATA: " + text.format(what=what, count=count, n_points=n_points), code)
        return cls(raw, count)

    @functools.cached_property
    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        offsets = np.zeros(self._count + 1, np.int64)
        indices = np.empty(self._raw.size // 4 - self._count, np.int64)  # all words but the sizes
        _walk_cells(self._raw, self._count, np.iinfo(np.int64).max, offsets, indices)
        return offsets, indices

    @property
    def offsets(self) -> np.ndarray:
        return self._read[0]

    @property
    def indices(self) -> np.ndarray:
        return self._read[1]

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.offsets)

    def __len__(self) -> int:
        return self._count

    @overload
    def __getitem__(self, c: int) -> np.ndarray: ...
    @overload
    def __getitem__(self, c: slice) -> list[np.ndarray]: ...
    def __getitem__(self, c: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(c, slice):
            return [self[i] for i in range(len(self))[c]]
        c = range(self._count)[c]  # negative counts from the end; IndexError past it
        return self.indices[self.offsets[c] : self.offsets[c + 1]]


@dataclasses.dataclass
class PolyData:
    """Shape: points (n, 3) float32; polygons, lines, vertices, strips: :class:`Cells` (index
    arrays of any size), triangles (f, 3) when every polygon is a triangle."""

    points: np.ndarray
    vertices: Cells
    lines: Cells
    polygons: Cells
    strips: Cells
    attributes: dict[str, np.ndarray]

    @property
    def triangles(self) -> np.ndarray:
        if np.any(self.polygons.sizes != 3):
            raise ValueError("not every polygon is a triangle")
        return self.polygons.indices.reshape(-1, 3)


_ATTR_COMPONENTS = {
    0: None,
    1: 3,
    2: 3,
    3: 9,
    4: 4,
}  # scalar (its own count), vector, normal, tensor, RGBA
#: the same table by the type's low nibble, for the numba walk: 0 where the head's own count holds
_ATTR_WIDTHS = np.array([_ATTR_COMPONENTS.get(k) or 0 for k in range(16)], np.int64)


def decode_polydata(content: bytes | bytearray, *, reuse: bool = False, attributes: bool = True) -> PolyData:
    """A POLYDATA body (pyigtl does not decode these; this follows igtl_polydata.c). ``reuse``:
    the points are byte-swapped where they lie in ``content`` (a bytearray its caller gives up),
    not copied: a cloud's points are nearly all of its body. ``attributes=False``: they are
    checked, not read (``attributes`` is empty): many tiny ones cost an array and a name each,
    about 20 times their bytes, for a caller that uses none (the bridge)."""
    if len(content) < POLY_HEADER.size:
        raise ProtocolError(f"POLYDATA: {len(content)} bytes, shorter than its 40-byte header")
    npts, nv, sv, nl, sl, npoly, spoly, ns, sstrip, natt = POLY_HEADER.unpack_from(content)
    if any(s % 4 for s in (sv, sl, spoly, sstrip)):
        raise ProtocolError("POLYDATA: a cell section size is not a multiple of 4 bytes")
    at = POLY_HEADER.size
    need = at + 12 * npts + sv + sl + spoly + sstrip
    if len(content) < need:
        raise ProtocolError(f"POLYDATA: {len(content)} bytes, but its header announces at least {need}")
    points = np.frombuffer(content, ">f4", 3 * npts, at)
    if reuse:
        points = points.byteswap(inplace=True).view(np.float32).reshape(npts, 3)
    else:
        points = points.astype(np.float32).reshape(npts, 3)
    at += 12 * npts
    body = np.frombuffer(content, np.uint8)
    sections = []
    for count, size, what in (
        (nv, sv, "vertices"),
        (nl, sl, "lines"),
        (npoly, spoly, "polygons"),
        (ns, sstrip, "triangle strips"),
    ):
        sections.append(Cells.checked(body[at : at + size], count, npts, what))
        at += size
    _check_attributes(content, at, natt)
    return PolyData(points, *sections, _attributes(content, at, natt) if attributes else {})


@numba.njit(cache=True)
def _walk_attributes(raw, at, count, widths):
    """Walk ``count`` attributes from byte ``at`` of ``raw`` (6-byte heads, NUL-ended names padded
    to an even length, then each one's data; ``widths``: _ATTR_WIDTHS): (0, 0, 0) when they fit
    the body, (1, 0, 0) when a name has no NUL in it, (2, start, end) the name of the first whose data runs past it."""
    n = raw.size
    heads = at
    at += 6 * count
    start = at
    for _ in range(count):
        while at < n and raw[at] != 0:
            at += 1
        if at >= n:
            return 1, 0, 0
        at += 1
    at += (at - start) % 2
    name = start
    for i in range(count):
        h = heads + 6 * i
        width = widths[raw[h] & 0x0F]
        if width == 0:  # a scalar's (kind 0) and an unknown kind's own count
            width = np.int64(raw[h + 1])
        items = (np.int64(raw[h + 2]) << 24) | (np.int64(raw[h + 3]) << 16) | (np.int64(raw[h + 4]) << 8) | raw[h + 5]
        end = name
        while raw[end] != 0:
            end += 1
        size = 4 * width * items
        if at + size > n:
            return 2, name, end
        at += size
        name = end + 1
    return 0, 0, 0


def _check_attributes(content: bytes | bytearray, at: int, count: int) -> None:
    """ProtocolError unless the ``count`` attributes from byte ``at`` fit the body; none is read."""
    left = len(content) - at
    if 7 * count > left:  # a 6-byte head and a name of at least its NUL each, before any is read
        raise ProtocolError(f"POLYDATA: {count} attributes cannot fit in the {left} bytes left of its body")
    fault, start, end = _walk_attributes(np.frombuffer(content, np.uint8), at, count, _ATTR_WIDTHS)
    if fault == 1:
        raise ProtocolError("POLYDATA: malformed attributes (a name has no NUL before the body ends)")
    if fault == 2:
        name = bytes(content[start:end]).decode("utf-8", errors="replace")
        raise ProtocolError(f"POLYDATA: attribute {quoted(name)} runs past the body")


def _attributes(content: bytes | bytearray, at: int, count: int) -> dict[str, np.ndarray]:
    """The attributes, as arrays by name (checked first: _check_attributes)."""
    try:
        heads = [struct.unpack_from(">BBI", content, at + 6 * i) for i in range(count)]
        at += 6 * count
        names = []
        start = at
        for _ in range(count):
            end = content.index(b"\0", at)
            names.append(content[at:end].decode("utf-8", errors="replace"))
            at = end + 1
        at += (at - start) % 2  # names padded to an even length
        out = {}
        for (kind, ncomp, n), name in zip(heads, names, strict=True):
            comps = _ATTR_COMPONENTS.get(kind & 0x0F)
            width = ncomp if comps is None else comps
            size = 4 * width * n
            if at + size > len(content):
                raise ProtocolError(f"POLYDATA: attribute {quoted(name)} runs past the body")
            out[name] = np.frombuffer(content, ">f4", width * n, at).astype(np.float32).reshape(n, width)
            at += size
        return out
    except (struct.error, ValueError) as exc:
        if isinstance(exc, ProtocolError):
            raise
        raise ProtocolError(f"POLYDATA: malformed attributes ({exc})") from None


def encode_polydata(points: np.ndarray, triangles: np.ndarray) -> bytes:
    """A POLYDATA body of points (n, 3) and triangles (f, 3), no attributes."""
    pts = np.ascontiguousarray(points, ">f4").reshape(-1, 3)
    tri = np.asarray(triangles, np.int64).reshape(-1, 3)
    cells = np.empty((len(tri), 4), ">u4")
    cells[:, 0] = 3
    cells[:, 1:] = tri
    header = POLY_HEADER.pack(len(pts), 0, 0, 0, 0, len(tri), cells.nbytes, 0, 0, 0)
    return header + pts.tobytes() + cells.tobytes()


def warm() -> None:
    """Compile (or load from numba's cache) the kernels a first message runs, the CRC and the
    cell and attribute walks, so that a bridge's first frame does not pay for them (about 250 ms here)."""
    body = encode_polydata(np.zeros((3, 3)), np.arange(3)[None])
    decode_polydata(body)
    crc64(body)


# -- POINT and STRING --------------------------------------------------------------------------


def decode_point(content: bytes | bytearray) -> np.ndarray:
    """The positions (m, 3) of a POINT body (136 bytes a point)."""
    if len(content) % POINT_ITEM:
        raise ProtocolError(f"POINT: {len(content)} bytes is not a whole number of 136-byte points")
    items = np.frombuffer(content, np.uint8).reshape(-1, POINT_ITEM)
    xyz = np.ascontiguousarray(items[:, 100:112]).view(">f4")
    return xyz.astype(np.float32).reshape(-1, 3)


def decode_string(content: bytes | bytearray) -> str:
    if len(content) < 4:
        raise ProtocolError("STRING: shorter than its 4-byte header")
    encoding, length = struct.unpack_from(">HH", content)
    if 4 + length > len(content):
        raise ProtocolError(f"STRING: {length} bytes announced, {len(content) - 4} present")
    return content[4 : 4 + length].decode("ascii" if encoding == ASCII else "utf-8", errors="replace")


def encode_string(text: str) -> bytes:
    raw = text.encode("utf-8")
    if len(raw) > STRING_MAX:
        raise ValueError(f"a STRING holds at most {STRING_MAX} bytes")
    return struct.pack(">HH", UTF8, len(raw)) + raw
