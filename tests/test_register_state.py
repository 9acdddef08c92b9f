"""Durable register state: the map round-trips through the state blobs; a restarted node resumes from its state
file and registers the next frame by the fast path without a new anchor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_register_stream_node import SITE, H, W, clicks_msg, make_photo
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide.runtime import start_node
from constructaide.runtime.history import Ledger
from constructaide.runtime.local import LocalBus
from nodes.register import state
from nodes.register.node import SPEC, Config
from schemas import keys
from schemas.messages import Registration


def frames(n: int):
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(5)
    poses = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(n - 1)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k) for k, (i, t) in enumerate(poses)]
    return intr, T, photos


def test_restart_resumes_the_map_and_registers_the_next_frame_without_an_anchor(tmp_path: Path) -> None:
    intr, T, photos = frames(4)
    photo_key = keys.key(keys.PHOTO, site=SITE, camera="cam-a")
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        bus.publish(photo_key, photos[0])
        px, pts = anchor_clicks(intr, T, noise_px=0.2)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
        )
        for p in photos[1:3]:
            bus.publish(photo_key, p)
        regs.wait(3, timeout=60)
        assert node.wait_idle(30)
        before = {pid: rec.world_from_camera.copy() for pid, rec in node.obj.registrar.poses.items()}
        sparse_revision = node.obj.sparse_revision
    led = Ledger(tmp_path / f"{SITE}-register.sqlite")
    blobs = led.load_state()
    assert led.handled_count() == 4
    assert set(blobs) == {"map", f"feat/{photos[0].photo_id}"}  # the anchor's features (fast-path frames: none)
    led.close()
    # A new process (a fresh bus: nothing to replay) resumes from the file.
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path) as node:
        reg = node.obj.registrar
        assert set(reg.poses) == set(before)
        for pid, T0 in before.items():
            np.testing.assert_array_equal(reg.poses[pid].world_from_camera, T0)
        assert node.obj.sparse_revision == sparse_revision
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        bus.publish(photo_key, photos[3])
        ((_, r),) = regs.wait(1, timeout=60)
        assert node.wait_idle(30)
        assert isinstance(r, Registration) and r.photo_id == photos[3].photo_id
        assert r.status == "auto" and r.method == "fastpath" and r.reprojection_rms_px < 1.0, r.message
        assert needs.items == []


def test_state_blobs_round_trip() -> None:
    class Holder:
        pass

    from nodes.register.streaming import StreamingRegistrar

    a = Holder()
    a.registrar = StreamingRegistrar(site=SITE)  # type: ignore[attr-defined]
    a.registrar.depth_lookup = lambda *x: None  # type: ignore[attr-defined]  # not kept (not picklable anyway)
    from nodes.register.bimsite import BimMeshes
    from nodes.register.inbox import Inbox

    inbox = Inbox(4, 4, 4)
    inbox.asked_groups.add("cam-a")
    bim = BimMeshes()
    bim.meshes = {"m": (np.zeros((3, 3)), np.zeros((1, 3), np.int32))}
    bim.ref_of = {"g": "m"}
    bim.terrain_height_m = 1.5
    for f, v in zip(state.MAP_FIELDS, (inbox, 3, 1), strict=True):
        setattr(a, f, v)
    a.bim = bim  # type: ignore[attr-defined]
    blobs = {**state.dump_map(a), "bim": state.dump_bim(a)}
    assert a.registrar.depth_lookup is not None  # type: ignore[attr-defined]  # put back after the dump
    b = Holder()
    assert state.load_into(b, blobs)
    assert b.registrar.depth_lookup is None and b.registrar.site == SITE  # type: ignore[attr-defined]
    assert b.inbox.asked_groups == {"cam-a"} and b.sparse_revision == 3  # type: ignore[attr-defined]
    assert b.bim.terrain_height_m == 1.5 and b.bim.ref_of == {"g": "m"}  # type: ignore[attr-defined]
