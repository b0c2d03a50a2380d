"""CRC-64 of OpenIGTLink bodies, with a fast path for bodies that are mostly constant.

OpenIGTLink protects each body with the CRC-64 of ECMA-182 (polynomial 0x42F0E1EBA9EA3693,
initial value 0, no final XOR), as computed by :data:`pyigtl.messages.CRC64`. With a zero
initial value and no final XOR this CRC is *linear* over GF(2):
``crc(a XOR b) = crc(a) XOR crc(b)`` for equally long inputs, and leading zero bytes do not
change it. A reply body whose layout is fixed (header words, triangles) and whose only
changing parts are a few float arrays can therefore be checked as

    crc(body) = crc(body with the changing parts zeroed)              (precomputed once)
                XOR  shift_t(crc(changing part)),   one term per changing part,

where ``shift_t`` (the effect of appending ``t`` zero bytes) is a fixed 64x64 bit matrix
applied with eight 256-entry tables. Per reply only the changing bytes are hashed.
"""

from __future__ import annotations

import numpy as np

from ..errors import require

CRC64 = require("pyigtl.messages", "serve", "OpenIGTLink messaging").CRC64

__all__ = ["CRC64", "ZeroShift", "SegmentedCrc"]


class ZeroShift:
    """The linear map ``c -> CRC64(t zero bytes, crc=c)`` (appending ``t`` zero bytes).

    Args:
        n_zero_bytes: t >= 0, the number of zero bytes appended.
    """

    def __init__(self, n_zero_bytes: int):
        zeros = bytes(int(n_zero_bytes))
        # image of each of the 64 basis bits, then byte-wise tables of all XOR combinations
        basis = np.array([CRC64(zeros, 1 << i) for i in range(64)], dtype=np.uint64)
        tables = np.zeros((8, 256), dtype=np.uint64)
        for k in range(8):
            for bit in range(8):
                size = 1 << bit
                tables[k, size : 2 * size] = tables[k, :size] ^ basis[8 * k + bit]
        self._tables = [[int(v) for v in row] for row in tables]

    def __call__(self, crc: int) -> int:
        t = self._tables
        return (
            t[0][crc & 0xFF]
            ^ t[1][(crc >> 8) & 0xFF]
            ^ t[2][(crc >> 16) & 0xFF]
            ^ t[3][(crc >> 24) & 0xFF]
            ^ t[4][(crc >> 32) & 0xFF]
            ^ t[5][(crc >> 40) & 0xFF]
            ^ t[6][(crc >> 48) & 0xFF]
            ^ t[7][(crc >> 56) & 0xFF]
        )


class SegmentedCrc:
    """CRC-64 of a fixed-length buffer in which only some byte ranges change.

    Args:
        buffer: the whole body (bytes-like); its bytes outside ``segments`` are constant.
        segments: list of ``(start, stop)`` byte ranges that change between calls, not
            overlapping.

    Call :meth:`compute` with the current buffer contents to get its CRC; only the segment
    bytes are hashed.
    """

    def __init__(self, buffer, segments: list[tuple[int, int]]):
        body = bytearray(buffer)
        length = len(body)
        self._segments = []
        for start, stop in sorted(segments):
            if not 0 <= start <= stop <= length:
                raise ValueError(f"segment ({start}, {stop}) outside a buffer of {length} bytes")
            body[start:stop] = bytes(stop - start)
            self._segments.append((start, stop, ZeroShift(length - stop)))
        self._constant = CRC64(bytes(body))
        self.length = length

    def compute(self, buffer) -> int:
        """CRC-64 of ``buffer`` (same length as at construction), hashing only the segments."""
        view = memoryview(buffer)
        crc = self._constant
        for start, stop, shift in self._segments:
            crc ^= shift(CRC64(view[start:stop]))
        return crc
