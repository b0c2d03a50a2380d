"""OpenIGTLink framing and validation of incoming messages.

Every OpenIGTLink message is a 58-byte header followed by a body::

    uint16 header version (1: OpenIGTLink 1/2; 2: OpenIGTLink 3 with extended header)
    char[12] message type, char[20] device name, uint64 timestamp,
    uint64 body size (bytes), uint64 CRC-64 of the body          (all big-endian)

With header version 2 the body starts with a 12-byte extended header (its own size,
metadata-header size, metadata size, message id) and ends with the metadata.

Headers are parsed like :meth:`pyigtl.MessageBase.parse_header` does (with a faster
timestamp conversion); TRANSFORM and STRING contents are unpacked with pyigtl's message
classes, POINT coordinates are read vectorised; replies are packed with pyigtl (STRING) or
pre-packed (POLYDATA, :mod:`tissuecast.serve.polydata`). Everything pyigtl
does not check (sizes, CRC, counts, finiteness, text encodings) is checked here, and every
problem becomes a :class:`ProtocolError` whose ``fatal`` flag says whether the byte stream
can still be trusted (``fatal=False``: the whole body was read, the next message starts
right after it).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from ..errors import TissuecastError, require
from .crc import CRC64

pyigtl = require("pyigtl", "serve", "OpenIGTLink messaging")
MessageBase = pyigtl.MessageBase

__all__ = [
    "HEADER_SIZE",
    "DEFAULT_MAX_BODY_BYTES",
    "ProtocolError",
    "Header",
    "parse_header",
    "message_content",
    "decode_points",
    "decode_transform",
    "decode_transform_translation",
    "decode_string",
    "pack_string",
    "pack_header",
]

HEADER_SIZE = MessageBase.IGTL_HEADER_SIZE  # 58 bytes
#: Largest body accepted by default; a marker message is far smaller (POINT: 136 bytes per point).
DEFAULT_MAX_BODY_BYTES = 1 << 16
_HEADER = struct.Struct("> H 12s 20s I I Q Q")
_EXTENDED_HEADER = struct.Struct("> H H I I")
_POINT_ELEMENT_SIZE = 136  # 64 name + 32 group + 4 RGBA + 12 XYZ + 4 diameter + 20 owner
_TRANSFORM_SIZE = 48  # 12 float32
# one POINT element: name, group, RGBA, then the coordinates (big-endian float32), diameter, owner
_POINT_ELEMENT = np.dtype([("head", "V100"), ("xyz", ">f4", (3,)), ("tail", "V24")])


class ProtocolError(TissuecastError, ValueError):
    """An incoming message is malformed or cannot be served.

    Attributes:
        fatal: True when the connection must be closed (the byte stream is out of step or
            the peer announced an oversized body); False when only this message is rejected.
    """

    def __init__(self, message: str, *, fatal: bool = False):
        super().__init__(message)
        self.fatal = fatal


@dataclass(frozen=True)
class Header:
    """A parsed and validated OpenIGTLink header.

    Attributes:
        version: header version (1 or 2).
        message_type: e.g. ``"POINT"``, ``"TRANSFORM"``, ``"GET_POLYDATA"``.
        device_name: the device (stream) name.
        timestamp: seconds since 1970 (float).
        body_size: body length in bytes.
        crc: CRC-64 of the body announced by the sender.
    """

    version: int
    message_type: str
    device_name: str
    timestamp: float
    body_size: int
    crc: int

    def as_pyigtl_fields(self) -> dict:
        return {
            "header_version": self.version,
            "message_type": self.message_type,
            "device_name": self.device_name,
            "timestamp": self.timestamp,
            "body_size": self.body_size,
        }


def _printable(raw: bytes, what: str) -> None:
    text = raw.rstrip(b"\0")
    if any(c < 0x20 or c > 0x7E for c in text):
        raise ProtocolError(f"the header's {what} is not printable ASCII: {raw!r}", fatal=True)


def parse_header(raw: bytes, max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> Header:
    """Parse and validate a 58-byte OpenIGTLink header.

    Args:
        raw: exactly :data:`HEADER_SIZE` bytes.
        max_body_bytes: largest body size accepted.

    Raises:
        ProtocolError: (fatal) unknown header version, non-ASCII type or device name, or a
            body size above ``max_body_bytes``; the caller must not read the body.
    """
    if len(raw) != HEADER_SIZE:
        raise ProtocolError(f"a header has {HEADER_SIZE} bytes, got {len(raw)}", fatal=True)
    version, mtype, device, seconds, fraction, body_size, crc = _HEADER.unpack(raw)
    if version not in (1, 2):
        raise ProtocolError(f"unsupported header version {version} (1 or 2 expected)", fatal=True)
    _printable(mtype, "message type")
    _printable(device, "device name")
    if body_size > max_body_bytes:
        raise ProtocolError(
            f"announced body of {body_size} bytes exceeds the limit of {max_body_bytes} bytes; "
            "closing the connection",
            fatal=True,
        )
    # same fields as pyigtl.MessageBase.parse_header, without its bit-by-bit fraction loop (docs/serving.md)
    return Header(
        version,
        mtype.rstrip(b"\0").decode("ascii").rstrip(),
        device.rstrip(b"\0").decode("ascii").rstrip(),
        seconds + fraction / 4294967296.0,
        body_size,
        crc,
    )


def message_content(header: Header, body: bytes | memoryview) -> bytes | memoryview:
    """Check the body's CRC and return its content part (extended header and metadata cut off).

    Raises:
        ProtocolError: (not fatal) CRC mismatch or inconsistent extended-header sizes.
    """
    if len(body) != header.body_size:
        raise ProtocolError(f"body has {len(body)} bytes, header announced {header.body_size}")
    crc = CRC64(body)
    if crc != header.crc:
        raise ProtocolError(
            f"CRC mismatch in {header.message_type} message {header.device_name!r}: "
            f"header says {header.crc:#018x}, body gives {crc:#018x}"
        )
    if header.version == 1:
        return body
    if len(body) < _EXTENDED_HEADER.size:
        raise ProtocolError(f"header version 2 body of {len(body)} bytes has no 12-byte extended header")
    ext_size, meta_header_size, meta_size, _ = _EXTENDED_HEADER.unpack_from(body)
    end = len(body) - meta_header_size - meta_size
    if ext_size < _EXTENDED_HEADER.size or end < ext_size:
        raise ProtocolError(
            f"extended header sizes ({ext_size}, {meta_header_size}, {meta_size}) do not fit "
            f"a body of {len(body)} bytes"
        )
    return body[ext_size:end]


def _unpack(message: MessageBase, header: Header, content) -> MessageBase:
    # pyigtl parses the content; header fields are set directly (version-1 body layout)
    fields = dict(header.as_pyigtl_fields(), header_version=1)
    try:
        message.unpack(fields, bytes(content))
    except Exception as exc:  # pyigtl raises struct.error, UnicodeDecodeError, TypeError...
        raise ProtocolError(f"cannot unpack {header.message_type} message {header.device_name!r}: {exc}") from exc
    return message


def decode_points(header: Header, content, *, allow_missing: bool = False, check_finite: bool = True) -> np.ndarray:
    """Positions of a POINT message.

    Args:
        allow_missing: accept points whose three coordinates are all NaN (untracked markers).
        check_finite: refuse non-finite coordinates here (False: the caller's input gate does,
            naming the marker).

    Returns:
        (p, 3) float64, mm, in the message's order.

    Raises:
        ProtocolError: content length not a multiple of 136 bytes, no points, or a
            non-finite coordinate (other than an all-NaN point when ``allow_missing``).
    """
    if len(content) == 0 or len(content) % _POINT_ELEMENT_SIZE:
        raise ProtocolError(
            f"POINT message {header.device_name!r} has {len(content)} content bytes, "
            f"not a positive multiple of {_POINT_ELEMENT_SIZE}"
        )
    positions = np.frombuffer(content, dtype=_POINT_ELEMENT)["xyz"].astype(np.float64)
    finite = np.isfinite(positions).all(axis=1)
    if check_finite and not finite.all() and not (allow_missing and np.isnan(positions[~finite]).all()):
        raise ProtocolError(
            f"POINT message {header.device_name!r} holds NaN or infinite coordinates "
            f"(points {np.flatnonzero(~finite).tolist()})"
        )
    return positions


def decode_transform(header: Header, content) -> np.ndarray:
    """The 4 x 4 matrix of a TRANSFORM message (rotation/scale columns and translation, mm).

    Raises:
        ProtocolError: content not 48 bytes or a non-finite matrix entry.
    """
    if len(content) != _TRANSFORM_SIZE:
        raise ProtocolError(
            f"TRANSFORM message {header.device_name!r} has {len(content)} content bytes, expected {_TRANSFORM_SIZE}"
        )
    matrix = np.asarray(_unpack(pyigtl.TransformMessage(), header, content).matrix, dtype=np.float64)
    if not np.isfinite(matrix).all():
        raise ProtocolError(f"TRANSFORM message {header.device_name!r} holds NaN or infinite values")
    return matrix


def decode_transform_translation(header: Header, content) -> np.ndarray:
    """Translation (marker position) of a TRANSFORM message: (3,) float64, mm (see :func:`decode_transform`)."""
    return decode_transform(header, content)[:3, 3].copy()


def decode_string(header: Header, content) -> str:
    """Text of a STRING message.

    Raises:
        ProtocolError: truncated content, unknown encoding or undecodable bytes.
    """
    if len(content) < 4:
        raise ProtocolError(f"STRING message {header.device_name!r} has only {len(content)} content bytes")
    encoding, length = struct.unpack_from("> H H", content)
    if encoding not in (MessageBase.IANA_CHARACTER_SET_ASCII, MessageBase.IANA_CHARACTER_SET_UTF8):
        raise ProtocolError(f"STRING message {header.device_name!r} uses unsupported encoding {encoding} (3 or 106)")
    if length > len(content) - 4:
        raise ProtocolError(f"STRING message {header.device_name!r} announces {length} bytes, has {len(content) - 4}")
    try:
        return _unpack(pyigtl.StringMessage(), header, content).string
    except UnicodeDecodeError as exc:  # pragma: no cover - wrapped by _unpack
        raise ProtocolError(str(exc)) from exc


def pack_header(message_type: str, device_name: str, timestamp: float, body_size: int, crc: int) -> bytes:
    """Pack a version-1 OpenIGTLink header (58 bytes)."""
    if not (math.isfinite(timestamp) and 0.0 <= timestamp < 4294967296.0):
        timestamp = 0.0
    seconds = int(timestamp)
    fraction = int((timestamp - seconds) * 4294967296.0)
    return _HEADER.pack(
        1,
        message_type.encode("ascii"),
        device_name.encode("ascii")[:20],
        seconds & 0xFFFFFFFF,
        min(max(fraction, 0), 0xFFFFFFFF),
        body_size,
        crc,
    )


def pack_string(device_name: str, text: str, timestamp: float | None = None) -> bytes:
    """A packed STRING message (used for error replies and status lines)."""
    # ASCII only (pyigtl's UTF-8 fallback is broken in 0.3.4); at most 60000 characters
    text = text[:60000].encode("ascii", "backslashreplace").decode("ascii")
    return pyigtl.StringMessage(text, device_name=device_name, timestamp=timestamp).pack()
