"""Rotating recordings: size/time rotation, retention, the index, SIGKILL mid-write, full disk."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

from constructaide.recording import iter_messages, read_index, recording_files
from nodes.recorder.mcapio import RecordingWriter
from nodes.recorder.rotation import RotatingRecorder, Rotation
from schemas import codec, keys
from schemas import messages as m

REPO = Path(__file__).resolve().parents[1]
SITE = "rot"


def photo_payload(i: int, size: int = 20_000) -> tuple[str, bytes]:
    data = np.random.default_rng(i).integers(0, 256, size, dtype=np.uint8).tobytes()  # incompressible
    msg = m.Photo(site=SITE, photo_id=f"p{i}", camera_id="cam-a", capture_time_ns=i + 1, data=data)
    return keys.key(keys.PHOTO, site=SITE, camera="cam-a"), codec.encode(msg)


def ids(path: Path) -> list[str]:
    return [codec.decode(r.payload).photo_id for r in iter_messages(path)]  # type: ignore[attr-defined]


def test_rotates_by_size_and_the_index_reads_as_one_recording(tmp_path: Path) -> None:
    rec = RotatingRecorder(tmp_path, SITE, Rotation(max_file_bytes=50_000, max_file_secs=0))
    for i in range(12):
        assert rec.write(*photo_payload(i))
    rec.close()
    entries = read_index(rec.index)
    assert len(entries) >= 4 and all(e.state == "closed" for e in entries)
    assert sum(e.messages for e in entries) == 12
    assert all(e.size_bytes <= 50_000 + 25_000 for e in entries)  # one message past the limit at most
    assert ids(rec.index) == [f"p{i}" for i in range(12)]
    assert ids(tmp_path) == ids(rec.index)  # the folder holding the index reads the same
    names = [p.name for p, _ in recording_files(rec.index)]
    assert names == [e.name for e in entries] and len(set(names)) == len(names)


def test_rotates_by_time_and_retention_keeps_the_newest(tmp_path: Path) -> None:
    now = [0.0]
    rec = RotatingRecorder(
        tmp_path, SITE, Rotation(max_file_bytes=0, max_file_secs=10, max_files=3), clock=lambda: now[0]
    )
    for i in range(10):
        now[0] = i * 5.0  # a new file every 2 messages
        rec.write(*photo_payload(i, 100))
    rec.close()
    entries = read_index(rec.index)
    assert len(entries) == 3 and rec.deleted  # oldest files deleted
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == sorted(e.name for e in entries)
    got = ids(rec.index)
    assert got == [f"p{i}" for i in range(10 - len(got), 10)]  # the newest, contiguous
    total = Rotation(max_file_bytes=300, max_file_secs=0, max_total_bytes=1000)
    rec = RotatingRecorder(tmp_path / "b", SITE, total)
    for i in range(20):
        rec.write(*photo_payload(i, 200))
    rec.close()
    assert sum(e.size_bytes for e in read_index(rec.index)[:-1]) <= 1000
    assert ids(rec.index)[-1] == "p19"


WRITER = textwrap.dedent(
    """
    import sys
    from nodes.recorder.rotation import Rotation, RotatingRecorder
    sys.path.insert(0, sys.argv[2])
    from test_recorder_rotation import photo_payload
    rec = RotatingRecorder(sys.argv[1], "rot", Rotation(max_file_bytes=60_000, max_file_secs=0))
    i = 0
    while True:
        rec.write(*photo_payload(i))  # a Photo: the chunk is finished and flushed
        print(i, flush=True)
        i += 1
    """
)


def test_sigkill_mid_write_keeps_every_complete_chunk_and_the_index(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(tmp_path), str(Path(__file__).parent)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    for _ in range(9):
        written = int(proc.stdout.readline())
    proc.send_signal(signal.SIGKILL)
    proc.wait(20)
    proc.stdout.close()
    index = tmp_path / f"{SITE}.index.json"
    entries = read_index(index)  # intact: replaced atomically
    assert entries[-1].state == "open" and all(e.state == "closed" for e in entries[:-1])
    open_file = tmp_path / entries[-1].name
    with open(open_file, "r+b") as f:  # and cut the file mid-record as a kill during a write would
        f.truncate(max(0, open_file.stat().st_size - 7))
    got = ids(index)  # the open file is read up to its last complete chunk
    assert got[: written + 1] == [f"p{i}" for i in range(written + 1)][: len(got)]
    assert len(got) >= written  # every flushed photo but the cut one
    # The next start repairs the open file in place and appends a new one; the index lists them all.
    rec = RotatingRecorder(tmp_path, SITE, Rotation(max_file_bytes=60_000, max_file_secs=0))
    rec.write(*photo_payload(1000))
    rec.close()
    after = read_index(index)
    assert [e.name for e in after[: len(entries)]] == [e.name for e in entries]
    assert after[len(entries) - 1].state == "repaired"
    assert ids(index) == got + ["p1000"]


class SmallDisk(RecordingWriter):
    """A writer on a 'disk' of BUDGET bytes for its whole folder (ENOSPC beyond it)."""

    BUDGET = 120_000

    def write(self, key, payload, receive_time_ns=None):  # type: ignore[no-untyped-def]
        used = sum(p.stat().st_size for p in self.path.parent.glob("*.mcap"))
        if used + len(payload) > self.BUDGET:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(key, payload, receive_time_ns)


def test_full_disk_reports_keeps_the_newest_and_never_raises(tmp_path: Path) -> None:
    reports: list[str] = []
    rec = RotatingRecorder(
        tmp_path, SITE, Rotation(max_file_bytes=30_000, max_file_secs=0), report=reports.append, writer_type=SmallDisk
    )
    for i in range(30):
        rec.write(*photo_payload(i))
    assert rec.write(*photo_payload(99, SmallDisk.BUDGET + 1)) is None  # can never fit: dropped, counted
    rec.close()
    assert reports and all("disk full" in r for r in reports)
    assert rec.dropped >= 1 and rec.deleted
    got = ids(rec.index)
    assert got[-1] == "p29" and "p0" not in got  # newest kept, oldest given up
    assert got == sorted(got, key=lambda s: int(s[1:]))
    doc = json.loads(rec.index.read_text())
    assert {f["name"] for f in doc["files"]} == {p.name for p in tmp_path.glob("*.mcap")}
