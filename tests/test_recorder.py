"""Recorder: MCAP layout, round trip of every message type, SIGKILL + repair, replay, node on LocalBus."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from nodes.recorder import mcapio
from schemas import codec, keys
from schemas import messages as m

REPO = Path(__file__).resolve().parents[1]
SITE = "t"


def sample_messages() -> list[tuple[str, m.Message]]:
    """One instance of every bus message type with its key (non-default fields filled)."""
    rng = np.random.default_rng(7)
    intr = m.Intrinsics(width_px=640, height_px=480, f_px=500.0, cx_px=319.5, cy_px=239.5, k1=-0.1, k2=0.01)
    elem = m.BimElement(global_id="2O2Fr$t4X7Zf8NOew3FLOH", ifc_class="IfcWall", name="W1", storey="L1")
    task = m.ScheduleTask(task_id="T1", name="walls", planned_start_ns=1, planned_finish_ns=2, element_ids=("a",))
    photo = m.Photo(
        site=SITE,
        photo_id="p0",
        camera_id="cam-a",
        capture_time_ns=1_700_000_000_000_000_000,
        tz="Europe/Zurich",
        data=rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        width_px=640,
        height_px=480,
        gps=m.GeoPoint(lat_deg=47.0, lon_deg=8.0),
    )
    out: list[tuple[str, m.Message]] = [
        (keys.key(keys.PHOTO, site=SITE, camera="cam-a"), photo),
        (
            keys.key(keys.BIM_MODEL, site=SITE),
            m.BimModel(site=SITE, revision="r1", elements=(elem,), tasks=(task,), geometry_glb=b"glTF\x02"),
        ),
        (
            keys.key(keys.BIM_UPDATE, site=SITE),
            m.BimUpdate(site=SITE, base_revision="r1", revision="r2", removed=("x",), tasks=()),
        ),
        (
            keys.key(keys.ANCHORS, site=SITE, photo="p0"),
            m.AnchorClicks(
                site=SITE,
                photo_id="p0",
                points=tuple(m.AnchorPoint(pixel_px=(i, i), point_in_world_m=(i, 0, 1)) for i in range(4)),
            ),
        ),
        (
            keys.key(keys.REGISTRATION, site=SITE, camera="cam-a", photo="p0"),
            m.Registration(
                site=SITE,
                photo_id="p0",
                camera_id="cam-a",
                capture_time_ns=1_700_000_000_000_000_123,
                intrinsics=intr,
                world_from_camera=tuple(np.eye(4).ravel().tolist()),
                status="anchor",
            ),
        ),
        (
            keys.key(keys.SPARSE, site=SITE),
            m.SparseCloud(site=SITE, revision=3, points_xyz_f32=np.ones((5, 3), np.float32).tobytes()),
        ),
        (
            keys.key(keys.VIEWPOINTS, site=SITE, photo="p0"),
            m.ViewpointGroup(
                site=SITE,
                photo_id="p0",
                neighbours=(
                    m.ViewpointNeighbour(
                        photo_id="p1",
                        this_from_neighbour=tuple(np.eye(3).ravel().tolist()),
                        inlier_ratio=0.5,
                        num_matches=9,
                    ),
                ),
            ),
        ),
        (keys.key(keys.NEEDS_ANCHOR, site=SITE, photo="p0"), m.NeedsAnchor(site=SITE, photo_id="p0", reason="few")),
        (
            keys.key(keys.OCCLUSION, site=SITE, kind="dynamic", photo="p0"),
            m.OcclusionMask(site=SITE, photo_id="p0", kind="dynamic", mask_png=b"\x89PNG"),
        ),
        (
            keys.key(keys.OVERLAY, site=SITE, mode="state4d", photo="p0"),
            m.Overlay(
                site=SITE,
                photo_id="p0",
                mode="state4d",
                image_png=b"\x89PNG",
                legend=(m.LegendEntry(label="built", rgba=(0, 255, 0, 128)),),
            ),
        ),
        (
            keys.key(keys.ANNOTATION, site=SITE, annotation="a1"),
            m.Annotation(site=SITE, annotation_id="a1", kind="occluder", polygon_px=((0, 0), (1, 0), (1, 1))),
        ),
        (keys.key(keys.ERRORS, site=SITE), m.NodeError(site=SITE, node="register", topic="x", reason="boom")),
        (
            keys.key(keys.PHOTO_EVIDENCE, site=SITE, photo="p0"),
            m.PhotoEvidence(
                site=SITE,
                photo_id="p0",
                elements=(m.ElementEvidence(global_id="a", state="built", confidence=0.9, visible_px=100),),
            ),
        ),
        (keys.key(keys.PROGRESS, site=SITE), m.ProgressUpdate(site=SITE, as_of_ns=1, photo_id="p0")),
    ]
    assert {type(msg) for _, msg in out} == set(m.MESSAGE_TYPES), "sample list must cover every message type"
    return out


def test_recorder_every_type_round_trips_and_file_layout(tmp_path: Path) -> None:
    samples = sample_messages()
    path = tmp_path / "rec.mcap"
    with mcapio.RecordingWriter(path, metadata={"site": SITE}) as w:
        for i, (key, msg) in enumerate(samples):
            w.write(key, codec.encode(msg), 1_000 + i)
        # a second photo on the same key reuses schema and channel
        w.write(samples[0][0], codec.encode(samples[0][1]), 5_000)

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {codec.type_name(t) for t in m.MESSAGE_TYPES}
        for name, schema in schemas.items():
            assert schema.encoding == "jsonschema"
            assert schema.data == codec.json_schema(codec.TYPES_BY_NAME[name])
            json.loads(schema.data)
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {k for k, _ in samples}
        assert all(c.message_encoding == "msgpack" for c in topics.values())
        assert summary.statistics is not None and summary.statistics.message_count == len(samples) + 1
        assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        got = list(reader.iter_messages(log_time_order=False))
        meta = list(reader.iter_metadata())
    assert meta and meta[0].metadata["site"] == SITE
    assert len(got) == len(samples) + 1
    by_key = {}
    for schema, channel, message in got:
        decoded = codec.decode(message.data, codec.TYPES_BY_NAME[schema.name])
        by_key.setdefault(channel.topic, []).append((decoded, message))
    for i, (key, msg) in enumerate(samples):
        decoded, message = by_key[key][0]
        assert decoded == msg
        assert message.log_time == 1_000 + i
        expected_publish = getattr(msg, "capture_time_ns", 0) or message.log_time
        assert message.publish_time == expected_publish
    photo_key = samples[0][0]
    assert [mm.sequence for _, mm in by_key[photo_key]] == [0, 1]

    # Our own reader agrees (the second photo is byte for byte the first: read once unless asked for every record).
    rows = [(r.key, r.type_name, r.payload, r.log_time_ns) for r in mcapio.iter_messages(path, dedupe=False)]
    assert [(k, t) for k, t, _, _ in rows[:-1]] == [(k, codec.type_name(msg)) for k, msg in samples]
    assert rows[-1][3] == 5_000
    assert [(k, t) for k, t, _, _ in mcapio.iter_recording(path)] == [(k, codec.type_name(msg)) for k, msg in samples]


def test_recorder_keeps_invalid_payloads(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with mcapio.RecordingWriter(path) as w:
        info = w.write("constructaide/t/photo/cam-a", b"\xc1 not msgpack", 7)
    assert info.type_name == mcapio.INVALID_SCHEMA_NAME and info.error
    rows = list(mcapio.iter_recording(path))
    assert rows == [("constructaide/t/photo/cam-a", mcapio.INVALID_SCHEMA_NAME, b"\xc1 not msgpack", 7)]


def test_recording_reads_a_message_recorded_twice_once(tmp_path: Path) -> None:
    """The recorder records at least once (a message in a chunk just before a kill comes again after the restart,
    in the next file): readers skip byte-identical repeats of a key and payload, not a different payload."""
    key = "constructaide/t/registration/cam-a/p1"
    first = tmp_path / "a.mcap"
    with mcapio.RecordingWriter(first) as w:
        w.write(key, b"\x91\x01", 1)
        w.write(key, b"\x91\x02", 2)
    second = tmp_path / "b.mcap"
    with mcapio.RecordingWriter(second) as w:
        w.write(key, b"\x91\x01", 3)  # the same message again (re-sent after a kill)
        w.write("constructaide/t/registration/cam-a/p2", b"\x91\x01", 4)  # same bytes, another key: kept
    for path in (first, second):
        assert len(list(mcapio.iter_messages(path))) == 2
    from constructaide.recording import iter_messages

    index = tmp_path / "t.index.json"
    files = [{"name": n, "started_ns": i, "state": "closed"} for i, n in enumerate(("a.mcap", "b.mcap"))]
    index.write_text(json.dumps({"version": 1, "files": files}))
    got = [(r.key, r.payload, r.log_time_ns) for r in iter_messages(index)]
    assert got == [
        (key, b"\x91\x01", 1),
        (key, b"\x91\x02", 2),
        ("constructaide/t/registration/cam-a/p2", b"\x91\x01", 4),
    ]
    assert len(list(iter_messages(index, dedupe=False))) == 4


_CHILD = textwrap.dedent(
    """
    import sys
    import numpy as np
    from nodes.recorder.mcapio import RecordingWriter
    from schemas import codec, keys
    from schemas import messages as m

    rng = np.random.default_rng(0)
    w = RecordingWriter(sys.argv[1], flush_on="photo", chunk_size=64 * 1024 * 1024)
    for i in range(100000):
        print(f"start {i}", flush=True)
        pid = f"p{i}"
        clicks = m.AnchorClicks(site="t", photo_id=pid, points=())
        w.write(keys.key(keys.ANCHORS, site="t", photo=pid), codec.encode(clicks), i)
        data = rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes()
        photo = m.Photo(site="t", photo_id=pid, camera_id="cam-a", capture_time_ns=i, data=data)
        w.write(keys.key(keys.PHOTO, site="t", camera="cam-a"), codec.encode(photo), i)
        print(f"done {i}", flush=True)
    """
)


def test_recorder_sigkill_then_repair_loses_at_most_last_event(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    lines: list[str] = []
    with subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], cwd=REPO, stdout=subprocess.PIPE, text=True, bufsize=1
    ) as proc:
        try:
            assert proc.stdout is not None
            for line in proc.stdout:  # blocks on the pipe, no sleeps
                lines.append(line.strip())
                if line.strip() == "done 5":
                    os.kill(proc.pid, signal.SIGKILL)
                    break
            lines += [ln for ln in proc.stdout.read().splitlines() if ln]
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    started = max(int(ln.split()[1]) for ln in lines if ln.startswith("start"))
    done = max(int(ln.split()[1]) for ln in lines if ln.startswith("done"))
    assert done >= 5

    # The killed file has no footer: the strict reader refuses it with a helpful message.
    with pytest.raises(mcapio.RecordingError, match="repair"):
        list(mcapio.iter_recording(path))

    out = tmp_path / "repaired.mcap"
    report = mcapio.repair(path, out)
    assert not report.was_complete
    photos = [codec.decode(p) for k, t, p, _ in mcapio.iter_recording(out) if t == "constructaide.Photo"]
    anchors = [codec.decode(p) for k, t, p, _ in mcapio.iter_recording(out) if t == "constructaide.AnchorClicks"]
    ids = [p.photo_id for p in photos]
    assert ids == [f"p{i}" for i in range(len(ids))], "recovered photos are a gap-free prefix"
    # every event the child had finished before the one in progress survives (at most the last is lost)
    assert len(ids) >= started, (started, done, len(ids))
    assert len(ids) >= done + 1
    assert [a.photo_id for a in anchors][: len(ids)] == ids
    assert all(len(p.data) == 200_000 for p in photos)
    # mcap's own indexed reader accepts the repaired file
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == report.messages


def test_recorder_repair_stops_at_corrupt_chunk_and_keeps_complete_files(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    with mcapio.RecordingWriter(path) as w:
        for i in range(6):
            photo = m.Photo(site=SITE, photo_id=f"p{i}", capture_time_ns=i, data=bytes([i]) * 5000)
            w.write(keys.key(keys.PHOTO, site=SITE, camera="c"), codec.encode(photo), i)
    same = mcapio.repair(path, tmp_path / "same.mcap")
    assert same.was_complete and same.messages == 6 and same.dropped_bytes == 0
    assert [r[2] for r in mcapio.iter_recording(tmp_path / "same.mcap")] == [r[2] for r in mcapio.iter_recording(path)]

    # Flip a byte inside the 4th chunk's compressed data: chunks 1-3 survive, the CRC catches the 4th.
    with open(path, "rb") as f:
        offsets = [ci.chunk_start_offset for ci in make_reader(f).get_summary().chunk_indexes]  # type: ignore[union-attr]
    data = bytearray(path.read_bytes())
    data[offsets[3] + 60] ^= 0xFF
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    report = mcapio.repair(broken, broken)  # in place
    assert report.messages == 3 and report.stopped_at_byte == offsets[3]
    assert "corrupt" in report.reason
    assert [codec.decode(r[2]).photo_id for r in mcapio.iter_recording(broken)] == ["p0", "p1", "p2"]

    with pytest.raises(ValueError, match="not an MCAP"):
        mcapio.repair(_write(tmp_path / "x.mcap", b"hello"), tmp_path / "y.mcap")


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _timed_recording(path: Path) -> None:
    with mcapio.RecordingWriter(path) as w:
        for i, t in enumerate([10_000_000_000, 11_000_000_000, 13_000_000_000]):
            photo = m.Photo(site="old", photo_id=f"p{i}", capture_time_ns=t, data=b"x")
            w.write(keys.key(keys.PHOTO, site="old", camera="c"), codec.encode(photo), t)
            reg = m.Registration(site="old", photo_id=f"p{i}", status="failed")
            w.write(keys.key(keys.REGISTRATION, site="old", camera="c", photo=f"p{i}"), codec.encode(reg), t + 1)


def test_recorder_replay_timing_filters_and_site(tmp_path: Path) -> None:
    path = tmp_path / "timed.mcap"
    _timed_recording(path)

    clock = [0.0]
    sleeps: list[float] = []

    def fake_sleep(secs: float) -> None:
        sleeps.append(secs)
        clock[0] += secs

    sent: list[tuple[str, bytes]] = []
    n = mcapio.replay(
        path,
        lambda k, p: sent.append((k, p)),
        2.0,
        topics=["constructaide/*/photo/*"],
        sleep=fake_sleep,
        monotonic=lambda: clock[0],
    )
    assert n == 3 and len(sent) == 3
    assert sleeps == pytest.approx([0.5, 1.0])  # 1 s and 2 s gaps at rate 2
    assert all(codec.decode(p).site == "old" for _, p in sent)

    sent.clear()
    n = mcapio.replay(path, lambda k, p: sent.append((k, p)), "max", site="new", sleep=fake_sleep)
    assert n == 6 and len(sleeps) == 2, "rate max never sleeps"
    assert all(k.startswith("constructaide/new/") for k, _ in sent)
    assert all(codec.decode(p).site == "new" for _, p in sent)
    assert sum(isinstance(codec.decode(p), m.Registration) for _, p in sent) == 3

    assert mcapio.replay(path, lambda k, p: None, "max", types=["Registration"]) == 3
    with pytest.raises(ValueError, match="rate"):
        mcapio.parse_rate("fast")
    with pytest.raises(ValueError, match="rate"):
        mcapio.parse_rate("0")


def test_recorder_node_on_local_bus(tmp_path: Path) -> None:
    from constructaide.runtime import start_node
    from constructaide.runtime.local import LocalBus
    from nodes.recorder.node import SPEC, Config

    out = tmp_path / "node.mcap"
    samples = sample_messages()
    with LocalBus() as bus:
        with start_node(SPEC, Config(site=SITE, path=str(out)), bus) as node:
            for key, msg in samples:
                bus.publish(key, msg)
            bus.publish("constructaide/other/photo/c", samples[0][1])  # another site: not recorded
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="c"), b"garbage")
            assert node.wait_idle(30)
        rows = list(mcapio.iter_recording(out))
    assert [k for k, *_ in rows] == [k for k, _ in samples] + [keys.key(keys.PHOTO, site=SITE, camera="c")]
    assert rows[-1][1] == mcapio.INVALID_SCHEMA_NAME
    assert [codec.decode(p) for _, t, p, _ in rows[:-1]] == [msg for _, msg in samples]


def test_recorder_cli_repair(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from constructaide.errors import UserError
    from nodes.recorder.cli import repair_main

    path = tmp_path / "r.mcap"
    _timed_recording(path)
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    assert repair_main([str(tmp_path / "cut.mcap")]) == 0
    assert "recovered" in capsys.readouterr().out
    assert (tmp_path / "cut.repaired.mcap").is_file()
    list(mcapio.iter_recording(tmp_path / "cut.repaired.mcap"))  # valid, complete
    with pytest.raises(UserError, match="no such recording"):
        repair_main([str(tmp_path / "missing.mcap")])


def test_recorder_repair_any_truncation_point_gives_a_prefix(tmp_path: Path) -> None:
    """Cut a recording at many byte offsets: repair always succeeds and keeps a prefix of the messages."""
    path = tmp_path / "src.mcap"
    with mcapio.RecordingWriter(path) as w:
        for i in range(8):
            photo = m.Photo(site=SITE, photo_id=f"p{i}", capture_time_ns=i, data=bytes([i]) * 3000)
            w.write(keys.key(keys.PHOTO, site=SITE, camera="c"), codec.encode(photo), i)
            w.write(
                keys.key(keys.NEEDS_ANCHOR, site=SITE, photo=f"p{i}"),
                codec.encode(m.NeedsAnchor(site=SITE, photo_id=f"p{i}", reason="r")),
                i,
            )
    full = [r[2] for r in mcapio.iter_recording(path)]
    data = path.read_bytes()
    rng = np.random.default_rng(1)
    cuts = sorted(set(rng.integers(8, len(data), 60).tolist()) | {8, 9, len(data) - 1})
    counts = []
    for cut in cuts:
        src = tmp_path / "cut.mcap"
        src.write_bytes(data[:cut])
        report = mcapio.repair(src, tmp_path / "fixed.mcap")
        got = [r[2] for r in mcapio.iter_recording(tmp_path / "fixed.mcap")]
        assert got == full[: len(got)] and report.messages == len(got)
        counts.append(len(got))
    assert counts == sorted(counts), "more bytes never recover fewer messages"
    assert counts[0] == 0 and counts[-1] == len(full)


@pytest.mark.zenoh
def test_recorder_replay_cli_over_zenoh(tmp_path: Path) -> None:
    """``replay`` waits for a live node on the target site, then re-publishes every message there."""
    from constructaide.runtime import BusConfig, open_bus
    from nodes.recorder.cli import replay_main

    path = tmp_path / "timed.mcap"
    _timed_recording(path)
    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"])) as bus:
        port = bus.listen_port()
        got = bus.collect("constructaide/moved/**")
        token = bus.declare_token(keys.key(keys.LIVELINESS, site="moved", node="test", instance="x"))
        try:
            argv = [str(path), "--rate", "max", "--site", "moved", "--connect", f"tcp/127.0.0.1:{port}"]
            argv += ["--listen", "tcp/127.0.0.1:0", "--wait-secs", "20"]
            assert replay_main(argv) == 0
            items = got.wait(count=6, timeout=30)
        finally:
            token.close()
            got.close()
    assert sorted(k for k, _ in items) == sorted(
        [keys.key(keys.PHOTO, site="moved", camera="c")] * 3
        + [keys.key(keys.REGISTRATION, site="moved", camera="c", photo=f"p{i}") for i in range(3)]
    )
    assert all(msg.site == "moved" for _, msg in items)


def test_recorder_node_refuses_to_overwrite(tmp_path: Path) -> None:
    from constructaide.errors import UserError
    from constructaide.runtime import start_node
    from constructaide.runtime.local import LocalBus
    from nodes.recorder.node import SPEC, Config

    existing = tmp_path / "taken.mcap"
    existing.write_bytes(b"keep me")
    with LocalBus() as bus, pytest.raises(UserError, match="already exists"):
        with start_node(SPEC, Config(site=SITE, path=str(existing)), bus):
            pass
    assert existing.read_bytes() == b"keep me"
    # default naming: <directory>/<site>-<UTC>.mcap, never reusing a name
    first = mcapio.new_recording_path(tmp_path / "recs", SITE)
    first.touch()
    second = mcapio.new_recording_path(tmp_path / "recs", SITE)
    assert first != second and first.name.startswith(f"{SITE}-") and first.name.endswith("Z.mcap")


@pytest.mark.zenoh
def test_recorder_node_process_sigkilled_mid_stream_over_zenoh(tmp_path: Path) -> None:
    """The recorder node as its own process on zenoh, SIGKILLed while photos stream in."""
    from constructaide.runtime import BusConfig, open_bus

    out = tmp_path / "node-killed.mcap"
    data = bytes(range(256)) * 1024  # 256 KiB
    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"])) as bus:
        port = bus.listen_port()
        argv = [sys.executable, "-m", "nodes.recorder.node", "--site", SITE, "--set", f"path={out}", "-v"]
        argv += ["--connect", f"tcp/127.0.0.1:{port}", "--listen", "tcp/127.0.0.1:0"]
        with subprocess.Popen(argv, cwd=REPO, stderr=subprocess.PIPE, text=True, bufsize=1) as proc:
            try:
                bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=SITE, node="recorder")], timeout=60)
                assert proc.stderr is not None
                for i in range(8):
                    photo = m.Photo(site=SITE, photo_id=f"p{i}", camera_id="c", capture_time_ns=i, data=data)
                    bus.publish(keys.key(keys.PHOTO, site=SITE, camera="c"), photo)
                    if i < 6:  # wait (on the pipe) until the recorder has flushed this photo
                        for line in proc.stderr:
                            if "flushed" in line and "constructaide.Photo" in line:
                                break
                os.kill(proc.pid, signal.SIGKILL)
            finally:
                if proc.poll() is None:
                    proc.kill()
                proc.wait(timeout=30)
                if proc.stderr is not None:
                    proc.stderr.read()
    assert proc.returncode == -signal.SIGKILL
    report = mcapio.repair(out, tmp_path / "fixed.mcap")
    ids = [codec.decode(p).photo_id for _, t, p, _ in mcapio.iter_recording(tmp_path / "fixed.mcap")]
    assert ids == [f"p{i}" for i in range(len(ids))] and report.messages == len(ids)
    assert len(ids) >= 6, "every photo the recorder confirmed before the kill is recovered"
