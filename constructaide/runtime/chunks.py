"""Large bus payloads in bounded parts: splitting on the publisher, reassembly on the subscriber.

A payload longer than ``chunk_bytes`` travels as ``count`` parts of at most ``chunk_bytes`` each; every part
carries a :class:`PartHeader` beside the payload (a zenoh attachment, :data:`HEADER_BYTES` bytes): the transfer id
(16 random bytes, one per publication), the sha256 of the whole payload, the part index, the part count and the
total size. A payload of at most ``chunk_bytes`` goes unchanged, without a header.

The receiving side (:class:`Receiver`, one per subscription) keeps the parts per (key, transfer id) and calls the
callback once with the whole payload, only when every part arrived and the sha256 matches; a transfer already
delivered is not delivered again (the same publication seen live and through a latched fetch). Incomplete
transfers are bounded by bytes held (the oldest dropped first, with a warning).

Pure: no zenoh.
"""

from __future__ import annotations

import collections
import hashlib
import logging
import os
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

log = logging.getLogger("constructaide.bus")

MAGIC = b"CAk1"
_HEAD = struct.Struct("<4s16s32sIIQ")  # magic, transfer id, sha256 of the whole payload, index, count, total bytes
HEADER_BYTES = _HEAD.size
REMEMBER_DELIVERED = 256
"""Transfer ids a receiver remembers as delivered (their late duplicate parts are ignored)."""


@dataclass(frozen=True)
class PartHeader:
    transfer_id: bytes
    """16 bytes, one per publication."""
    digest: bytes
    """sha256 of the whole payload (32 bytes)."""
    index: int
    count: int
    total: int
    """Bytes of the whole payload."""

    def encode(self) -> bytes:
        return _HEAD.pack(MAGIC, self.transfer_id, self.digest, self.index, self.count, self.total)

    @classmethod
    def decode(cls, raw: bytes | None) -> PartHeader | None:
        """The header in ``raw``; None when ``raw`` is not a part header (no attachment, or another one)."""
        if raw is None or len(raw) != HEADER_BYTES or not raw.startswith(MAGIC):
            return None
        _, tid, dig, index, count, total = _HEAD.unpack(raw)
        return cls(tid, dig, index, count, total)


def needs_chunks(size: int, chunk_bytes: int) -> bool:
    """Whether a payload of ``size`` bytes travels in parts (``chunk_bytes`` <= 0: never)."""
    return 0 < chunk_bytes < size


