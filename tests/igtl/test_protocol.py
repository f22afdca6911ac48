"""The OpenIGTLink codec against messages pyigtl packs (header versions 1 and 2, metadata,
POLYDATA, POINT, STRING), our own packing read back by pyigtl, and malformed input refused."""

from __future__ import annotations

import struct
import tracemalloc

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from service.igtl import protocol as p  # noqa: E402


def split(data: bytes) -> p.Message:
    version, mtype, device, ts, size, crc = p.parse_header(data[: p.HEADER_SIZE])
    body = data[p.HEADER_SIZE :]
    assert len(body) == size
    return p.parse_body(version, mtype, device, ts, body, crc)


@pytest.fixture
def surface():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3)).astype(np.float32)
    tris = rng.integers(0, 50, size=(30, 3))
    return points, tris


@pytest.mark.parametrize("version", [1, 2])
def test_polydata_packed_by_pyigtl_decodes(surface, version):
    points, tris = surface
    polygons = np.c_[np.full(len(tris), 3), tris].ravel()
    msg = pyigtl.PolyDataMessage(points=points, polygons=polygons, device_name="cloud", timestamp=1234.5)
    msg.header_version = version
    if version == 2:
        msg.metadata = {"frame": "7", "origin": "slicer"}
    m = split(msg.pack())
    assert (m.type, m.device, m.version) == ("POLYDATA", "cloud", version)
    assert abs(m.timestamp - 1234.5) < 1e-6
    assert m.metadata == ({"frame": "7", "origin": "slicer"} if version == 2 else {})
    poly = p.decode_polydata(m.content)
    np.testing.assert_array_equal(poly.points, points)
    np.testing.assert_array_equal(poly.triangles, tris)


def test_polydata_with_quads_and_lines():
    pts = np.arange(18, dtype=np.float32).reshape(6, 3)
    polygons = np.array([4, 0, 1, 2, 3, 3, 3, 4, 5])
    lines = np.array([2, 0, 5])
    poly = p.decode_polydata(
        split(pyigtl.PolyDataMessage(points=pts, polygons=polygons, lines=lines, device_name="m").pack()).content
    )
    assert [c.tolist() for c in poly.polygons] == [[0, 1, 2, 3], [3, 4, 5]]
    assert [c.tolist() for c in poly.lines] == [[0, 5]]
    with pytest.raises(ValueError):
        _ = poly.triangles


def test_our_polydata_and_string_read_back_by_pyigtl(surface):
    points, tris = surface
    data = p.pack("POLYDATA", "registered", p.encode_polydata(points, tris), version=2, metadata={"a": "b"})
    header = pyigtl.MessageBase.parse_header(data[: p.HEADER_SIZE])
    assert header["message_type"] == "POLYDATA" and header["device_name"] == "registered"
    assert struct.unpack(">Q", data[50:58])[0] == pyigtl.messages.CRC64(data[p.HEADER_SIZE :])
    back = pyigtl.MessageBase()  # its POLYDATA decoder is broken: read the framing and metadata only
    back.unpack(header, data[p.HEADER_SIZE :])
    assert back.metadata == {"a": "b"}
    poly = p.decode_polydata(split(data).content)
    np.testing.assert_array_equal(poly.points, points)
    np.testing.assert_array_equal(poly.triangles, tris)
    s = p.pack("STRING", "status", p.encode_string('{"ok": "é"}'))
    msg = pyigtl.StringMessage()
    msg.unpack(pyigtl.MessageBase.parse_header(s[: p.HEADER_SIZE]), s[p.HEADER_SIZE :])
    assert msg.string == '{"ok": "é"}'


def test_point_and_string_from_pyigtl():
    xyz = np.array([[1.5, -2.0, 3.25], [0.0, 0.5, -1.0]])
    m = split(pyigtl.PointMessage(positions=xyz, names=["a", "b"], device_name="cloud").pack())
    np.testing.assert_array_equal(p.decode_point(m.content), xyz.astype(np.float32))
    m = split(pyigtl.StringMessage("hello", device_name="note").pack())
    assert p.decode_string(m.content) == "hello"


