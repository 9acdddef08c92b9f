"""Reading ConstructAide MCAP recordings (the file layout is described in :mod:`nodes.recorder.mcapio`, which
writes them): a tolerant sequential scan that stops at the first truncated or corrupt record, messages with
their keys, schema names and times, and decoded messages of chosen types.

A rotating recorder writes a set of files and an index, ``<site>.index.json`` (:func:`read_index`); every reader
here takes the index (or the folder holding exactly one) for a path and reads the set in order, the file still
open when the recorder stopped (killed: truncated) up to its last complete chunk.

Shared by the recorder (repair, replay), the render CLI, the app and the benches; uses the ``mcap`` package
but no bus.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from schemas import codec
from schemas import messages as m

MCAP_MAGIC = b"\x89MCAP0\r\n"
INVALID_SCHEMA_NAME = "constructaide.Invalid"
"""Schema name of payloads that did not decode as a ConstructAide message (recorded as received)."""

# ---------------------------------------------------------------------------
# Tolerant sequential scan (shared by reading, repair and replay)
# ---------------------------------------------------------------------------


@dataclass
class ScanState:
    """Where a scan stopped. ``complete``: the file ends in the closing magic after DataEnd;
    ``data_complete``: DataEnd was reached (every message is there, the summary may be damaged)."""

    complete: bool = False
    data_complete: bool = False
    stopped_at_byte: int = 0
    reason: str = ""
    file_size: int = 0
    chunks: int = 0
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)


_RECORD_READERS: dict[int, Callable[[ReadDataStream], Any]] = {
    Opcode.HEADER: Header.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.METADATA: Metadata.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


def _parse_record(opcode: int, body: bytes) -> Any:
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.MESSAGE:
        if len(body) < 22:
            raise ValueError("message record shorter than its header")
        return Message.read(stream, len(body))
    reader = _RECORD_READERS.get(opcode)
    if reader is None:
        return None  # index/summary records and unknown opcodes: not data
    record = reader(stream)
    if stream.count > len(body):
        raise ValueError(f"record {Opcode(opcode).name} overruns its length")
    return record


def scan_records(f: IO[bytes], state: ScanState) -> Iterator[Any]:
    """Yield Schema, Channel, Message, Metadata and Attachment records in file order.

    Chunks are opened (CRC checked) and yielded record by record only when whole and valid.
    Stops quietly at the first truncated or corrupt record, or at DataEnd; ``state`` says where
    and why. Raises ValueError when the file does not start with the MCAP magic.
    """
    f.seek(0, os.SEEK_END)
    state.file_size = f.tell()
    f.seek(0)
    if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        raise ValueError("not an MCAP file (bad magic)")
    pos = len(MCAP_MAGIC)
    while True:
        state.stopped_at_byte = pos
        head = f.read(9)
        if len(head) < 9:
            state.reason = "end of file before the footer (truncated)"
            return
        opcode, length = struct.unpack("<BQ", head)
        if length > state.file_size - pos - 9:
            state.reason = f"record at byte {pos} claims {length} bytes, file ends first (truncated)"
            return
        body = f.read(length)
        try:
            record = _parse_record(opcode, body)
            inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else None
        except Exception as exc:  # any parse failure marks the corruption point
            state.reason = f"corrupt record at byte {pos}: {type(exc).__name__}: {exc}"
            return
        pos += 9 + length
        if inner is not None:
            state.chunks += 1
            for rec in inner:
                _note(rec, state)
                yield rec
        elif isinstance(record, DataEnd):
            state.data_complete = True
            state.stopped_at_byte = pos
            tail = f.read()
            # Summary section is a repeat of what we have; the file is complete if it ends in magic.
            state.complete = tail.endswith(MCAP_MAGIC)
            state.reason = "complete" if state.complete else "data section complete, summary truncated"
            return
        elif record is not None and not isinstance(record, Header | Footer):
            _note(record, state)
            yield record


def _note(record: Any, state: ScanState) -> None:
    if isinstance(record, Schema):
        state.schemas[record.id] = record
    elif isinstance(record, Channel):
        state.channels[record.id] = record


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded payload: zenoh key, schema name, exact bytes, times in ns UTC."""

    key: str
    type_name: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int


class RecordingError(ValueError):
    """A recording is truncated or corrupt (run ``constructaide recording repair``)."""


INDEX_SUFFIX = ".index.json"
INDEX_VERSION = 1


