"""A small blocking OpenIGTLink client for the tissuecast server (tests, benchmarks, examples).

Messages are packed with pyigtl; replies are read with a blocking socket (no polling
thread, unlike ``pyigtl.OpenIGTLinkClient``, which sleeps in 10 ms steps and cannot decode
POLYDATA) and decoded with :func:`~tissuecast.serve.polydata.decode_polydata`.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

import numpy as np

from ..config import ServeConfig
from .polydata import PolyData, decode_polydata
from .predictor import FIELD_DEVICE
from .protocol import (HEADER_SIZE, Header, ProtocolError, decode_string, message_content, pack_header, parse_header,
                       pyigtl)
from .session import MARKER_PREFIX

__all__ = ["IGTLClient", "Reply"]

#: Seconds a blocking read waits for the server (a reply takes milliseconds; a silent server
#: is a failure, not a delay).
REPLY_TIMEOUT_S = 5.0
#: Largest reply body read (the server is trusted; the check only stops a corrupt header).
MAX_REPLY_BYTES = 1 << 31
#: Starting size of the reusable body buffer (grows to the largest reply).
BODY_BUFFER_BYTES = 1 << 16


@dataclass(frozen=True)
class Reply:
    """One message received from the server.

    Attributes:
        header: its parsed header (``message_type``, ``device_name``, ``timestamp``...).
        polydata: the decoded POLYDATA, or None.
        text: the text of a STRING message (e.g. an ``ERROR`` reply) or of a STATUS message, or None.
        status: a STATUS message's fields (:class:`~tissuecast.serve.status.StatusMessage`), or None.
    """

    header: Header
    polydata: PolyData | None = None
    text: str | None = None
    status: object | None = None

    @property
    def is_error(self) -> bool:
        return self.header.message_type == "STRING" and self.header.device_name == "ERROR"


class IGTLClient:
    """A blocking connection to an OpenIGTLink server.

    Args:
        host, port: server address.
        timeout: seconds to wait for a reply before ``socket.timeout`` (TimeoutError).
    """

    def __init__(self, host: str = ServeConfig.host, port: int = ServeConfig.port, timeout: float = REPLY_TIMEOUT_S):
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._header = bytearray(HEADER_SIZE)
        self._body = bytearray(BODY_BUFFER_BYTES)

    # ------------------------------------------------------------------ sending
    def send(self, message: pyigtl.MessageBase | bytes) -> None:
        """Send a pyigtl message or already packed bytes."""
        self.sock.sendall(message.pack() if isinstance(message, pyigtl.MessageBase) else message)

    def send_positions(self, positions: np.ndarray, device_name: str = "Markers", timestamp: float | None = None) -> None:
        """Send (n_d, 3) marker positions (mm) as one POINT message."""
        positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.send(pyigtl.PointMessage(positions, device_name=device_name, timestamp=timestamp))

    def send_transforms(self, positions: np.ndarray, timestamp: float | None = None) -> None:
        """Send (n_d, 3) marker positions (mm) as TRANSFORM messages ``Marker0``.. in one write."""
        stamp = time.time() if timestamp is None else timestamp
        packed = []
        for index, xyz in enumerate(np.asarray(positions, dtype=np.float32).reshape(-1, 3)):
            matrix = np.eye(4, dtype=np.float32)
            matrix[:3, 3] = xyz
            packed.append(pyigtl.TransformMessage(matrix, device_name=f"{MARKER_PREFIX}{index}", timestamp=stamp).pack())
        self.sock.sendall(b"".join(packed))

    def request(self, message_type: str, device_name: str) -> None:
        """Send a body-less message such as ``GET_POLYDATA``."""
        self.send(pack_header(message_type, device_name, time.time(), 0, 0))  # no body: its CRC-64 is 0

    def request_field(self) -> None:
        """Ask for the full vertex field of the latest prediction (``GET_POLYDATA TissueField``)."""
        self.request("GET_POLYDATA", FIELD_DEVICE)

    # ------------------------------------------------------------------ receiving
    def _read_into(self, view: memoryview) -> None:
        got = 0
        while got < len(view):
            n = self.sock.recv_into(view[got:])
            if n == 0:
                raise ConnectionError("the server closed the connection")
            got += n

    def receive(self, verify_crc: bool = True) -> Reply:
        """Block until one whole message has arrived and decode it.

        Raises:
            ConnectionError: the server closed the connection.
            TimeoutError: nothing arrived within the timeout.
            ProtocolError: the reply is malformed (or its CRC is wrong).
        """
        self._read_into(memoryview(self._header))
        header = parse_header(bytes(self._header), max_body_bytes=MAX_REPLY_BYTES)
        if header.body_size > len(self._body):
            self._body = bytearray(header.body_size)
        body = memoryview(self._body)[: header.body_size]
        self._read_into(body)
        if verify_crc:
            content = message_content(header, body)
        else:
            content = body if header.version == 1 else message_content(header, body)
        if header.message_type == "POLYDATA":
            return Reply(header, polydata=decode_polydata(content))
        if header.message_type == "STRING":
            return Reply(header, text=decode_string(header, content))
        if header.message_type == "STATUS":
            from .status import decode_status

            status = decode_status(content)
            return Reply(header, text=status.status_message, status=status)
        return Reply(header)

    def predict(self, positions: np.ndarray) -> Reply:
        """Send positions as POINT and wait for the reply; raises ProtocolError on an ERROR reply."""
        self.send_positions(positions)
        reply = self.receive()
        if reply.is_error:
            raise ProtocolError(f"server error: {reply.text}")
        return reply

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> "IGTLClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
