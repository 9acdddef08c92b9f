"""A recording that lasts: MCAP files rotated by size and age, retention, an index of the files, full disk handled.

:class:`RotatingRecorder` writes ``<directory>/<site>-<UTC>.mcap`` files through
:class:`~nodes.recorder.mcapio.RecordingWriter` and keeps ``<directory>/<site>.index.json``
(:func:`constructaide.recording.read_index`) up to date, replaced atomically (temporary file, fsync, rename) at
every rotation: a SIGKILL leaves an index whose last file is ``open`` and truncated; the next start repairs it
(every complete chunk kept) before it opens a new file. Retention deletes the oldest files beyond
``max_total_bytes`` / ``max_files`` / ``max_age_secs``. When the disk is full (``ENOSPC``/``EDQUOT``) the
current file is abandoned, the oldest files are deleted to make room (never the last one written) and the message
is written to a new file; if nothing can be freed the message is dropped and counted. Each problem is reported
through ``report(reason)``; nothing raises past :meth:`write`, so the recorder never crash-loops on a full disk.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

from constructaide.recording import INDEX_VERSION, IndexEntry, RecordingError, index_path, read_index
from nodes.recorder.mcapio import Classified, FlushPolicy, RecordingWriter, new_recording_path, repair

log = logging.getLogger("constructaide.recorder")
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


@dataclass(frozen=True)
class Rotation:
    max_file_bytes: int = 256_000_000
    max_file_secs: float = 3600.0
    max_total_bytes: int = 0
    """Retention: total size of the set (0: unlimited)."""
    max_files: int = 0
    max_age_secs: float = 0.0


class RotatingRecorder:
    """See the module docstring. Not thread-safe (the recorder node calls it under its lock)."""

    def __init__(
        self,
        directory: str | Path,
        site: str,
        rotation: Rotation = Rotation(),
        *,
        flush_on: FlushPolicy = "photo",
        chunk_size: int = 8 * 1024 * 1024,
        compression: Literal["zstd", "lz4", "none"] = "zstd",
        metadata: dict[str, str] | None = None,
        report: Callable[[str], None] = lambda reason: None,
        writer_type: type[RecordingWriter] = RecordingWriter,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.site = site
        self.rotation = rotation
        self.report = report
        self._writer_args = dict(flush_on=flush_on, chunk_size=chunk_size, compression=compression, metadata=metadata)
        self._writer_type = writer_type
        self._clock = clock
        self.index = index_path(self.directory, site)
        self.entries: list[IndexEntry] = self._recover()
        self.writer: RecordingWriter | None = None
        self._opened_at = 0.0
        self.dropped = 0
        self.deleted: list[str] = []
        self.message_count = 0
        self._open()

    # -- index ----------------------------------------------------------------

    def _recover(self) -> list[IndexEntry]:
        """Entries of an existing index; a file left ``open`` (killed recorder) is repaired in place."""
        if not self.index.exists():
            return []
        try:
            entries = read_index(self.index)
        except RecordingError as bad:
            self.report(f"recording index unreadable, starting a new one: {bad}")
            self.index.rename(self.index.with_name(self.index.name + f".bad-{time.time_ns()}"))
            return []
        out: list[IndexEntry] = []
        for e in entries:
            path = self.directory / e.name
            if not path.exists():
                continue
            if e.state == "open":
                try:
                    rep = repair(path, path)
                    e = replace(e, state="repaired", messages=rep.messages, size_bytes=path.stat().st_size)
                    log.info("repaired %s", rep.summary())
                except (OSError, ValueError) as exc:
                    self.report(f"cannot repair {path} (left as is, read up to its last chunk): {exc}")
            out.append(e)
        return out

    def _write_index(self) -> None:
        doc = {"version": INDEX_VERSION, "site": self.site, "files": [asdict(e) for e in self.entries]}
        tmp = self.index.with_name(self.index.name + ".tmp")
        with open(tmp, "w") as f:
            json.dump(doc, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.index)

    # -- files ----------------------------------------------------------------

    def _open(self) -> None:
        path = new_recording_path(self.directory, self.site)
        self.writer = self._writer_type(path, **self._writer_args)  # type: ignore[arg-type]
        self._opened_at = self._clock()
        self.entries.append(IndexEntry(name=path.name, started_ns=time.time_ns()))
        self._write_index()

    def _finish_current(self, state: str) -> None:
        w, self.writer = self.writer, None
        if w is None:
            return
        if state == "closed":
            w.close()
        else:
            w.abandon()
        size = w.path.stat().st_size if w.path.exists() else 0
        self.entries[-1] = replace(
            self.entries[-1], ended_ns=time.time_ns(), messages=w.message_count, size_bytes=size, state=state
        )

    def rotate(self) -> None:
        self._finish_current("closed")
        self._apply_retention()
        self._open()

    def _delete(self, e: IndexEntry) -> None:
        (self.directory / e.name).unlink(missing_ok=True)
        self.entries.remove(e)
        self.deleted.append(e.name)

    def _apply_retention(self) -> None:
        r = self.rotation
        now = time.time_ns()
        done = [e for e in self.entries if e.state != "open"]
        while done:
            total = sum(e.size_bytes for e in done)
            old = done[0]
            if (
                (r.max_files and len(done) >= r.max_files)
                or (r.max_total_bytes and total > r.max_total_bytes)
                or (r.max_age_secs and (now - (old.ended_ns or old.started_ns)) / 1e9 > r.max_age_secs)
            ):
                self._delete(old)
                done.pop(0)
            else:
                break

    def _due(self) -> bool:
        r, w = self.rotation, self.writer
        if w is None or w.message_count == 0:
            return False
        return (r.max_file_bytes > 0 and w.size_bytes >= r.max_file_bytes) or (
            r.max_file_secs > 0 and self._clock() - self._opened_at >= r.max_file_secs
        )

    # -- writing --------------------------------------------------------------

    def write(self, key: str, payload: bytes, receive_time_ns: int | None = None) -> Classified | None:
        """Record one payload; its classification, None when it had to be dropped (disk full, nothing to free)."""
        for attempt in range(3):
            try:
                if self.writer is None:
                    self._open()
                elif self._due():
                    self.rotate()
                assert self.writer is not None
                info = self.writer.write(key, payload, receive_time_ns)
                self.message_count += 1
                return info
            except OSError as e:
                if e.errno not in DISK_FULL:
                    raise
                freed = self._disk_full(e, attempt)
                if not freed:
                    break
        self.dropped += 1
        return None

    def _disk_full(self, e: OSError, attempt: int) -> bool:
        """Abandon the current file, free the oldest files; True when a retry is worth it."""
        if self.writer is not None:
            self._finish_current("open")  # truncated: read up to its last chunk, repaired at the next start
        freeable = [x for x in self.entries[:-1] if x.state != "open"] or [
            x for x in self.entries[:-1] if x.state == "open"
        ]
        victims = freeable[: max(1, len(freeable) // 4)]  # the oldest quarter
        for v in victims:
            self._delete(v)
        try:
            self._write_index()
        except OSError:
            pass
        self.report(
            f"disk full writing the recording ({e.strerror}): deleted the {len(victims)} oldest files "
            f"({', '.join(v.name for v in victims) or 'none left'}); newest data kept"
            + ("" if victims else f"; message dropped ({self.dropped + 1} so far)")
        )
        return bool(victims) or attempt == 0

    def flush(self) -> None:
        """Finish the open chunk and push it to the OS."""
        if self.writer is not None:
            try:
                self.writer.flush()
            except OSError as e:
                if e.errno not in DISK_FULL:
                    raise
                self._disk_full(e, 1)

    def flush_if_older_than(self, max_age_secs: float) -> None:
        if self.writer is not None:
            try:
                self.writer.flush_if_older_than(max_age_secs)
            except OSError as e:
                if e.errno not in DISK_FULL:
                    raise
                self._disk_full(e, 1)

    @property
    def unflushed_count(self) -> int:
        return 0 if self.writer is None else self.writer.unflushed_count

    @property
    def path(self) -> Path:
        return self.directory / self.entries[-1].name if self.entries else self.index

    def close(self) -> None:
        try:
            self._finish_current("closed")
            self._write_index()
        except OSError as e:
            self.report(f"closing the recording failed: {e}")
