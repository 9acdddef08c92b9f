"""Polling folder watcher (cameras uploading by FTP/SMB) and a bounded set of seen content hashes.

No threads here: the owner calls :meth:`FolderWatcher.poll` periodically. A file is *ready* once
its size and mtime were the same on two consecutive polls (an upload in progress keeps
changing). Files are never moved or deleted.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from collections.abc import Iterable
from pathlib import Path

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
Signature = tuple[tuple[int, int], ...]
"""(size, mtime_ns) per file; (-1, -1) for a file that cannot be read."""
PARTIAL_SUFFIXES = (".part", ".tmp", ".partial", ".crdownload", ".filepart")


def file_signature(paths: Iterable[Path]) -> Signature:
    """The :data:`Signature` of files, in order."""
    out = []
    for p in paths:
        try:
            st = p.stat()
            out.append((st.st_size, st.st_mtime_ns))
        except OSError:
            out.append((-1, -1))
    return tuple(out)


def settled_change(current: Signature, loaded: Signature | None, previous: Signature | None) -> bool:
    """Whether to reload files: their signature differs from what was loaded and was the same on the previous poll
    (a file still being written changes between polls)."""
    return current != loaded and current == previous


class SeenHashes:
    """Bounded LRU set of content hashes, optionally persisted one hash per line.

    ``add`` returns False when the hash was already present (a duplicate). Thread-safe.
    """

    def __init__(self, capacity: int = 100_000, path: str | Path | None = None) -> None:
        self.capacity = max(1, capacity)
        self.path = Path(path) if path else None
        self._items: OrderedDict[str, None] = OrderedDict()
        self._lock = threading.Lock()
        self._file_lines = 0
        if self.path is not None and self.path.is_file():
            lines = self.path.read_text(encoding="ascii", errors="ignore").splitlines()
            self._file_lines = len(lines)
            for line in lines:
                if line.strip():
                    self._items[line.strip()] = None
                    self._items.move_to_end(line.strip())
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)

    def __contains__(self, h: object) -> bool:
        with self._lock:
            return h in self._items

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def add(self, h: str) -> bool:
        """Record ``h``; False if it was seen before (it becomes most recent either way)."""
        with self._lock:
            if h in self._items:
                self._items.move_to_end(h)
                return False
            self._items[h] = None
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)
            if self.path is not None:
                # Append; compact the file once it holds twice the capacity.
                with self.path.open("a", encoding="ascii") as fh:
                    fh.write(h + "\n")
                self._file_lines += 1
                if self._file_lines > 2 * self.capacity:
                    self._save_locked()
            return True

    def save(self) -> None:
        """Rewrite the persisted file with the current contents (atomic replace)."""
        with self._lock:
            self._save_locked()

    def _save_locked(self) -> None:
        if self.path is None:
            return
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        tmp.write_text("".join(h + "\n" for h in self._items), encoding="ascii")
        os.replace(tmp, self.path)
        self._file_lines = len(self._items)


def content_hash(data: bytes) -> str:
    """sha256 hex (16 characters) of raw bytes: the dedupe key of uploaded files."""
    return hashlib.sha256(data).hexdigest()[:16]


class FolderWatcher:
    """Finds new, completely written photo files under ``root`` (recursively).

    Hidden files and names ending in a partial-upload suffix are ignored. Each file (path, size,
    mtime) is reported once; a file rewritten with new content is reported again.
    """

    def __init__(self, root: str | Path, suffixes: Iterable[str] = PHOTO_SUFFIXES, recursive: bool = True) -> None:
        self.root = Path(root)
        self.suffixes = tuple(s.lower() for s in suffixes)
        self.recursive = recursive
        self._pending: dict[Path, tuple[int, int]] = {}
        self._done: dict[Path, tuple[int, int]] = {}

    def _candidates(self) -> Iterable[Path]:
        if not self.root.is_dir():
            return []
        it = self.root.rglob("*") if self.recursive else self.root.iterdir()
        out = []
        for p in it:
            rel = p.relative_to(self.root)
            if any(part.startswith(".") for part in rel.parts):
                continue
            name = p.name.lower()
            if name.endswith(PARTIAL_SUFFIXES) or not name.endswith(self.suffixes):
                continue
            out.append(p)
        return sorted(out)

    def poll(self) -> list[Path]:
        """Files whose size and mtime did not change since the previous poll and that were not
        reported before, in path order."""
        ready: list[Path] = []
        seen_now: set[Path] = set()
        for p in self._candidates():
            try:
                st = p.stat()
            except OSError:
                continue  # vanished between listing and stat
            if not p.is_file():
                continue
            sig = (st.st_size, st.st_mtime_ns)
            seen_now.add(p)
            if self._done.get(p) == sig:
                continue
            if self._pending.get(p) == sig and st.st_size > 0:
                ready.append(p)
                self._done[p] = sig
                self._pending.pop(p, None)
            else:
                self._pending[p] = sig
        for gone in [p for p in self._pending if p not in seen_now]:
            del self._pending[gone]
        for gone in [p for p in self._done if p not in seen_now]:
            del self._done[gone]
        return ready
