"""OpenIGTLink framing, CRC and POLYDATA coding (no sockets)."""

from __future__ import annotations

import struct

import numpy as np
import pyigtl
import pytest
from pyigtl.messages import CRC64

from tissuecast.serve.crc import SegmentedCrc, ZeroShift
from tissuecast.serve.polydata import PolyDataTemplate, decode_polydata
from tissuecast.serve.protocol import (
    HEADER_SIZE,
    ProtocolError,
    decode_points,
    decode_string,
    decode_transform_translation,
    message_content,
    pack_header,
    pack_string,
    parse_header,
)


def split(packed: bytes):
    header = parse_header(packed[:HEADER_SIZE])
    return header, message_content(header, packed[HEADER_SIZE:])


# ---------------------------------------------------------------------------- CRC
def test_zero_shift_equals_crc_over_appended_zeros():
    rng = np.random.default_rng(1)
    for length in (0, 1, 7, 1000):
        shift = ZeroShift(length)
        for _ in range(5):
            c = int(rng.integers(0, 2**63)) * 2 + int(rng.integers(0, 2))
            assert shift(c) == CRC64(bytes(length), c)


def test_segmented_crc_matches_full_crc_after_changes():
    rng = np.random.default_rng(2)
    buf = bytearray(rng.bytes(5000))
    crc = SegmentedCrc(buf, [(3000, 4000), (10, 400), (4990, 5000)])
    for _ in range(10):
        for a, b in ((10, 400), (3000, 4000), (4990, 5000)):
            buf[a:b] = rng.bytes(b - a)
        assert crc.compute(buf) == CRC64(bytes(buf))
    buf[500] ^= 1  # a change outside the declared segments is (by design) not seen
    assert crc.compute(buf) != CRC64(bytes(buf))


# ---------------------------------------------------------------------------- header
def test_header_round_trip_with_pyigtl_and_own_packer():
    msg = pyigtl.StringMessage("hello", device_name="Dev", timestamp=1234.5)
    header, content = split(msg.pack())
    assert (header.version, header.message_type, header.device_name) == (1, "STRING", "Dev")
    assert header.timestamp == pytest.approx(1234.5, abs=1e-6)
    assert decode_string(header, content) == "hello"
    raw = pack_header("POLYDATA", "TissueSurface", 99.25, 10, 7)
    h = parse_header(raw)
    assert (h.message_type, h.device_name, h.timestamp, h.body_size, h.crc) == ("POLYDATA", "TissueSurface", 99.25, 10, 7)


def test_header_version_2_extended_header_and_metadata_are_cut_off():
    msg = pyigtl.TransformMessage(np.eye(4), device_name="Marker1")
    msg.header_version = 2
    msg.metadata = {"key": "value"}
    msg.matrix[:3, 3] = [1.0, -2.0, 3.5]
    header, content = split(msg.pack())
    assert header.version == 2 and len(content) == 48
    assert decode_transform_translation(header, content).tolist() == [1.0, -2.0, 3.5]


@pytest.mark.parametrize(
    "mutate, text",
    [
        (lambda raw: struct.pack(">H", 7) + raw[2:], "header version 7"),
        (lambda raw: raw[:42] + struct.pack(">Q", 2**40) + raw[50:], "exceeds the limit"),
        (lambda raw: raw[:2] + b"\xff" * 12 + raw[14:], "not printable"),
    ],
)
def test_bad_headers_are_fatal(mutate, text):
    raw = mutate(pyigtl.StringMessage("x", device_name="D").pack()[:HEADER_SIZE])
    with pytest.raises(ProtocolError, match=text) as info:
        parse_header(raw)
    assert info.value.fatal


def test_crc_mismatch_and_bad_extended_header_are_not_fatal():
    packed = bytearray(pyigtl.StringMessage("abc", device_name="D").pack())
    packed[-1] ^= 0x20
    header = parse_header(bytes(packed[:HEADER_SIZE]))
    with pytest.raises(ProtocolError, match="CRC mismatch") as info:
        message_content(header, bytes(packed[HEADER_SIZE:]))
    assert not info.value.fatal
    body = struct.pack(">H H I I", 12, 0, 500, 0) + b"x" * 8  # metadata larger than the body
    raw = struct.pack(">H 12s 20s I I Q Q", 2, b"STRING", b"D", 0, 0, len(body), CRC64(body))
    with pytest.raises(ProtocolError, match="do not fit"):
        message_content(parse_header(raw), body)


