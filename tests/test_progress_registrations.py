"""The progress engine reads a photo at its solved registration, not at the register node's outline polish."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nodes.progress import batch
from nodes.progress.engine import ProgressEngine
from nodes.progress.registrations import ignores_polish
from nodes.recorder.mcapio import RecordingWriter
from schemas import codec, keys
from schemas.messages import BimModel, Intrinsics, Registration

INTR = Intrinsics(width_px=640, height_px=480, f_px=500.0, cx_px=320.0, cy_px=240.0)


def reg(photo: str, x_m: float, method: str, status: str = "auto") -> Registration:
    pose = np.eye(4)
    pose[0, 3] = x_m
    return Registration(
        site="t",
        photo_id=photo,
        camera_id="cam",
        intrinsics=INTR,
        world_from_camera=tuple(float(v) for v in pose.ravel()),
        status=status,  # type: ignore[arg-type]
        method=method,
    )


def test_the_outline_polish_does_not_replace_the_solved_registration() -> None:
    solved, polished, again = reg("a", 0.0, "fastpath"), reg("a", 0.1, "fastpath+outline"), reg("a", 0.5, "pnp")
    assert ignores_polish(solved, polished) and not ignores_polish(None, polished)
    assert not ignores_polish(solved, again) and not ignores_polish(polished, again)
    engine = ProgressEngine()
    assert engine.add_registration(solved)
    assert not engine.add_registration(polished)  # nothing changed: the node does not read the photo again
    assert engine.registrations["a"] is solved
    assert engine.add_registration(again) and engine.registrations["a"] is again  # a new solve replaces it
    # a polish alone (its solved registration never reached this node) is better than nothing
    assert engine.add_registration(reg("b", 0.1, "anchor+outline", "anchor")) and "b" in engine.registrations
    assert engine.add_registration(reg("b", 0.0, "", "failed")) and "b" not in engine.registrations


def test_recording_reader_keeps_the_solved_registration(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    with RecordingWriter(path) as w:
        w.write(keys.key(keys.BIM_MODEL, site="t"), codec.encode(BimModel(site="t", revision="r1")))
        for r in (reg("a", 0.0, "fastpath"), reg("a", 0.1, "fastpath+outline"), reg("c", 0.2, "anchor+outline")):
            w.write(keys.key(keys.REGISTRATION, site="t", camera="cam", photo=r.photo_id), codec.encode(r))
    got = batch.read_inputs(path).registrations
    assert got["a"].method == "fastpath" and got["c"].method == "anchor+outline"
