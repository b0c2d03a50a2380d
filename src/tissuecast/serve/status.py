"""OpenIGTLink STATUS messages: the out-of-distribution alarm on the wire.

A STATUS body (OpenIGTLink version 1 layout) is::

    uint16 code, int64 subcode, char[20] error name, char[] status text (NUL-terminated)

all big-endian. tissuecast sends, on device :data:`STATUS_DEVICE`, one STATUS after the
POLYDATA reply of a prediction that raised the alarm (code :attr:`StatusCode.UNKNOWN_ERROR`,
the protocol's generic error, name :data:`ALARM_NAME`, subcode a bitmask of
:class:`AlarmBits`, text the alarm's one-line explanation), and one STATUS ``OK`` when a
later prediction no longer raises it. Marker input the model's input gate refuses gets no mesh
but a STATUS with name :data:`REFUSED_NAME` (subcode :class:`RefusalBits`, text naming the
marker). The server keeps serving either way.

pyigtl 0.3.4 has no STATUS class: :class:`StatusMessage` is one (a ``pyigtl.MessageBase``),
and :func:`register_status_message` teaches ``pyigtl.OpenIGTLinkClient`` to receive it.
"""

from __future__ import annotations

import struct
from enum import IntEnum, IntFlag

from .protocol import ProtocolError, pyigtl

__all__ = ["StatusCode", "AlarmBits", "RefusalBits", "StatusMessage", "pack_status", "decode_status",
           "register_status_message", "refusal_bits", "STATUS_DEVICE", "ALARM_NAME", "REFUSED_NAME"]

STATUS_DEVICE = "TissueStatus"
ALARM_NAME = "OutOfDistribution"
REFUSED_NAME = "InputRefused"
_FIXED = struct.Struct("> H q 20s")


class StatusCode(IntEnum):
    """Status codes of the OpenIGTLink STATUS message (protocol specification)."""

    INVALID = 0
    OK = 1
    UNKNOWN_ERROR = 2
    PANIC = 3
    NOT_FOUND = 4
    ACCESS_DENIED = 5
    BUSY = 6
    TIME_OUT = 7
    OVERFLOW = 8
    CHECKSUM_ERROR = 9
    CONFIG_ERROR = 10
    RESOURCE_ERROR = 11
    UNKNOWN_INSTRUCTION = 12
    NOT_READY = 13
    MANUAL_MODE = 14
    DISABLED = 15
    NOT_PRESENT = 16
    UNKNOWN_VERSION = 17
    HARDWARE_FAILURE = 18
    SHUT_DOWN = 19


class AlarmBits(IntFlag):
    """Subcode bits of an alarm STATUS."""

    FAR_FROM_TRAINING = 1  # the marker input lies far from every simulated deformation
    INCONSISTENT_MARKERS = 2  # a marker is far from where the others place it
    STILL_MARKER = 32  # a marker stood still where every simulation moved it (the tissue held there?)
    SWAPPED_MARKERS = 64  # two markers look exchanged: the markers agree far better with them swapped back


class RefusalBits(IntFlag):
    """Subcode bits of an ``InputRefused`` STATUS (the input gate, :mod:`tissuecast.surrogate.gate`)."""

    NON_FINITE = 4  # a marker's position is NaN or infinite
    BEYOND_SIMULATED = 8  # a marker displaced far beyond its largest simulated displacement
    IMPOSSIBLE_GEOMETRY = 16  # two markers at a distance the body cannot take (swapped, mislabelled)


def refusal_bits(reason: str) -> int:
    """The :class:`RefusalBits` of a gate refusal's reason (``"non-finite"``, ``"displacement"``, ``"stretch"``)."""
    return int({"non-finite": RefusalBits.NON_FINITE, "displacement": RefusalBits.BEYOND_SIMULATED,
                "stretch": RefusalBits.IMPOSSIBLE_GEOMETRY}.get(reason, 0))


class StatusMessage(pyigtl.MessageBase):
    """A STATUS message as a pyigtl message.

    Args:
        code: :class:`StatusCode` value.  subcode: int64 detail (here :class:`AlarmBits`).
        error_name: at most 20 ASCII characters.  status_message: ASCII text.
    """

    def __init__(self, code: int = StatusCode.OK, subcode: int = 0, error_name: str = "", status_message: str = "",
                 timestamp=None, device_name=None):
        super().__init__(timestamp=timestamp, device_name=device_name)
        self._message_type = "STATUS"
        self.code, self.subcode, self.error_name, self.status_message = int(code), int(subcode), error_name, status_message

    def _pack_content(self):
        text = self.status_message.encode("ascii", "backslashreplace")
        return _FIXED.pack(self.code, self.subcode, self.error_name.encode("ascii")[:20]) + text + b"\0"

    def _unpack_content(self, content):
        if len(content) < _FIXED.size:
            raise ValueError(f"a STATUS body has at least {_FIXED.size} bytes, got {len(content)}")
        code, sub, name = _FIXED.unpack_from(content)
        self.code, self.subcode = code, sub
        self.error_name = name.rstrip(b"\0").decode("ascii", "replace")
        self.status_message = bytes(content[_FIXED.size:]).split(b"\0", 1)[0].decode("ascii", "replace")


def pack_status(code: int, subcode: int, error_name: str, text: str, timestamp: float | None = None,
                device_name: str = STATUS_DEVICE) -> bytes:
    """A packed STATUS message (version-1 header)."""
    return StatusMessage(code, subcode, error_name, text[:60000], timestamp=timestamp, device_name=device_name).pack()


def decode_status(content) -> StatusMessage:
    """The fields of a STATUS content (body without extended header and metadata).

    Raises:
        ProtocolError: (not fatal) content shorter than its 30 fixed bytes.
    """
    message = StatusMessage()
    try:
        message._unpack_content(bytes(content))
    except ValueError as exc:
        raise ProtocolError(str(exc)) from exc
    return message


def register_status_message() -> None:
    """Let ``pyigtl.OpenIGTLinkClient`` decode STATUS messages (as :class:`StatusMessage`)."""
    pyigtl.messages.message_type_to_class_constructor.setdefault("STATUS", StatusMessage)
