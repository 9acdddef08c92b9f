"""Delivery across crashes: a publisher's cache of recent data publications and a node's ledger of handled input.

Every bus session keeps what it published (data topics, not previews) in a :class:`PublicationCache` bounded by
bytes, and answers history queries over it (:mod:`constructaide.runtime.bus`). A node started with a state
directory keeps a :class:`Ledger` (SQLite): on start it asks every publisher for what was published since the
ledger was created, skips what it already handled (by key and payload digest: a photo id and revision republished
byte for byte is handled once) and handles the rest in publication order. A handled message is marked done in the
same SQLite transaction as the node's state snapshot (when it has one), so a restart resumes exactly there.

Retention (:class:`Retention`): the ledger's handled rows are pruned by age (``keep_days``, default 30) and by
count (``max_rows``, default 1e6), at most every ``prune_every_secs`` and only after the start's history catch-up.
The rule that keeps delivery exactly-once: a prune that deletes the rows handled before ``cut`` moves the
ledger's history horizon (``since_ns``, what a restart asks publishers for) to ``cut + skew_margin_secs`` (never
past now). A publication the history cache could still re-deliver at the next start is then either older than
the horizon (not asked for; it was handled or queued before the prune, since the node was running and caught up)
or newer, and was handled at or after its publication time minus the clock skew, so its row is still there. The
effective retention is therefore never shorter than the bus history asked for; clock skew between publisher and
node beyond the margin could re-handle a message (at least once, never lost).

Pure: no zenoh. Times are ``time.time_ns()`` of the publisher (one clock on loopback).
"""

from __future__ import annotations

import collections
import hashlib
import math
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgspec

HISTORY_ROOT = "history"
"""Prefix of history queries: ``history/<key expression>`` asks for the cached publications under it."""


def digest(key: str, payload: bytes) -> str:
    """Identity of one publication: blake2b-128 of key and payload (hex)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(key.encode())
    h.update(b"\0")
    h.update(payload)
    return h.hexdigest()


@dataclass(frozen=True)
class Publication:
    key: str
    payload: bytes
    time_ns: int


class PublicationCache:
    """The newest publications of a session, at most ``max_bytes`` of payload (oldest dropped first)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._items: collections.deque[Publication] = collections.deque()
        self._bytes = 0
        self._lock = threading.Lock()
        self.evicted = 0

    def add(self, key: str, payload: bytes, time_ns: int | None = None) -> None:
        if self.max_bytes <= 0 or len(payload) > self.max_bytes:
            return
        pub = Publication(key, bytes(payload), time.time_ns() if time_ns is None else time_ns)
        with self._lock:
            self._items.append(pub)
            self._bytes += len(pub.payload)
            while self._bytes > self.max_bytes:
                old = self._items.popleft()
                self._bytes -= len(old.payload)
                self.evicted += 1

    def since(self, match: Callable[[str], bool], since_ns: int = 0) -> list[Publication]:
        """Cached publications at or after ``since_ns`` whose key ``match`` accepts, oldest first."""
        with self._lock:
            return [p for p in self._items if p.time_ns >= since_ns and match(p.key)]

    @property
    def nbytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)


