"""Durable render state: a restarted render node keeps its photos and registrations and does not redraw them."""

from __future__ import annotations

from pathlib import Path

import msgspec
from render_scenes import four_box_model
from test_render_node import _photo_and_reg

from constructaide.partition import Partition
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.render.node import SPEC, Config
from schemas import keys
from schemas.messages import OcclusionMask


def test_restart_keeps_photos_and_draws_a_new_mask_without_redrawing(tmp_path: Path) -> None:
    model = four_box_model()
    photo, reg = _photo_and_reg()
    cfg = Config(site="t", modes=("state4d",))
    with LocalBus() as bus:
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model, latched=True)
        with start_node(SPEC, cfg, bus, state_dir=tmp_path) as node:
            got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
            bus.publish(keys.key(keys.PHOTO, site="t", camera="cam-a"), photo)
            bus.publish(keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=photo.photo_id), reg)
            got.wait(1, timeout=60)
            assert node.wait_idle(30)
    with LocalBus() as bus:  # a new process: only the latched model comes again
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model, latched=True)
        got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
        with start_node(SPEC, cfg, bus, state_dir=tmp_path) as node:
            assert node.wait_idle(30)
            assert photo.photo_id in node.obj.rendered and got.items == []  # same model revision: no redraw
            mask = OcclusionMask(site="t", photo_id=photo.photo_id, kind="combined", status="ok", mask_png=b"")
            bus.publish(keys.key(keys.OCCLUSION, site="t", kind="combined", photo=photo.photo_id), mask)
            ((_, ov),) = got.wait(1, timeout=60)
            assert ov.photo_id == photo.photo_id


def test_a_camera_moved_to_another_worker_keeps_its_photos(tmp_path: Path) -> None:
    """Two render workers, then one: the one takes the camera's cached photos from worker 1's state file, so a
    later mask redraws a photo drawn there and a photo whose registration comes only now is drawn."""
    cameras = ("cam-a", "cam-b", "cam-c", "cam-d")
    parts = [Partition.parse(f"{i}/2", cameras) for i in range(2)]
    owner = next(i for i, p in enumerate(parts) if p.owns_camera("cam-a"))
    model = four_box_model()
    photo, reg = _photo_and_reg()
    later = msgspec.structs.replace(photo, photo_id="p0000000000000002", capture_time_ns=photo.capture_time_ns + 60)
    later_reg = msgspec.structs.replace(reg, photo_id=later.photo_id, capture_time_ns=later.capture_time_ns)
    cfg = Config(site="t", modes=("state4d",))
    photo_key = keys.key(keys.PHOTO, site="t", camera="cam-a")
    with LocalBus() as bus:
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model, latched=True)
        with (
            start_node(SPEC, cfg, bus, state_dir=tmp_path, partition=parts[0]) as w0,
            start_node(SPEC, cfg, bus, state_dir=tmp_path, partition=parts[1]) as w1,
        ):
            got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
            bus.publish(photo_key, photo)
            bus.publish(keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=photo.photo_id), reg)
            bus.publish(photo_key, later)  # its registration is still to come when the worker goes
            got.wait(1, timeout=60)
            assert w0.wait_idle(30) and w1.wait_idle(30)
            workers = (w0, w1)
            assert set(workers[owner].obj.photos) == {photo.photo_id, later.photo_id}
            assert not workers[1 - owner].obj.photos
    with LocalBus() as bus:  # one plain instance now, with its own (empty) state file
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model, latched=True)
        got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
        with start_node(SPEC, cfg, bus, state_dir=tmp_path) as node:
            assert node.wait_idle(30)
            assert set(node.obj.photos) == {photo.photo_id, later.photo_id} and photo.photo_id in node.obj.rendered
            mask = OcclusionMask(site="t", photo_id=photo.photo_id, kind="combined", status="ok", mask_png=b"")
            bus.publish(keys.key(keys.OCCLUSION, site="t", kind="combined", photo=photo.photo_id), mask)
            bus.publish(keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=later.photo_id), later_reg)
            drawn = got.wait(2, timeout=60)
            assert {ov.photo_id for _, ov in drawn} == {photo.photo_id, later.photo_id}


def test_adopted_overlays_keep_their_model_revision() -> None:
    """A fresh worker taking a camera over takes the revision its overlays were drawn with (the same model arriving
    next redraws nothing: the hand-over test once saw a spurious redraw); a worker already drawing with another
    revision draws the adopted photos again."""
    from types import SimpleNamespace

    from nodes.render import state

    photo, reg = _photo_and_reg()
    source = state.dump(
        SimpleNamespace(
            photos={photo.photo_id: photo},
            registrations={photo.photo_id: reg},
            masks={},
            dirty={},
            rendered={photo.photo_id},
            _photo_bytes=len(photo.data),
            drawn_revision="r1",
        )
    )

    def worker(revision: str | None) -> SimpleNamespace:
        w = SimpleNamespace(
            photos={}, registrations={}, masks={}, dirty={}, rendered=set(), _photo_bytes=0, drawn_revision=revision
        )
        w._mark = lambda pid: w.dirty.__setitem__(pid, ("state4d",))
        return w

    fresh, other = worker(None), worker("r2")
    for w in (fresh, other):
        assert state.adopt_cameras(w, [source], lambda camera: True) == [photo.camera_id]
        assert photo.photo_id in w.rendered and photo.photo_id in w.registrations
    assert fresh.drawn_revision == "r1" and not fresh.dirty
    assert other.drawn_revision == "r2" and list(other.dirty) == [photo.photo_id]
