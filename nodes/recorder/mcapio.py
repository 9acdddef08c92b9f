"""MCAP recordings of ConstructAide bus traffic: writer, reader, repair and replay.

File layout (one file per recorder run, ``<site>-<YYYYmmddTHHMMSSZ>.mcap``):

* one Schema record per message type: name ``constructaide.<Type>`` (``schemas.codec.type_name``),
  encoding ``jsonschema``, data ``schemas.codec.json_schema(Type)``;
* one Channel per (zenoh key, schema): topic = the key, message encoding ``msgpack``;
* Message records hold the exact payload bytes seen on the bus. ``log_time`` is the receive time,
  ``publish_time`` the capture time when the message has one (Photo, Registration) else the
  receive time; both integer ns since the Unix epoch, UTC. ``sequence`` counts per channel.
* Payloads that do not decode as a ConstructAide message are recorded anyway (nothing is lost)
  on a channel whose schema is :data:`INVALID_SCHEMA_NAME`; replay re-publishes them as they were.
* zstd-compressed chunks. The writer finishes the current chunk and flushes the file after every
  flush-triggering message (default: every Photo), so a SIGKILLed recorder loses at most the
  event in progress; ``repair`` turns such a truncated file into a valid, indexed one.

This module is the recorder's core (writer, repair, replay): it uses the ``mcap`` package but no bus. Reading is
:mod:`constructaide.recording`, shared with the render CLI, the app and the benches.
"""

from __future__ import annotations

import fnmatch
import os
import re
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Literal

import msgspec
from mcap.records import (
    Attachment,
    Channel,
    Message,
    Metadata,
    Schema,
)
from mcap.writer import CompressionType, Writer

from constructaide.recording import (
    INVALID_SCHEMA_NAME,
    MCAP_MAGIC,
    RecordedMessage,
    RecordingError,
    ScanState,
    iter_messages,
    iter_recording,
    scan_records,
)
from schemas import codec
from schemas import messages as m

__all__ = [
    "INVALID_SCHEMA_NAME",
    "MCAP_MAGIC",
    "RecordedMessage",
    "RecordingError",
    "RecordingWriter",
    "ScanState",
    "iter_messages",
    "iter_recording",
    "new_recording_path",
    "repair",
    "replay",
    "scan_records",
]

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
INVALID_SCHEMA = b'{"description": "payload that did not decode as a ConstructAide message; bytes kept as received"}'
PROFILE = "constructaide"
METADATA_NAME = "constructaide.recording"

FlushPolicy = Literal["photo", "message"]


@dataclass(frozen=True)
class Classified:
    """What the recorder learns from one payload: schema name and publish time (ns, UTC)."""

    type_name: str
    publish_time_ns: int | None
    error: str = ""


def classify(payload: bytes) -> Classified:
    """Decode ``payload`` (msgpack, tagged) to find its message type and capture time.

    Invalid payloads give ``type_name == INVALID_SCHEMA_NAME`` and the decode error.
    """
    try:
        msg = codec.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        return Classified(INVALID_SCHEMA_NAME, None, f"{type(exc).__name__}: {exc}")
    capture_ns: int | None = None
    if isinstance(msg, m.Photo):
        capture_ns = msg.capture_time_ns
    elif isinstance(msg, m.Registration) and msg.capture_time_ns > 0:
        capture_ns = msg.capture_time_ns
    return Classified(codec.type_name(msg), capture_ns)


def recording_filename(site: str, started: datetime | None = None) -> str:
    """``<site>-<UTC YYYYmmddTHHMMSSZ>.mcap``."""
    started = started or datetime.now(UTC)
    return f"{site}-{started.astimezone(UTC).strftime('%Y%m%dT%H%M%SZ')}.mcap"


