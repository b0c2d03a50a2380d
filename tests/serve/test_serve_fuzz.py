"""Fuzzing the OpenIGTLink server with more than 10,000 random and mutated messages.

Two streams, both over real loopback sockets:

- on long-lived connections, messages whose framing is intact (bad CRC, unknown type, wrong
  point count, NaN/inf, implausible positions, wrong content sizes, random bodies with a
  valid CRC, valid requests mixed in) are pipelined in batches; each must get exactly one
  well-formed reply: STRING ERROR for bad input, the correct POLYDATA for valid input;
- on fresh connections, messages that may break the framing (random bytes, random bit
  flips anywhere, truncation, huge or garbage header fields) are sent, the client
  half-closes, and every byte the server sends back must parse as well-formed replies.

Afterwards the server must still answer a valid request correctly, with nothing leaked.
"""

from __future__ import annotations

import socket
import struct
import time

import numpy as np
import pyigtl
import pytest
from pyigtl.messages import CRC64
from serve_support import small_model

from tissuecast.serve import IGTLClient, IGTLServer
from tissuecast.serve.polydata import decode_polydata
from tissuecast.serve.protocol import HEADER_SIZE, decode_string, message_content, parse_header
from tissuecast.serve.status import decode_status

pytestmark = pytest.mark.timeout(180)

_HEADER = struct.Struct("> H 12s 20s I I Q Q")


def frame(mtype: bytes, device: bytes, body: bytes, version: int = 1, crc: int | None = None) -> bytes:
    crc = CRC64(body) if crc is None else crc
    return _HEADER.pack(version, mtype, device, 1, 0, len(body), crc) + body


def parse_stream(data: bytes) -> list:
    """Split received bytes into (type, device, text-or-polydata); every message must be well formed."""
    out, at = [], 0
    while at < len(data):
        header = parse_header(data[at : at + HEADER_SIZE], max_body_bytes=1 << 24)
        body = data[at + HEADER_SIZE : at + HEADER_SIZE + header.body_size]
        content = message_content(header, body)
        if header.message_type == "STRING":
            out.append(("STRING", header.device_name, decode_string(header, content)))
        elif header.message_type == "STATUS":  # the input gate's refusals and all-clears (serve/status.py)
            status = decode_status(content)
            assert status.error_name in ("InputRefused", "") and header.device_name == "TissueStatus"
            out.append(("STATUS", header.device_name, status.status_message))
        else:
            assert header.message_type == "POLYDATA"
            out.append(("POLYDATA", header.device_name, decode_polydata(content)))
        at += HEADER_SIZE + header.body_size
    return out


class Fuzzer:
    def __init__(self, model, seed: int):
        self.model = model
        self.rng = np.random.default_rng(seed)
        self.ref = model.reference_marker_positions
        self.n_d = model.n_markers

    def points(self, positions) -> bytes:
        return pyigtl.PointMessage(np.asarray(positions, np.float32), device_name="Markers").pack()

    def valid(self) -> tuple[bytes, np.ndarray]:
        positions = (self.ref + self.rng.normal(0, 2, self.ref.shape)).astype(np.float32).astype(np.float64)
        if self.rng.random() < 0.3:
            msg = pyigtl.PointMessage(positions.astype(np.float32), device_name="Markers")
            msg.header_version = 2
            msg.metadata = {"fuzz": "yes"}
            return msg.pack(), positions
        return self.points(positions), positions

    def framed_bad(self) -> bytes:
        """A message with intact framing but bad content: the server must reply with one error."""
        rng, kind = self.rng, self.rng.integers(9)
        if kind == 0:  # bad CRC: flip a body byte
            raw = bytearray(self.valid()[0])
            raw[HEADER_SIZE + rng.integers(len(raw) - HEADER_SIZE)] ^= 1 << rng.integers(8)
            return bytes(raw)
        if kind == 1:  # bad CRC field
            raw = bytearray(self.valid()[0])
            raw[50 + rng.integers(8)] ^= 1 << rng.integers(8)
            return bytes(raw)
        if kind == 2:  # unknown type, random body
            name = bytes(rng.integers(65, 91, rng.integers(1, 13)).astype(np.uint8))
            return frame(name.ljust(12, b"\0"), b"X", rng.bytes(rng.integers(0, 200)))
        if kind == 3:  # wrong point count
            k = int(rng.choice([c for c in range(1, 12) if c != self.n_d]))
            return self.points(self.ref[np.arange(k) % self.n_d] + 1.0)
        if kind == 4:  # NaN / inf
            p = self.ref.copy()
            p[rng.integers(self.n_d), rng.integers(3)] = rng.choice([np.nan, np.inf, -np.inf])
            return self.points(p)
        if kind == 5:  # implausible positions (unit or frame error)
            return self.points(self.ref * 1000.0 + 1e4)
        if kind == 6:  # TRANSFORM with wrong content size or unknown device
            if rng.random() < 0.5:
                return frame(b"TRANSFORM", b"Marker0", rng.bytes(int(rng.choice([0, 12, 47, 49, 96]))))
            return pyigtl.TransformMessage(np.eye(4), device_name=f"Tool{rng.integers(100)}").pack()
        if kind == 7:  # random body with a valid CRC under a known type
            mtype = [b"POINT", b"STRING", b"GET_POLYDATA"][rng.integers(3)]
            body = rng.bytes(int(rng.integers(1, 300)))
            if mtype == b"POINT" and len(body) % 136 == 0:
                body += b"\0"
            return frame(mtype, b"Markers", body)
        # kind 8: header version 2 with inconsistent extended-header sizes
        body = struct.pack(">H H I I", int(rng.integers(0, 40)), 0, int(rng.integers(100, 10**6)), 0) + rng.bytes(20)
        return frame(b"POINT", b"Markers", body, version=2)

    def breaking(self) -> bytes:
        """A message that may break the framing (sent on a fresh connection)."""
        rng, kind = self.rng, self.rng.integers(5)
        raw = bytearray(self.valid()[0] if rng.random() < 0.7 else self.framed_bad())
        if kind == 0:
            return rng.bytes(int(rng.integers(0, 400)))
        if kind == 1:  # bit flips anywhere, header included
            for _ in range(rng.integers(1, 9)):
                raw[rng.integers(len(raw))] ^= 1 << rng.integers(8)
            return bytes(raw)
        if kind == 2:  # truncated
            return bytes(raw[: rng.integers(0, len(raw))])
        if kind == 3:  # huge body size
            raw[42:50] = struct.pack(">Q", int(rng.integers(1 << 17, 1 << 63)))
            return bytes(raw)
        raw[0:2] = struct.pack(">H", int(rng.integers(3, 65536)))  # unknown header version
        return bytes(raw)