@dataclass
class Transfer:
    """One publication's payload and how it goes on the wire with parts of at most ``chunk_bytes``."""

    payload: bytes
    chunk_bytes: int
    transfer_id: bytes = field(default_factory=lambda: os.urandom(16))
    _digest: bytes | None = field(default=None, repr=False)

    @property
    def chunked(self) -> bool:
        return needs_chunks(len(self.payload), self.chunk_bytes)

    @property
    def digest(self) -> bytes:
        if self._digest is None:
            self._digest = hashlib.sha256(self.payload).digest()
        return self._digest

    def parts(self) -> Iterator[tuple[bytes | None, bytes]]:
        """``(header, part)`` in order; one ``(None, payload)`` when the payload is not chunked."""
        if not self.chunked:
            yield None, self.payload
            return
        n, size = -(-len(self.payload) // self.chunk_bytes), len(self.payload)
        view = memoryview(self.payload)
        for i in range(n):
            head = PartHeader(self.transfer_id, self.digest, i, n, size).encode()
            yield head, bytes(view[i * self.chunk_bytes : (i + 1) * self.chunk_bytes])


@dataclass
class _Pending:
    head: PartHeader
    parts: dict[int, bytes] = field(default_factory=dict)
    nbytes: int = 0


class Reassembler:
    """Parts of the transfers in progress, per (key, transfer id), at most ``max_bytes`` held. Thread-safe."""

    def __init__(self, max_bytes: int, name: str = "") -> None:
        self.max_bytes = max_bytes
        self.name = name
        self._pending: collections.OrderedDict[tuple[str, bytes], _Pending] = collections.OrderedDict()
        self._finished: collections.OrderedDict[tuple[str, bytes], None] = collections.OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.dropped = 0
        """Transfers given up: evicted incomplete, too large, inconsistent or with a wrong digest."""

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._pending)

    def add(self, key: str, head: PartHeader, part: bytes) -> bytes | None:
        """Take one part; the whole payload when it completes a transfer whose sha256 matches, else None."""
        tid = (key, head.transfer_id)
        with self._lock:
            if tid in self._finished:
                return None
            pending = self._pending.get(tid)
            if pending is None:
                if not self._plausible(head, part):
                    self._drop_new(key, head, "inconsistent part header")
                    return None
                if head.total > self.max_bytes:
                    self._drop_new(key, head, f"{head.total} bytes exceed the reassembly buffer ({self.max_bytes})")
                    return None
                pending = self._pending[tid] = _Pending(head)
            elif (head.digest, head.count, head.total) != (pending.head.digest, pending.head.count, pending.head.total):
                self._give_up(tid, "parts disagree on the transfer")
                return None
            if head.index in pending.parts:
                return None  # a duplicate part: the first copy is kept
            if head.index >= head.count or len(part) > head.total - pending.nbytes:
                self._give_up(tid, f"part {head.index} does not fit the transfer")
                return None
            pending.parts[head.index] = part
            pending.nbytes += len(part)
            self._bytes += len(part)
            self._evict(keep=tid)
            if len(pending.parts) < head.count:
                return None
            del self._pending[tid]
            self._bytes -= pending.nbytes
            whole = b"".join(pending.parts[i] for i in range(head.count))
            if len(whole) != head.total or hashlib.sha256(whole).digest() != head.digest:
                self.dropped += 1
                self._finish(tid)
                log.warning(
                    "%s: dropped a %d-byte transfer on %s: the sha256 does not match", self.name, head.total, key
                )
                return None
            self._finish(tid)
            return whole

    def _finish(self, tid: tuple[str, bytes]) -> None:
        """Remember a transfer as done (delivered or given up): its late parts are ignored."""
        self._finished[tid] = None
        while len(self._finished) > REMEMBER_DELIVERED:
            self._finished.popitem(last=False)

    @staticmethod
    def _plausible(head: PartHeader, part: bytes) -> bool:
        return 1 <= head.count and head.index < head.count and 0 < len(part) <= head.total and head.count <= head.total

    def _drop_new(self, key: str, head: PartHeader, why: str) -> None:
        self.dropped += 1
        self._finish((key, head.transfer_id))  # its other parts are ignored too
        log.warning("%s: dropped a transfer on %s: %s", self.name, key, why)

    def _give_up(self, tid: tuple[str, bytes], why: str) -> None:
        pending = self._pending.pop(tid)
        self._bytes -= pending.nbytes
        self.dropped += 1
        self._finish(tid)
        log.warning("%s: dropped a transfer on %s: %s", self.name, tid[0], why)

    def _evict(self, keep: tuple[str, bytes]) -> None:
        """Drop the oldest incomplete transfers (not ``keep``) until the bytes held fit ``max_bytes``."""
        while self._bytes > self.max_bytes:
            victim = next((t for t in self._pending if t != keep), None)
            if victim is None:
                return
            p = self._pending[victim]
            self._give_up(victim, f"incomplete ({len(p.parts)}/{p.head.count} parts) and the reassembly buffer is full")


def unpack(parts: Reassembler, key: str, payload: bytes, attachment: bytes | None) -> bytes | None:
    """The whole payload a sample completes: itself when ``attachment`` is no part header, else what ``parts``
    returns for the part (None until the transfer completes)."""
    head = PartHeader.decode(attachment)
    return payload if head is None else parts.add(key, head, payload)


class Receiver:
    """The receiving end of one subscription: payloads with no part header go straight to ``callback(key,
    payload)``; parts go through a :class:`Reassembler` and the callback gets each whole payload once."""

    def __init__(self, callback: Callable[[str, bytes], None], max_bytes: int, name: str = "") -> None:
        self.callback = callback
        self.reassembler = Reassembler(max_bytes, name)

    def unpack(self, key: str, payload: bytes, attachment: bytes | None) -> bytes | None:
        """The whole payload this sample completes (itself when it is not a part), or None."""
        return unpack(self.reassembler, key, payload, attachment)

    def __call__(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        whole = self.unpack(key, payload, attachment)
        if whole is not None:
            self.callback(key, whole)