def test_malformed_messages_are_refused(surface):
    points, tris = surface
    good = p.pack("POLYDATA", "cloud", p.encode_polydata(points, tris))
    corrupt = bytearray(good)
    corrupt[-1] ^= 0xFF
    with pytest.raises(p.ProtocolError, match="CRC"):
        split(bytes(corrupt))
    with pytest.raises(p.ProtocolError, match="version"):
        p.parse_header(struct.pack(">H", 9) + good[2 : p.HEADER_SIZE])
    content = split(good).content
    with pytest.raises(p.ProtocolError, match="announces"):
        p.decode_polydata(content[:-20])
    bad = bytearray(content)
    bad[40 + 12 * len(points) + 4 : 40 + 12 * len(points) + 8] = struct.pack(">I", 999)
    with pytest.raises(p.ProtocolError, match="beyond") as beyond:
        p.decode_polydata(bytes(bad))
    assert beyond.value.code == 422  # parsed, but invalid: the HTTP API's 422
    with pytest.raises(p.ProtocolError) as unparsed:
        p.decode_point(b"\0" * 100)
    assert unparsed.value.code == 400  # cannot be parsed: the HTTP API's 400
    with pytest.raises(p.ProtocolError):
        p.decode_string(struct.pack(">HH", 3, 50) + b"short")


def test_a_zero_crc_is_checked_and_header_version_3_is_refused(surface):
    """OpenIGTLink has header versions 1 and 2, and every body carries its CRC-64: a CRC of 0
    on a non-empty body is a corrupt message, not an unchecked one."""
    points, tris = surface
    good = bytearray(p.pack("POLYDATA", "cloud", p.encode_polydata(points, tris)))
    good[50:58] = b"\0" * 8  # the header's CRC field
    with pytest.raises(p.ProtocolError, match="CRC"):
        split(bytes(good))
    with pytest.raises(p.ProtocolError, match="reads 1 and 2"):
        p.parse_header(struct.pack(">H", 3) + bytes(good[2 : p.HEADER_SIZE]))


def test_cells_of_one_size_are_read_whole_and_checked_against_the_points():
    """A cloud sent as VTK does it, one vertex cell a point: read without a loop over cells;
    cells that name points the message does not hold are malformed, with no points at all too."""
    points = np.random.default_rng(0).normal(size=(5000, 3)).astype(np.float32)
    vertices = np.column_stack([np.ones(5000, np.uint32), np.arange(5000, dtype=np.uint32)])
    header = struct.pack(">IIIIIIIIII", 5000, 5000, vertices.nbytes, 0, 0, 0, 0, 0, 0, 0)
    body = header + points.astype(">f4").tobytes() + vertices.astype(">u4").tobytes()
    decoded = p.decode_polydata(body)
    np.testing.assert_array_equal(decoded.points, points)
    assert len(decoded.vertices) == 5000 and decoded.vertices[17].tolist() == [17]
    empty = struct.pack(">IIIIIIIIII", 0, 0, 0, 0, 0, 1, 16, 0, 0, 0) + struct.pack(">IIII", 3, 0, 1, 2)
    with pytest.raises(p.ProtocolError, match="beyond the 0 points"):
        p.decode_polydata(empty)


def test_an_error_quotes_a_long_name_shortened():
    """A POLYDATA whose attribute (a 70 kB name) runs past the body: the error quotes the
    name's first characters, so that it stays a line a STRING can carry."""
    content = struct.pack(">10I", 1, 0, 0, 0, 0, 0, 0, 0, 0, 1) + bytes(12)
    content += struct.pack(">BBI", 0, 1, 5) + b"a" * 70_000 + b"\0"
    with pytest.raises(p.ProtocolError, match="runs past the body") as err:
        p.decode_polydata(content)
    assert err.value.code == 400 and len(str(err.value)) < 40 + 2 * p.QUOTE_MAX
    assert f"{'a' * p.QUOTE_MAX!r}…" in str(err.value)


def _cloud_of_cells(cells: np.ndarray, count: int, n_points: int = 1) -> bytes:
    """A POLYDATA body of ``n_points`` points and ``count`` vertex cells (``cells``: their records)."""
    cells = np.asarray(cells, ">u4")
    header = p.POLY_HEADER.pack(n_points, count, cells.nbytes, 0, 0, 0, 0, 0, 0, 0)
    return header + bytes(12 * n_points) + cells.tobytes()