# ---------------------------------------------------------------------------- contents
def test_points_decode_and_reject_non_finite():
    pts = np.array([[1.5, 2, 3], [4, 5, 6], [-7, 8, 9.25]], dtype=np.float32)
    header, content = split(pyigtl.PointMessage(pts, device_name="Markers").pack())
    np.testing.assert_array_equal(decode_points(header, content), pts)
    pts[1, 2] = np.nan
    header, content = split(pyigtl.PointMessage(pts, device_name="Markers").pack())
    with pytest.raises(ProtocolError, match="NaN"):
        decode_points(header, content)
    with pytest.raises(ProtocolError, match="multiple of 136"):
        decode_points(header, content[:-1])


def test_transform_and_string_validation():
    header, content = split(pyigtl.TransformMessage(np.eye(4), device_name="Marker0").pack())
    with pytest.raises(ProtocolError, match="expected 48"):
        decode_transform_translation(header, content[:40])
    header, content = split(pack_string("D", "some text"))
    assert decode_string(header, content) == "some text"
    with pytest.raises(ProtocolError, match="announces"):
        decode_string(header, content[:6])
    with pytest.raises(ProtocolError, match="encoding"):
        decode_string(header, b"\x00\x07" + content[2:])


# ---------------------------------------------------------------------------- POLYDATA
def test_decoder_reads_pyigtl_packed_polydata():
    """Cross-check against an independent packer (pyigtl.PolyDataMessage)."""
    pts = np.random.default_rng(3).normal(size=(6, 3)).astype(np.float32)
    polygons = np.array([3, 0, 1, 2, 4, 2, 3, 4, 5], dtype=np.uint32)
    lines = np.array([2, 0, 5], dtype=np.uint32)
    packed = pyigtl.PolyDataMessage(points=pts, polygons=polygons, lines=lines, device_name="P").pack()
    header, content = split(packed)
    poly = decode_polydata(content)
    np.testing.assert_array_equal(poly.points, pts)
    assert [p.tolist() for p in poly.polygons] == [[0, 1, 2], [2, 3, 4, 5]]
    assert [p.tolist() for p in poly.lines] == [[0, 5]]
    with pytest.raises(ValueError, match="triangle"):
        poly.triangles()


def test_template_round_trip_with_attributes():
    rng = np.random.default_rng(4)
    tris = np.array([[0, 1, 2], [1, 3, 2], [0, 3, 1]])
    template = PolyDataTemplate(4, tris, [("uncertainty_mm", "scalars"), ("displacement_mm", "vectors")])
    for _ in range(3):
        pts, sc, vec = rng.normal(size=(4, 3)), rng.random(4), rng.normal(size=(4, 3))
        template.points[:] = pts
        template.values["uncertainty_mm"][:] = sc
        template.values["displacement_mm"][:] = vec
        packed = bytes(template.finish("TissueSurface", 5.5))
        header, content = split(packed)  # checks the CRC computed over the segments
        poly = decode_polydata(content)
        np.testing.assert_array_equal(poly.points, pts.astype(np.float32))
        np.testing.assert_array_equal(poly.triangles(), tris)
        np.testing.assert_array_equal(poly.point_data["uncertainty_mm"], sc.astype(np.float32))
        np.testing.assert_array_equal(poly.point_data["displacement_mm"], vec.astype(np.float32))
        assert header.device_name == "TissueSurface" and header.timestamp == pytest.approx(5.5)


def test_polydata_decoder_rejects_inconsistent_sizes():
    template = PolyDataTemplate(3, np.array([[0, 1, 2]]), [("s", "scalars")])
    content = bytes(template.finish("P", 0.0))[HEADER_SIZE:]
    decode_polydata(content)
    with pytest.raises(ProtocolError, match="runs past|trailing"):
        decode_polydata(content[:-3])
    with pytest.raises(ProtocolError, match="trailing"):
        decode_polydata(content + b"\0\0\0\0")
    bad_id = bytearray(content)
    bad_id[40 + 36 + 4 : 40 + 36 + 8] = struct.pack(">I", 9)  # first triangle's first id -> 9
    with pytest.raises(ProtocolError, match="point id 9"):
        decode_polydata(bytes(bad_id))
    huge = struct.pack(">10I", 2**30, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    with pytest.raises(ProtocolError, match="runs past"):
        decode_polydata(huge)
    with pytest.raises(ProtocolError, match="40-byte"):
        decode_polydata(b"\0" * 12)
