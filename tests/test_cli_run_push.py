"""CLI end to end over real zenoh: `run` starts nodes from TOML, `push` publishes photos, the recorder keeps them."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from constructaide.recording import iter_recording
from constructaide.runtime import BusConfig, open_bus
from schemas import codec, keys

pytestmark = pytest.mark.zenoh


def _jpeg_with_exif(path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    img = Image.fromarray(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    exif = Image.Exif()
    exif[0x8769] = {0x9003: f"2026:03:0{seed + 1} 10:00:00", 0x9011: "+01:00"}  # DateTimeOriginal, OffsetTimeOriginal
    buf = io.BytesIO()
    img.save(buf, "JPEG", quality=90, exif=exif)
    path.write_bytes(buf.getvalue())


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "constructaide.app.cli", *args]


def test_run_config_push_and_recording(tmp_path: Path, hub_port: int) -> None:
    site = "clirun"
    mcap = tmp_path / "run.mcap"
    cfg = tmp_path / "site.toml"
    cfg.write_text(f'[site]\nname = "{site}"\n\n[nodes.recorder]\npath = "{mcap}"\n')
    photos = []
    for i in range(3):
        _jpeg_with_exif(p := tmp_path / f"f{i}.jpg", i)
        photos.append(p)
    env = dict(os.environ, CONSTRUCTAIDE_HUB_PORT=str(hub_port))
    run = subprocess.Popen(_cli("run", str(cfg), "--log-dir", str(tmp_path / "logs")), env=env)
    try:
        with open_bus(BusConfig(hub_port=hub_port)) as bus:
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=site, node="recorder")], timeout=60)
        push = subprocess.run(
            _cli("push", *map(str, photos), "--camera", "cam-a", "--site", site, "--tz", "Europe/Amsterdam"),
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert push.returncode == 0, push.stderr
        assert "pushed 3 photo(s)" in push.stdout
    finally:
        run.send_signal(signal.SIGINT)
        assert run.wait(60) == 0
    recorded = [(k, codec.decode(p)) for k, p, *_ in ((r[0], r[2]) for r in iter_recording(mcap))]
    photo_msgs = [m for k, m in recorded if k.startswith(f"constructaide/{site}/photo/cam-a")]
    assert len(photo_msgs) == 3
    assert sorted(m.capture_time_ns for m in photo_msgs)[0] == 1772355600 * 10**9  # 2026-03-01T10:00+01:00


def test_push_bad_file_is_one_clear_line(tmp_path: Path, hub_port: int) -> None:
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not an image at all")
    env = dict(os.environ, CONSTRUCTAIDE_HUB_PORT=str(hub_port))
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        token = bus.declare_token(keys.key(keys.LIVELINESS, site="bad", node="sink", instance="0"))
        r = subprocess.run(_cli("push", str(bad), "--site", "bad"), env=env, capture_output=True, text=True, timeout=60)
        token.close()
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.strip().splitlines() if "error:" in ln]
    assert len(lines) == 1 and "bad.jpg" in lines[0]
    assert "Traceback" not in r.stderr


def test_unknown_command_and_missing_config_are_one_line() -> None:
    r = subprocess.run(_cli("frobnicate"), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "unknown command" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(_cli("run", "/nonexistent/site.toml"), capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "config file not found" in r.stderr and "Traceback" not in r.stderr