class Retention(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """How long a ledger keeps handled-message rows (see the module docstring for the idempotence rule)."""

    keep_days: float = 30.0
    """Rows handled longer ago are pruned (0: no age limit)."""
    max_rows: int = 1_000_000
    """About this many rows at most: the oldest beyond are pruned (0: no count limit; rows of one commit share a
    time and go together)."""
    prune_every_secs: float = 3600.0
    """Least time between two prunes (a prune is one DELETE on an index; not per message)."""
    skew_margin_secs: float = 3600.0
    """Clock skew tolerated between publishers and the node: rows are kept this much longer than the horizon."""


_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS handled (digest TEXT PRIMARY KEY, key TEXT NOT NULL, handled_ns INTEGER NOT NULL);
CREATE INDEX IF NOT EXISTS handled_by_time ON handled (handled_ns);
CREATE TABLE IF NOT EXISTS state (name TEXT PRIMARY KEY, data BLOB NOT NULL, saved_ns INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS outbox (seq INTEGER PRIMARY KEY AUTOINCREMENT, key TEXT NOT NULL, payload BLOB NOT NULL,
    preview INTEGER NOT NULL);
"""
Outgoing = tuple[str, bytes, bool]
"""A held publication: key, payload, preview."""


class Ledger:
    """SQLite file of a node: what it handled (digests), since when it exists, and its state snapshots.

    Writes are transactions (WAL journal): a SIGKILL leaves the last committed state. Thread-safe.
    """

    def __init__(self, path: str | Path, retention: Retention | None = None) -> None:
        self.path = Path(path)
        self.retention = retention or Retention()
        self.pruned = 0
        """Rows pruned by this instance."""
        self._last_prune = -math.inf
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE name='since_ns'").fetchone()
            if row is None:
                self.since_ns = time.time_ns()
                self._db.execute("INSERT INTO meta VALUES ('since_ns', ?)", (str(self.since_ns),))
                self.resumed = False
            else:
                self.since_ns = int(row[0])
                self.resumed = True

    def is_done(self, dig: str) -> bool:
        with self._lock:
            return self._db.execute("SELECT 1 FROM handled WHERE digest=?", (dig,)).fetchone() is not None

    def done(self, dig: str, key: str, state: dict[str, bytes] | None = None) -> None:
        """Mark a message handled and (optionally) save state blobs, in one transaction."""
        self.done_many([(dig, key)], state)

    def done_many(
        self,
        handled: list[tuple[str, str]],
        state: dict[str, bytes] | None = None,
        outbox: list[Outgoing] | None = None,
    ) -> list[int]:
        """Mark messages ``(digest, key)`` handled, save state blobs and the publications they made (to be sent,
        each then :meth:`sent`), in one transaction; returns the outbox sequence numbers."""
        now = time.time_ns()
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._db.executemany(
                    "INSERT OR IGNORE INTO handled VALUES (?, ?, ?)", [(d, k, now) for d, k in handled]
                )
                seqs = []
                for k, p, pv in outbox or []:
                    cur = self._db.execute(
                        "INSERT INTO outbox (key, payload, preview) VALUES (?, ?, ?)", (k, p, int(pv))
                    )
                    seqs.append(int(cur.lastrowid or 0))
                self._write_state(state or {}, now)
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return seqs

    def outbox(self) -> list[tuple[int, Outgoing]]:
        """Publications committed but not confirmed sent (the node was killed in between), oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT seq, key, payload, preview FROM outbox ORDER BY seq").fetchall()
        return [(int(q), (k, bytes(p), bool(pv))) for q, k, p, pv in rows]

    def sent(self, seq: int) -> None:
        """One outbox publication went out (a crash repeats at most the one being sent)."""
        with self._lock:
            self._db.execute("DELETE FROM outbox WHERE seq=?", (seq,))

    def save_state(self, state: dict[str, bytes]) -> None:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                self._write_state(state, time.time_ns())
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def _write_state(self, state: dict[str, bytes], now_ns: int) -> None:
        """Inside a transaction: store each blob; an empty one deletes its name (state that went away)."""
        for name, data in state.items():
            if data:
                self._db.execute("INSERT OR REPLACE INTO state VALUES (?, ?, ?)", (name, data, now_ns))
            else:
                self._db.execute("DELETE FROM state WHERE name=?", (name,))

    def load_state(self) -> dict[str, bytes]:
        with self._lock:
            return {n: bytes(d) for n, d in self._db.execute("SELECT name, data FROM state")}

    def maybe_prune(self, now_ns: int | None = None) -> int:
        """:meth:`prune` when the last one is at least ``prune_every_secs`` old; rows pruned."""
        if time.monotonic() - self._last_prune < self.retention.prune_every_secs:
            return 0
        return self.prune(now_ns)

    def prune(self, now_ns: int | None = None) -> int:
        """Delete handled rows older than ``keep_days`` and the oldest beyond ``max_rows``, and move the history
        horizon (``since_ns``) past them by the skew margin (never past ``now_ns``); rows deleted. Call only once
        the start's history is queued (the runtime does)."""
        r = self.retention
        now = time.time_ns() if now_ns is None else now_ns
        self._last_prune = time.monotonic()
        cut = now - int(r.keep_days * 86_400e9) if r.keep_days > 0 else None
        with self._lock:
            if r.max_rows > 0:
                row = self._db.execute(
                    "SELECT handled_ns FROM handled ORDER BY handled_ns DESC LIMIT 1 OFFSET ?", (r.max_rows - 1,)
                ).fetchone()
                if row is not None:  # rows handled before the max_rows-th newest go
                    cut = int(row[0]) if cut is None else max(cut, int(row[0]))
            if cut is None:
                return 0
            horizon = min(now, cut + int(r.skew_margin_secs * 1e9))
            self._db.execute("BEGIN IMMEDIATE")
            try:
                n = self._db.execute("DELETE FROM handled WHERE handled_ns < ?", (cut,)).rowcount
                if n and horizon > self.since_ns:
                    self._db.execute("UPDATE meta SET value=? WHERE name='since_ns'", (str(horizon),))
                    self.since_ns = horizon
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        self.pruned += n
        return int(n)

    def handled_count(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM handled").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()


def read_state(path: str | Path) -> dict[str, bytes]:
    """The state blobs of another node's ledger file, read-only (empty when it has none or cannot be read)."""
    try:
        db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
    except sqlite3.Error:
        return {}
    try:
        return {n: bytes(d) for n, d in db.execute("SELECT name, data FROM state")}
    except sqlite3.Error:
        return {}
    finally:
        db.close()