@pytest.mark.parametrize("mixed", [False, True])
def test_a_million_cells_are_checked_without_an_array_each(mixed):
    """Cells are read and ignored by the bridge: a body of a million vertex cells (one size, or
    sizes that alternate) is decoded in less memory than its own size, its cells read when used."""
    n = 1_000_000
    records = np.tile([1, 0, 2, 0, 0], n // 2) if mixed else np.tile([1, 0], n)
    body = _cloud_of_cells(records, n)
    p.decode_polydata(_cloud_of_cells([1, 0], 1))  # compiled before it is measured
    tracemalloc.start()
    try:
        poly = p.decode_polydata(body)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < len(body) // 4, f"{peak} bytes to decode a body of {len(body)}"
    assert len(poly.vertices) == n and poly.vertices[-1].tolist() == ([0, 0] if mixed else [0])
    assert poly.vertices.sizes.sum() == (3 * n // 2 if mixed else n)


@pytest.mark.parametrize(
    "records, count, words, code",
    [
        ([1, 0, 2, 0], 2, "cell runs past its section", 400),
        ([1, 0, 1, 0], 3, "ends before its 3 cells", 400),
        ([1, 0, 1, 0, 1], 2, "holds more than its 2 cells", 400),
        ([2, 0, 1, 1, 5], 2, "refers to a point beyond the 3 points", 422),
        ([1, 5, 2, 0], 2, "runs past", 400),  # a section that cannot be read is 400 before any 422
    ],
)
def test_malformed_cell_sections_are_refused(records, count, words, code):
    with pytest.raises(p.ProtocolError, match=words) as err:
        p.decode_polydata(_cloud_of_cells(records, count, n_points=3))
    assert err.value.code == code


def test_device_names_are_those_a_header_carries():
    """The bridge's names, in and out, fit the header's 20 bytes and read back as sent."""
    from service.igtl.answers import STATUS, SURFACE

    for name in ("cloud", SURFACE, STATUS, "a" * 20, "my cloud"):
        assert p.check_device_name(name) == name
        assert p.parse_header(p.pack("STRING", name, b"")[: p.HEADER_SIZE])[2] == name
    for name in ("a" * 21, "", "wolkè", "cloud ", "a\tb"):
        with pytest.raises(ValueError, match="1 to 20 printable ASCII"):
            p.check_device_name(name)


def test_a_bridge_readies_the_message_kernels_before_its_first_client(api_server):
    """A fresh bridge process's first POLYDATA paid numba's compile or cache load (about 250 ms:
    the CRC and the cell walk). Bridge.prepare, which runs before the bridge listens, readies
    them, so the first frame does not wait."""
    import subprocess
    import sys

    api = api_server()
    code = (
        "import asyncio\n"
        "from service.igtl import protocol as p\n"
        "from service.igtl.bridge import Bridge\n"
        "kernels = (p._crc64, p._walk_cells)\n"
        "assert not any(k.signatures for k in kernels), 'compiled before the bridge was prepared'\n"
        f"asyncio.run(Bridge({api.url!r}, 'bar').prepare())\n"
        "assert all(k.signatures for k in kernels), [k.signatures for k in kernels]\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.parametrize("version", [1, 2])
def test_a_bytearray_body_is_the_content_and_its_points_are_decoded_in_place(surface, version):
    """The bridge's own buffer: the content is the body trimmed in place, its metadata read
    first, and reuse=True decodes the points where they lie, as a copy would give them."""
    points, tris = surface
    data = p.pack("POLYDATA", "cloud", p.encode_polydata(points, tris), version=version, metadata={"unit": "m"})
    version_, mtype, device, ts, size, crc = p.parse_header(data[: p.HEADER_SIZE])
    body = bytearray(data[p.HEADER_SIZE :])
    msg = p.parse_body(version_, mtype, device, ts, body, crc)
    assert msg.content is body and bytes(body) == split(data).content
    assert msg.metadata == ({"unit": "m"} if version == 2 else {})
    poly = p.decode_polydata(msg.content, reuse=True)
    np.testing.assert_array_equal(poly.points, points)
    np.testing.assert_array_equal(poly.triangles, tris)
    assert np.shares_memory(poly.points, np.frombuffer(body, np.uint8))  # no copy


def test_an_attribute_count_the_body_cannot_hold_is_refused_before_reading_them():
    """natt = 2**32-1 over 4 MiB of zeros: the attribute heads were read into a list (about 13
    times the body, the review's +212 MiB for 16 MiB) before the body was found too short."""
    body = p.POLY_HEADER.pack(0, 0, 0, 0, 0, 0, 0, 0, 0, 0xFFFFFFFF) + bytes(4 << 20)
    tracemalloc.start()
    try:
        with pytest.raises(p.ProtocolError) as refused:
            p.decode_polydata(body)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = len(body)
    assert peak < size // 10, f"{peak / size:.1f}x the body"
    assert refused.value.code == 400 and "4294967295 attributes cannot fit" in str(refused.value)