def new_recording_path(directory: str | Path, site: str, started: datetime | None = None) -> Path:
    """A fresh path in ``directory`` (created); ``-1``, ``-2`` ... appended if the name is taken."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    base = recording_filename(site, started)
    path = directory / base
    n = 1
    while path.exists():
        path = directory / f"{base[: -len('.mcap')]}-{n}.mcap"
        n += 1
    return path


class RecordingWriter:
    """Writes bus payloads to one MCAP file (not thread-safe: call from one thread or under a lock).

    ``flush_on``: ``"photo"`` finishes the chunk after every Photo (and BimModel/BimUpdate);
    ``"message"`` after every message. Chunks also end when they exceed ``chunk_size`` bytes.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_on: FlushPolicy = "photo",
        chunk_size: int = 8 * 1024 * 1024,
        compression: Literal["zstd", "lz4", "none"] = "zstd",
        metadata: dict[str, str] | None = None,
    ) -> None:
        if flush_on not in ("photo", "message"):
            raise ValueError(f"flush_on must be 'photo' or 'message', got {flush_on!r}")
        self.path = Path(path)
        self.flush_on: FlushPolicy = flush_on
        self._file: IO[bytes] = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(
            self._file,
            chunk_size=chunk_size,
            compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                compression
            ],
            enable_crcs=True,
        )
        self._writer.start(profile=PROFILE, library="constructaide-recorder")
        if metadata:
            self._writer.add_metadata(METADATA_NAME, dict(metadata))
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self.message_count = 0
        self.unflushed_count = 0
        self.oldest_unflushed_monotonic: float | None = None
        self._closed = False

    def _schema_id(self, type_name: str) -> int:
        sid = self._schema_ids.get(type_name)
        if sid is None:
            if type_name == INVALID_SCHEMA_NAME:
                data = INVALID_SCHEMA
            else:
                data = codec.json_schema(codec.TYPES_BY_NAME[type_name])
            sid = self._writer.register_schema(name=type_name, encoding=SCHEMA_ENCODING, data=data)
            self._schema_ids[type_name] = sid
        return sid

    def _channel_id(self, key: str, type_name: str) -> int:
        cid = self._channel_ids.get((key, type_name))
        if cid is None:
            cid = self._writer.register_channel(
                topic=key, message_encoding=MESSAGE_ENCODING, schema_id=self._schema_id(type_name)
            )
            self._channel_ids[(key, type_name)] = cid
        return cid

    def write(self, key: str, payload: bytes, receive_time_ns: int | None = None) -> Classified:
        """Record one payload seen on ``key``; returns its classification. Flushes per policy."""
        if self._closed:
            raise ValueError(f"recording {self.path} is closed")
        receive_time_ns = time.time_ns() if receive_time_ns is None else receive_time_ns
        info = classify(payload)
        cid = self._channel_id(key, info.type_name)
        seq = self._sequence.get(cid, 0)
        self._sequence[cid] = seq + 1
        publish_ns = info.publish_time_ns if info.publish_time_ns is not None else receive_time_ns
        self._writer.add_message(
            channel_id=cid,
            log_time=receive_time_ns,
            data=bytes(payload),
            publish_time=publish_ns,
            sequence=seq & 0xFFFFFFFF,
        )
        self.message_count += 1
        self.unflushed_count += 1
        if self.oldest_unflushed_monotonic is None:
            self.oldest_unflushed_monotonic = time.monotonic()
        if self.flush_on == "message" or info.type_name in _FLUSH_TYPES:
            self.flush()
        return info

    def flush(self) -> None:
        """Finish the current chunk and push everything to the OS (survives SIGKILL, not power loss)."""
        if self._closed:
            return
        self._writer.flush()
        self.unflushed_count = 0
        self.oldest_unflushed_monotonic = None

    @property
    def size_bytes(self) -> int:
        """Bytes handed to the file so far (the open chunk not included)."""
        return self._file.tell()

    def abandon(self) -> None:
        """Close the file without a summary (e.g. the disk is full); it reads as truncated, ``repair`` fixes it."""
        self._closed = True
        try:
            self._file.close()
        except OSError:
            pass

    def flush_if_older_than(self, max_age_secs: float) -> bool:
        """Flush when the oldest unflushed message is older than ``max_age_secs``; True if flushed."""
        t = self.oldest_unflushed_monotonic
        if t is not None and time.monotonic() - t >= max_age_secs:
            self.flush()
            return True
        return False

    def close(self) -> None:
        """Write the summary section (indexes, statistics) and close the file."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_FLUSH_TYPES = frozenset(codec.type_name(t) for t in (m.Photo, m.BimModel, m.BimUpdate))


# ---------------------------------------------------------------------------
# Repair
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RepairReport:
    """Outcome of :func:`repair`. Byte offsets refer to the input file."""

    path_in: Path
    path_out: Path
    messages: int
    chunks: int
    schemas: int
    channels: int
    was_complete: bool
    stopped_at_byte: int
    input_bytes: int
    reason: str
    dropped_bytes: int

    def summary(self) -> str:
        state = "was already complete" if self.was_complete else f"stopped at byte {self.stopped_at_byte}"
        return (
            f"{self.path_out}: recovered {self.messages} messages on {self.channels} channels "
            f"from {self.chunks} chunks ({state}; {self.dropped_bytes} trailing bytes dropped: {self.reason})"
        )


def repair(path_in: str | Path, path_out: str | Path) -> RepairReport:
    """Copy every complete record of a (possibly truncated) MCAP file into a new valid MCAP.

    Whole CRC-valid chunks and complete un-chunked records are kept; reading stops at the first
    truncated or corrupt record. The output is written to a temporary file then renamed, so
    ``path_out`` may equal ``path_in``.
    """
    path_in, path_out = Path(path_in), Path(path_out)
    if not path_in.is_file():
        raise FileNotFoundError(f"no such recording: {path_in}")
    tmp = path_out.with_name(path_out.name + ".partial")
    state = ScanState()
    schema_map: dict[int, int] = {}
    channel_map: dict[int, int] = {}
    n_messages = 0
    try:
        with open(path_in, "rb") as f_in, open(tmp, "wb") as f_out:
            writer = Writer(f_out, compression=CompressionType.ZSTD)
            writer.start(profile=PROFILE, library="constructaide-repair")
            for rec in scan_records(f_in, state):
                if isinstance(rec, Schema):
                    if rec.id not in schema_map:
                        schema_map[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channel_map:
                        channel_map[rec.id] = writer.register_channel(
                            rec.topic, rec.message_encoding, schema_map.get(rec.schema_id, 0), dict(rec.metadata)
                        )
                elif isinstance(rec, Message):
                    cid = channel_map.get(rec.channel_id)
                    if cid is None:
                        state.reason = f"message on undefined channel {rec.channel_id}; stopped"
                        break
                    writer.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    n_messages += 1
                elif isinstance(rec, Metadata):
                    writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            writer.finish()
        os.replace(tmp, path_out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return RepairReport(
        path_in=path_in,
        path_out=path_out,
        messages=n_messages,
        chunks=state.chunks,
        schemas=len(schema_map),
        channels=len(channel_map),
        was_complete=state.complete,
        stopped_at_byte=state.stopped_at_byte,
        input_bytes=state.file_size,
        reason=state.reason,
        dropped_bytes=0 if state.complete else state.file_size - state.stopped_at_byte,
    )


# ---------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------

_SITE_IN_KEY = re.compile(r"^constructaide/[^/]+/")


def parse_rate(text: str | float) -> float | None:
    """``"max"`` -> None (as fast as possible); else a positive speed factor (1.0 = real time)."""
    if isinstance(text, str) and text.strip().lower() == "max":
        return None
    try:
        rate = float(text)
    except ValueError:
        raise ValueError(f"rate must be a positive number or 'max', got {text!r}") from None
    if not rate > 0 or rate == float("inf"):
        raise ValueError(f"rate must be a positive number or 'max', got {text!r}")
    return rate


def retarget_site(key: str, payload: bytes, site: str) -> tuple[str, bytes]:
    """Move one message to another site: key prefix and the message's ``site`` field.

    Payloads that do not decode keep their bytes (only the key moves).
    """
    new_key = _SITE_IN_KEY.sub(f"constructaide/{site}/", key, count=1)
    try:
        msg = codec.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return new_key, payload
    if msg.site == site:
        return new_key, payload
    return new_key, codec.encode(msgspec.structs.replace(msg, site=site))


def select_messages(
    messages: Iterable[RecordedMessage], topics: Iterable[str] = (), types: Iterable[str] = ()
) -> Iterator[RecordedMessage]:
    """Keep messages whose key matches any ``topics`` glob (fnmatch, ``*`` spans ``/``) and whose
    type is in ``types`` (names with or without the ``constructaide.`` prefix); empty = all."""
    globs = tuple(topics)
    wanted = {t if t.startswith("constructaide.") else f"constructaide.{t}" for t in types}
    for msg in messages:
        if globs and not any(fnmatch.fnmatchcase(msg.key, g) for g in globs):
            continue
        if wanted and msg.type_name not in wanted:
            continue
        yield msg


def replay(
    path: str | Path,
    publish: Callable[[str, bytes], None],
    rate: float | str | None = 1.0,
    *,
    topics: Iterable[str] = (),
    types: Iterable[str] = (),
    site: str | None = None,
    allow_truncated: bool = False,
    sleep: Callable[[float], None] = time.sleep,
    monotonic: Callable[[], float] = time.monotonic,
    progress: Callable[[RecordedMessage], None] | None = None,
) -> int:
    """Re-publish a recording's payloads through ``publish(key, bytes)``; returns the count.

    Timing follows ``log_time`` divided by ``rate`` (``None``/``"max"``: no waiting, the
    publisher's back-pressure paces it). ``site`` moves every message to another site.
    """
    rate_f = parse_rate(rate) if isinstance(rate, str) else rate
    if rate_f is not None and not rate_f > 0:
        raise ValueError(f"rate must be positive, got {rate_f}")
    first_log_ns: int | None = None
    start = monotonic()
    count = 0
    for msg in select_messages(iter_messages(path, allow_truncated=allow_truncated), topics, types):
        if rate_f is not None:
            if first_log_ns is None:
                first_log_ns = msg.log_time_ns
            due_secs = max(0, msg.log_time_ns - first_log_ns) / 1e9 / rate_f
            wait = due_secs - (monotonic() - start)
            if wait > 0:
                sleep(wait)
        key, payload = (msg.key, msg.payload) if site is None else retarget_site(msg.key, msg.payload, site)
        publish(key, payload)
        count += 1
        if progress is not None:
            progress(msg)
    return count
