"""Wire format between the host and a sandbox worker: length-prefixed JSON frames.

JSON, never pickle: the host must not deserialize anything executable from a process that
runs untrusted code. Arrays travel as ``[shape, dtype, base64 of the raw bytes]``.

Invariants:
1. ``decode_frame_body(encode_frame(m)[4:]) == m`` for every JSON-able mapping ``m``.
2. :func:`decode_arrays` rebuilds arrays equal in shape, dtype and bits to those
   :func:`encode_arrays` encoded, and raises :class:`ProtocolError` (never anything else)
   on a malformed entry.
3. :class:`FrameReader` never buffers more than ``max_frame`` bytes of one frame: a longer
   announced length is a :class:`ProtocolError` before any of the body is read.
"""

from __future__ import annotations

import base64
import json
import os
import select
import struct
import time
from collections.abc import Mapping
from typing import Any, BinaryIO

import numpy as np

HEADER = struct.Struct(">I")
MAX_REQUEST_BYTES = 16 * 1024 * 1024
MAX_REPLY_BYTES = 1024 * 1024
WIRE_DTYPES: frozenset[str] = frozenset({"float32", "float64", "int32", "int64", "bool", "uint8"})


class ProtocolError(Exception):
    """The peer sent bytes that are not a valid frame."""


class PeerClosed(Exception):
    """The peer closed its end of the pipe (it exited or was killed)."""


def encode_frame(message: Mapping[str, Any]) -> bytes:
    """``message`` as one frame: 4-byte big-endian length, then compact JSON."""
    body = json.dumps(message, separators=(",", ":"), allow_nan=True).encode()
    return HEADER.pack(len(body)) + body


def decode_frame_body(body: bytes) -> dict[str, Any]:
    """Parse one frame body.

    Raises:
        ProtocolError: not JSON, or not a JSON object.
    """
    try:
        msg = json.loads(body)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"frame is not JSON: {exc}") from None
    if not isinstance(msg, dict):
        raise ProtocolError(f"frame is a JSON {type(msg).__name__}, expected an object")
    return msg


def encode_arrays(arrays: Mapping[str, np.ndarray]) -> dict[str, list[Any]]:
    """Arrays as JSON-able ``[shape, dtype, base64]`` triples."""
    out: dict[str, list[Any]] = {}
    for key, arr in arrays.items():
        a = np.asarray(arr)  # not ascontiguousarray: it turns 0-d arrays into 1-d
        out[key] = [list(a.shape), a.dtype.name, base64.b64encode(a.tobytes(order="C")).decode("ascii")]
    return out


def decode_arrays(wire: object) -> dict[str, np.ndarray]:
    """Read-only arrays from :func:`encode_arrays` output.

    Raises:
        ProtocolError: a malformed entry.
    """
    if not isinstance(wire, dict):
        raise ProtocolError("arrays must be an object")
    out: dict[str, np.ndarray] = {}
    for key, entry in wire.items():
        try:
            shape, dtype, data = entry
            if dtype not in WIRE_DTYPES:
                raise ProtocolError(f"array {key!r}: dtype {dtype!r} not allowed")
            shape_t = tuple(int(s) for s in shape)
            arr = np.frombuffer(base64.b64decode(data, validate=True), dtype=np.dtype(dtype)).reshape(shape_t)
        except ProtocolError:
            raise
        except (TypeError, ValueError) as exc:
            raise ProtocolError(f"array {key!r} is malformed: {exc}") from None
        out[str(key)] = arr  # frombuffer over bytes is already read-only
    return out


def read_frame_blocking(stream: BinaryIO, *, max_frame: int = MAX_REQUEST_BYTES) -> dict[str, Any]:
    """Read one frame from a blocking stream (the worker's stdin).

    Raises:
        PeerClosed: end of stream.
        ProtocolError: oversize or malformed frame.
    """
    header = _read_exact(stream, HEADER.size)
    (length,) = HEADER.unpack(header)
    if length > max_frame:
        raise ProtocolError(f"frame of {length} bytes exceeds the limit of {max_frame}")
    return decode_frame_body(_read_exact(stream, length))


def _read_exact(stream: BinaryIO, n: int) -> bytes:
    chunks: list[bytes] = []
    remaining = n
    while remaining:
        chunk = stream.read(remaining)
        if not chunk:
            raise PeerClosed("stream closed")
        chunks.append(chunk)
        remaining -= len(chunk)
    return b"".join(chunks)


class FrameReader:
    """Reads frames from a non-blocking pipe fd with a deadline (the host's side).

    Args:
        fd: Readable file descriptor.
        max_frame: Largest frame body accepted.
    """

    def __init__(self, fd: int, *, max_frame: int = MAX_REPLY_BYTES) -> None:
        self._fd = fd
        self._max = max_frame
        self._buf = bytearray()
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN | select.POLLHUP | select.POLLERR)

    def read(self, deadline: float) -> dict[str, Any]:
        """The next frame, waiting until ``deadline`` (a :func:`time.monotonic` value).

        Raises:
            TimeoutError: no complete frame by the deadline.
            PeerClosed: the writer closed the pipe.
            ProtocolError: oversize or malformed frame.
        """
        while True:
            if len(self._buf) >= HEADER.size:
                (length,) = HEADER.unpack_from(self._buf)
                if length > self._max:
                    raise ProtocolError(f"reply frame of {length} bytes exceeds the limit of {self._max}")
                end = HEADER.size + length
                if len(self._buf) >= end:
                    body = bytes(self._buf[HEADER.size : end])
                    del self._buf[:end]
                    return decode_frame_body(body)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("no reply before the deadline")
            if not self._poll.poll(max(1, int(remaining * 1000) + 1)):
                continue
            try:
                chunk = os.read(self._fd, 1 << 16)
            except BlockingIOError:
                continue
            if not chunk:
                raise PeerClosed("worker closed its output")
            self._buf += chunk
