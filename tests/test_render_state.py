"""Durable render state: a restarted render node keeps its photos and registrations and does not redraw them."""

from __future__ import annotations

from pathlib import Path

from render_scenes import four_box_model
from test_render_node import _photo_and_reg

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