def check_surface(poly, model, positions):
    u = model.predict(positions - model.reference_marker_positions)
    expected = (model.mesh.points + u)[model.mesh.surface_vertices]
    np.testing.assert_allclose(poly.points, expected, atol=1e-4)


def test_fuzz_ten_thousand_messages():
    model = small_model("single")
    fuzz = Fuzzer(model, seed=20261122)
    counts = {"framed": 0, "breaking": 0, "errors": 0, "valid": 0, "status": 0}
    with IGTLServer(model, "127.0.0.1", 0, client_timeout=1.0, max_body_bytes=1 << 16) as server:
        # 1) pipelined framed messages on long-lived connections: exactly one reply each
        for _ in range(7):
            with IGTLClient(*server.address, timeout=10) as client:
                for _ in range(50):
                    batch, expect = [], []
                    for _ in range(20):
                        if fuzz.rng.random() < 0.15:
                            raw, positions = fuzz.valid()
                            expect.append(positions)
                        else:
                            raw = fuzz.framed_bad()
                            expect.append(None)
                        batch.append(raw)
                    client.send(b"".join(batch))
                    counts["framed"] += len(batch)
                    for positions in expect:
                        reply = client.receive()
                        while reply.header.message_type == "STATUS":  # the input gate's refusals and all-clears
                            counts["status"] += 1
                            reply = client.receive()
                        if positions is None:
                            assert reply.is_error, reply.header
                            counts["errors"] += 1
                        else:
                            assert reply.polydata is not None, reply.text
                            check_surface(reply.polydata, model, positions)
                            counts["valid"] += 1
        # 2) framing breakers on fresh connections, 1-4 messages each, then half-close
        while counts["breaking"] < 3000:
            batch = [fuzz.breaking() for _ in range(int(fuzz.rng.integers(1, 5)))]
            with socket.create_connection(server.address, timeout=10) as sock:
                sock.sendall(b"".join(batch))
                sock.shutdown(socket.SHUT_WR)
                data = bytearray()
                while chunk := sock.recv(1 << 16):
                    data += chunk
            for kind, device, _ in parse_stream(bytes(data)):
                assert (kind, device) in {("STRING", "ERROR"), ("POLYDATA", "TissueSurface"), ("STATUS", "TissueStatus")}
            counts["breaking"] += len(batch)
        total = counts["framed"] + counts["breaking"]
        assert total >= 10_000
        # 3) the server is intact: a valid request is answered correctly, no connection leaked
        with IGTLClient(*server.address, timeout=5) as client:
            raw, positions = fuzz.valid()
            started = time.perf_counter()
            client.send(raw)
            reply = client.receive()
            elapsed = time.perf_counter() - started
            check_surface(reply.polydata, model, positions)
        deadline = time.monotonic() + 5
        while server.n_clients and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.n_clients == 0
        assert server.stats["connections"] == server.stats["disconnections"]
        assert server._thread.is_alive()
        assert server.stats["internal_errors"] == 0
    print(f"fuzz: {total} messages ({counts}), post-fuzz round trip {elapsed * 1e3:.2f} ms, server stats {dict(server.stats)}")