@dataclass(frozen=True)
class IndexEntry:
    """One file of a rotated recording. ``state``: ``open`` (being written, or the recorder was killed),
    ``closed`` (summary written), ``repaired`` (truncated, then repaired). Times ns UTC (receive times)."""

    name: str
    started_ns: int
    ended_ns: int = 0
    messages: int = 0
    size_bytes: int = 0
    state: str = "open"


def index_path(directory: str | Path, site: str) -> Path:
    return Path(directory) / f"{site}{INDEX_SUFFIX}"


def read_index(path: str | Path) -> list[IndexEntry]:
    """The files of a rotated recording, oldest first (paths relative to the index's folder)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise RecordingError(f"cannot read the recording index {path}: {e}") from None
    if doc.get("version") != INDEX_VERSION:
        raise RecordingError(f"{path}: unknown index version {doc.get('version')!r}")
    return [IndexEntry(**f) for f in doc.get("files", [])]


def recording_files(path: str | Path) -> list[tuple[Path, bool]]:
    """``(file, may_be_truncated)`` of a recording: one ``.mcap``, an index, or a folder with one index."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob(f"*{INDEX_SUFFIX}"))
        if len(found) != 1:
            raise RecordingError(f"{path}: expected one *{INDEX_SUFFIX} in the folder, found {len(found)}")
        path = found[0]
    if path.name.endswith(INDEX_SUFFIX):
        return [(path.parent / e.name, e.state == "open") for e in read_index(path) if (path.parent / e.name).exists()]
    return [(path, False)]


def iter_messages(path: str | Path, *, allow_truncated: bool = False, dedupe: bool = True) -> Iterator[RecordedMessage]:
    """Every message of a recording in file (= receive) order (of a rotated set: file after file).

    A file whose data section is truncated or corrupt yields its complete part, then raises
    :class:`RecordingError` unless ``allow_truncated`` (a damaged summary section alone is fine); in a rotated
    set the files the index says were open (the recorder was killed) are read up to their last complete chunk.
    With ``dedupe`` a message whose key and payload are byte for byte those of an earlier one is skipped: the
    recorder records at least once (a message written to a chunk just before a kill comes again after the
    restart), and the system handles a message once by that digest anyway.
    """
    seen: set[bytes] = set()
    for file, open_ in recording_files(path):
        for rec in _iter_file(file, allow_truncated=allow_truncated or open_):
            if dedupe:
                dig = hashlib.blake2b(rec.key.encode() + b"\0" + rec.payload, digest_size=16).digest()
                if dig in seen:
                    continue
                seen.add(dig)
            yield rec


def _iter_file(path: Path, *, allow_truncated: bool) -> Iterator[RecordedMessage]:
    state = ScanState()
    with open(path, "rb") as f:
        for rec in scan_records(f, state):
            if isinstance(rec, Message):
                channel = state.channels.get(rec.channel_id)
                if channel is None:
                    raise RecordingError(f"{path}: message on unknown channel {rec.channel_id}")
                schema = state.schemas.get(channel.schema_id)
                yield RecordedMessage(
                    key=channel.topic,
                    type_name=schema.name if schema is not None else "",
                    payload=rec.data,
                    log_time_ns=rec.log_time,
                    publish_time_ns=rec.publish_time,
                )
    if not state.data_complete and not allow_truncated:
        raise RecordingError(f"{path}: {state.reason}; run `constructaide recording repair {path}`")


def iter_recording(path: str | Path, *, allow_truncated: bool = False) -> Iterator[tuple[str, str, bytes, int]]:
    """``(key, type_name, payload bytes, log_time_ns)`` for every message, in file order."""
    for msg in iter_messages(path, allow_truncated=allow_truncated):
        yield msg.key, msg.type_name, msg.payload, msg.log_time_ns


def decoded_messages(
    path: str | Path, types: Iterable[type[m.Message]] | None = None, *, allow_truncated: bool = False
) -> Iterator[tuple[str, m.Message]]:
    """``(key, message)`` of every recorded message of the given types (all types when None), in file order.

    Payloads that do not decode are skipped. Raises :class:`RecordingError` as :func:`iter_messages` does.
    """
    names = None if types is None else {codec.type_name(t) for t in types}
    for rec in iter_messages(path, allow_truncated=allow_truncated):
        if names is not None and rec.type_name not in names:
            continue
        try:
            msg = codec.decode(rec.payload)
        except (msgspec.DecodeError, msgspec.ValidationError):
            continue
        yield rec.key, msg
