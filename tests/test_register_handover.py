"""State hand-over between partitioned register workers through the durable store: when the worker count changes
(2 -> 3 -> 1), a camera that moves to another worker registers its next frame by the fast path, without new clicks."""

from __future__ import annotations

import itertools
from contextlib import ExitStack
from pathlib import Path

import numpy as np
from test_register_stream_node import SITE, H, W, clicks_msg, make_photo
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide.partition import Partition
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.register.node import SPEC, Config
from schemas import keys
from schemas.messages import Photo, Registration


def camera_frames(seed: int, camera: str, n: int) -> tuple[list[Photo], object]:
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(seed)
    poses = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(n - 1)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), camera, 10 * k + seed) for k, (i, t) in enumerate(poses)]
    return photos, anchor_clicks(intr, T, noise_px=0.2)


def split_cameras() -> tuple[str, str]:
    """Two camera ids that two workers share one each."""
    for a, b in itertools.combinations([f"cam-{c}" for c in "abcdefgh"], 2):
        if all(len(Partition.parse(f"{i}/2", [a, b]).my_cameras() or ()) == 1 for i in range(2)):
            return a, b
    raise AssertionError("no split")


def push(bus: LocalBus, nodes: list, photos: list[Photo]) -> dict[str, Registration]:
    regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
    needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
    for p in photos:
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera=p.camera_id), p)
    regs.wait(len(photos), timeout=60)
    assert all(n.wait_idle(30) for n in nodes)
    assert needs.items == [], [m.reason for _k, m in needs.items]
    return {r.photo_id: r for _k, r in regs.items}


def test_moved_cameras_register_their_next_frame_without_new_clicks(tmp_path: Path) -> None:
    cameras = split_cameras()
    frames = {c: camera_frames(s, c, 5) for s, c in enumerate(cameras, start=1)}

    def workers(stack: ExitStack, bus: LocalBus, count: int) -> list:
        parts = [Partition.parse(f"{i}/{count}", cameras) for i in range(count)] if count > 1 else [None]
        return [
            stack.enter_context(start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path, partition=p))
            for p in parts
        ]

    # Two workers, one camera each: anchored, then two frames by the fast path.
    with LocalBus() as bus, ExitStack() as stack:
        nodes = workers(stack, bus, 2)
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        for photos, (px, pts) in frames.values():
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera=photos[0].camera_id), photos[0])
            bus.publish(
                keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
            )
        regs.wait(2, timeout=60)
        assert all(n.wait_idle(30) for n in nodes)
        push(bus, nodes, [ph for photos, _ in frames.values() for ph in photos[1:3]])
        owner2 = {c: next(i for i, n in enumerate(nodes) if c in n.obj.registrar.fast.tracks) for c in cameras}
        assert sorted(owner2.values()) == [0, 1]
    # Three workers, then one: every camera's next frame (the moved ones' too) by the fast path, no new clicks.
    for count, k in ((3, 3), (1, 4)):
        with LocalBus() as bus, ExitStack() as stack:
            nodes = workers(stack, bus, count)
            got = push(bus, nodes, [photos[k] for photos, _ in frames.values()])
            for photos, _ in frames.values():
                r = got[photos[k].photo_id]
                assert r.status == "auto" and r.method == "fastpath" and r.reprojection_rms_px < 1.0, r.message
            holders = {c: [i for i, n in enumerate(nodes) if c in n.obj.registrar.fast.tracks] for c in cameras}
            assert all(len(h) == 1 for h in holders.values()), holders  # only its owner holds a camera
