"""Recorder node: every data topic of a site into ``<directory>/<site>-<UTC time>.mcap`` files.

The files rotate by size and age, old ones are deleted by the retention rules, and ``<directory>/<site>.index.json``
lists them (:mod:`nodes.recorder.rotation`; readers take the index for a path); a full disk is reported on the
error topic and the newest data kept. ``path`` writes one exact file instead (no rotation).

Payloads are recorded byte for byte, one message per publication (the bus reassembles payloads sent in parts,
:mod:`constructaide.runtime.chunks`; see :mod:`nodes.recorder.mcapio` for the file layout).
The chunk is finished and the file flushed after every Photo/BimModel/BimUpdate (or every
message with ``flush_on = "message"``), and a background timer flushes anything older than
``max_unflushed_secs``; so a SIGKILLed recorder loses at most the event in progress.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Literal

import msgspec

from constructaide.errors import UserError
from constructaide.runtime import Input, NodeContext, NodeSpec, run_node_cli
from nodes.recorder.mcapio import RecordingWriter
from nodes.recorder.rotation import RotatingRecorder, Rotation
from schemas.messages import Message


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    directory: str = "recordings"
    """Folder of the .mcap files (created when missing)."""
    path: str = ""
    """Exact output file instead of ``<directory>/<site>-<UTC>.mcap`` (must not exist)."""
    flush_on: Literal["photo", "message"] = "photo"
    max_unflushed_secs: float = 1.0
    """Other messages are flushed at the latest this long after they arrived (<= 0: never by time)."""
    chunk_size_bytes: int = 8 * 1024 * 1024
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    max_file_mb: float = 256.0
    """Rotate to a new file beyond this size (<= 0: never by size)."""
    max_file_secs: float = 3600.0
    """Rotate to a new file after this long (<= 0: never by time)."""
    keep_total_gb: float = 0.0
    """Retention: delete the oldest files beyond this total (0: keep all)."""
    keep_files: int = 0
    """Retention: at most this many files (0: no limit)."""
    keep_days: float = 0.0
    """Retention: delete files older than this (0: keep all)."""


class RecorderNode:
    """Writes each received payload to the MCAP file; ``close`` writes the summary and closes it."""

    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx
        self._lock = threading.Lock()
        self._last_report = 0.0
        meta = {"site": ctx.site, "started_ns": str(time.time_ns()), "node": ctx.node}
        self.writer: RecordingWriter | RotatingRecorder
        if config.path:
            path = Path(config.path)
            path.parent.mkdir(parents=True, exist_ok=True)
            try:
                self.writer = RecordingWriter(
                    path,
                    flush_on=config.flush_on,
                    chunk_size=config.chunk_size_bytes,
                    compression=config.compression,
                    metadata=meta,
                )
            except FileExistsError:
                raise UserError(f"recording {path} already exists; choose another path") from None
        else:
            rotation = Rotation(
                max_file_bytes=int(config.max_file_mb * 1e6),
                max_file_secs=config.max_file_secs,
                max_total_bytes=int(config.keep_total_gb * 1e9),
                max_files=config.keep_files,
                max_age_secs=config.keep_days * 86400.0,
            )
            self.writer = RotatingRecorder(
                config.directory,
                ctx.site,
                rotation,
                flush_on=config.flush_on,
                chunk_size=config.chunk_size_bytes,
                compression=config.compression,
                metadata=meta,
                report=self._report,
            )
            path = self.writer.index
        self.path = path
        ctx.log.info("recording site %s to %s", ctx.site, path)
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None
        if config.max_unflushed_secs > 0:
            self._timer = threading.Thread(target=self._flush_loop, name="recorder-flush", daemon=True)
            self._timer.start()

    def _report(self, reason: str) -> None:
        """Errors of the rotating writer on the error topic (at most one per second: a full disk repeats)."""
        now = time.monotonic()
        if now - self._last_report >= 1.0:
            self._last_report = now
            self.ctx.error("recording", reason)
        else:
            self.ctx.log.warning("%s", reason)

    def on_message(self, payload: bytes, key: str) -> None:
        if "/@" in key:
            return  # liveliness/admin keys are not data
        with self._lock:
            info = self.writer.write(key, payload, time.time_ns())
            flushed = self.writer.unflushed_count == 0
        if flushed and info is not None:
            self.ctx.log.debug("flushed %d messages, last %s on %s", self.writer.message_count, info.type_name, key)

    # with a state dir the runtime marks messages handled at most every state_every_secs, right after
    # state_snapshot, which flushes the open chunk first: a SIGKILL loses nothing marked handled (the messages of
    # the lost chunk are replayed at the next start)
    state_every_secs = 1.0

    def state_snapshot(self) -> dict[str, bytes]:
        with self._lock:
            self.writer.flush()
        return {}

    def _flush_loop(self) -> None:
        interval = self.config.max_unflushed_secs
        while not self._stop.wait(interval / 2):
            with self._lock:
                self.writer.flush_if_older_than(interval)

    def close(self) -> None:
        self._stop.set()
        if self._timer is not None:
            self._timer.join(timeout=10)
        with self._lock:
            self.writer.close()
        self.ctx.log.info("recording closed: %s (%d messages)", self.path, self.writer.message_count)


SPEC = NodeSpec(
    name="recorder",
    description="Records every data topic of a site to an MCAP file (zstd chunks, JSON Schema, msgpack payloads).",
    config_type=Config,
    factory=RecorderNode,
    inputs=(Input("constructaide/{site}/**", Message, "on_message", raw=True, latched=True),),
    outputs=(),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
