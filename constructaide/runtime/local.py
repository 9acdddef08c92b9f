"""In-process bus with the same semantics as :class:`ZenohBus` (for node-logic tests).

Delivery is synchronous on the publisher's thread: a node's queue provides the asynchrony, as
with zenoh. Liveliness tokens and latched values behave as on zenoh.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from constructaide.runtime.bus import Bus, Callback, Closeable, _Closer, ke_match, payload_of
from constructaide.runtime.history import Publication, PublicationCache
from schemas.messages import Message


class LocalBus(Bus):
    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._subs: dict[int, tuple[str, Callback]] = {}
        self._tokens: dict[int, str] = {}
        self._token_watchers: dict[int, tuple[str, Callable[[str, bool], None]]] = {}
        self._latched: dict[str, bytes] = {}
        self._next = 0
        self.published: list[str] = []
        self.cache = PublicationCache(64_000_000)

    def _drop(self, table: dict[int, Any], entry_id: int) -> None:
        with self._lock:
            table.pop(entry_id, None)

    def _id(self) -> int:
        self._next += 1
        return self._next

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False, latched: bool = False) -> None:
        payload = bytes(payload_of(msg))
        with self._lock:
            if latched:
                self._latched[key] = payload
            self.published.append(key)
            if not preview:
                self.cache.add(key, payload)
            targets = [cb for ke, cb in self._subs.values() if ke_match(ke, key)]
        for cb in targets:
            cb(key, payload)

    def subscribe(self, keyexpr: str, callback: Callback, *, fetch_latched: bool = False) -> Closeable:
        with self._lock:
            sid = self._id()
            self._subs[sid] = (keyexpr, callback)
            latched = [(k, v) for k, v in self._latched.items() if ke_match(keyexpr, k)] if fetch_latched else []
        for k, v in latched:
            callback(k, v)
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
