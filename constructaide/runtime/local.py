"""In-process bus with the same semantics as :class:`ZenohBus` (for node-logic tests).

Delivery is synchronous on the publisher's thread: a node's queue provides the asynchrony, as
with zenoh. Liveliness tokens and latched values behave as on zenoh, and so do large payloads: above
``chunk_bytes`` they go to each subscription in parts with part headers and are reassembled there
(:mod:`constructaide.runtime.chunks`); previews above it are not sent. ``wire`` counts what went "on the wire".
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from constructaide.runtime.bus import (
    Bus,
    Callback,
    Closeable,
    _Closer,
    default_chunk_buffer_bytes,
    default_chunk_bytes,
    ke_match,
    payload_of,
    warn_large_preview,
)
from constructaide.runtime.chunks import Receiver, Transfer
from constructaide.runtime.history import Publication, PublicationCache
from schemas.messages import Message


class LocalBus(Bus):
    def __init__(self, chunk_bytes: int | None = None, chunk_buffer_bytes: int | None = None) -> None:
        self._lock = threading.RLock()
        self._subs: dict[int, tuple[str, Receiver]] = {}
        self._tokens: dict[int, str] = {}
        self._token_watchers: dict[int, tuple[str, Callable[[str, bool], None]]] = {}
        self._latched: dict[str, Transfer] = {}
        self._next = 0
        self.chunk_bytes = default_chunk_bytes() if chunk_bytes is None else chunk_bytes
        self.chunk_buffer_bytes = default_chunk_buffer_bytes() if chunk_buffer_bytes is None else chunk_buffer_bytes
        self.published: list[str] = []
        self.wire: list[tuple[str, int, bool]] = []
        """(key, bytes, with a part header) of every sample sent to subscribers."""
        self.cache = PublicationCache(64_000_000)

    def _drop(self, table: dict[int, Any], entry_id: int) -> None:
        with self._lock:
            table.pop(entry_id, None)

    def _id(self) -> int:
        self._next += 1
        return self._next

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False, latched: bool = False) -> None:
        transfer = Transfer(bytes(payload_of(msg)), self.chunk_bytes)
        if preview and transfer.chunked:
            warn_large_preview(key, len(transfer.payload), self.chunk_bytes)
            return
        with self._lock:
            if latched:
                self._latched[key] = transfer
            self.published.append(key)
            if not preview:
                self.cache.add(key, transfer.payload)
            targets = [r for ke, r in self._subs.values() if ke_match(ke, key)]
        for head, part in transfer.parts():
            with self._lock:
                self.wire.append((key, len(part), head is not None))
            for receiver in targets:
                receiver(key, part, head)

    def subscribe(self, keyexpr: str, callback: Callback, *, fetch_latched: bool = False) -> Closeable:
        receiver = Receiver(callback, self.chunk_buffer_bytes, f"subscription {keyexpr}")
        with self._lock:
            sid = self._id()
            self._subs[sid] = (keyexpr, receiver)
            latched = [(k, v) for k, v in self._latched.items() if ke_match(keyexpr, k)] if fetch_latched else []
        for k, transfer in latched:
            for head, part in transfer.parts():
                receiver(k, part, head)
        return _Closer(lambda: self._drop(self._subs, sid))

    def declare_token(self, key: str) -> Closeable:
        with self._lock:
            tid = self._id()
            self._tokens[tid] = key
            watchers = [cb for ke, cb in self._token_watchers.values() if ke_match(ke, key)]
        for cb in watchers:
            cb(key, True)

        def undeclare() -> None:
            with self._lock:
                gone = self._tokens.pop(tid, None)
                ws = [cb for ke, cb in self._token_watchers.values() if gone and ke_match(ke, gone)]
            for cb in ws:
                cb(key, False)

        return _Closer(undeclare)

    def live_tokens(self, keyexpr: str, timeout: float = 2.0) -> list[str]:
        with self._lock:
            return sorted({k for k in self._tokens.values() if ke_match(keyexpr, k)})

    def watch_tokens(self, keyexpr: str, callback: Callable[[str, bool], None]) -> Closeable:
        with self._lock:
            wid = self._id()
            self._token_watchers[wid] = (keyexpr, callback)
            current = [k for k in self._tokens.values() if ke_match(keyexpr, k)]
        for k in current:
            callback(k, True)
        return _Closer(lambda: self._drop(self._token_watchers, wid))

    def history(self, keyexpr: str, since_ns: int = 0, timeout: float = 10.0) -> list[Publication]:
        return self.cache.since(lambda k: ke_match(keyexpr, k), since_ns)

    def close(self) -> None:
        with self._lock:
            self._subs.clear()
            self._token_watchers.clear()
