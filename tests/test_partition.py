"""Partitioned workers: stable camera assignment (rendezvous hashing) and per-message routing in the runner."""

from __future__ import annotations

import threading
from collections import Counter

import msgspec
import pytest

from constructaide.partition import PARK, SKIP, TAKE, Partition, Router, assign, owner, worker_names
from constructaide.runtime import Input, NodeContext, NodeSpec, start_node
from constructaide.runtime.local import LocalBus
from schemas import keys
from schemas.messages import AnchorClicks, AnchorPoint, Photo, Registration

SITE = "part"
CAMERAS = [f"cam-{i:03d}" for i in range(100)]


def test_assignment_is_deterministic_and_covers_every_camera_once() -> None:
    a = assign(CAMERAS, worker_names(3))
    b = assign(reversed(CAMERAS), ("w2", "w0", "w1"))
    assert a == b
    flat = [c for cams in a.values() for c in cams]
    assert sorted(flat) == sorted(CAMERAS)
    # spread: each of 3 workers gets a fair share of 100 cameras (binomial, far from 0 or all)
    assert all(15 <= len(v) <= 55 for v in a.values()), {w: len(v) for w, v in a.items()}


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_adding_a_worker_moves_only_the_cameras_it_takes(n: int) -> None:
    before = {c: owner(c, worker_names(n)) for c in CAMERAS}
    after = {c: owner(c, worker_names(n + 1)) for c in CAMERAS}
    moved = [c for c in CAMERAS if before[c] != after[c]]
    new = f"w{n}"
    assert moved, "the new worker took no camera"
    assert all(after[c] == new for c in moved)
    assert all(before[c] == after[c] for c in CAMERAS if after[c] != new)


def test_removing_a_worker_moves_only_its_cameras() -> None:
    ws = worker_names(4)
    gone = "w1"
    rest = tuple(w for w in ws if w != gone)
    before = {c: owner(c, ws) for c in CAMERAS}
    after = {c: owner(c, rest) for c in CAMERAS}
    for c in CAMERAS:
        if before[c] != gone:
            assert after[c] == before[c]
        else:
            assert after[c] != gone


def test_partition_parse_and_key_expressions() -> None:
    p = Partition.parse("1/2", ["cam-a", "cam-b", "cam-c"])
    assert p.spec() == "1/2" and p.workers == ("w0", "w1")
    other = Partition.parse("0/2", ["cam-a", "cam-b", "cam-c"])
    mine, theirs = p.my_cameras(), other.my_cameras()
    assert mine is not None and theirs is not None
    assert sorted(mine + theirs) == ["cam-a", "cam-b", "cam-c"]
    kes = p.camera_keyexprs(keys.PHOTO, site=SITE)
    assert kes == [keys.key(keys.PHOTO, site=SITE, camera=c) for c in (*mine, keys.PHONE)]
    assert Partition.parse("0/2").camera_keyexprs(keys.PHOTO, site=SITE) == [keys.pattern(keys.PHOTO, site=SITE)]
    for bad in ("2/2", "x", "1/0", "-1/2"):
        with pytest.raises(ValueError):
            Partition.parse(bad)
    with pytest.raises(ValueError):
        Partition("w0", ("w0", "w1"), ("phone",))


def test_router_takes_own_skips_others_parks_unknown_photo_keys() -> None:
    p = Partition.parse("0/2", CAMERAS)
    r = Router(p, max_parked=3)
    mine = next(c for c in p.cameras or () if p.owns_camera(c))
    theirs = next(c for c in p.cameras or () if not p.owns_camera(c))
    photo_key = keys.key(keys.PHOTO, site=SITE, camera=mine)
    anchors = keys.key(keys.ANCHORS, site=SITE, photo="p1")
    assert r.route(keys.PHOTO, keys.key(keys.PHOTO, site=SITE, camera=theirs), lambda: "p0") == SKIP
    assert r.route(keys.ANCHORS, anchors, lambda: None) == PARK
    r.park("p1", "clicks")
    assert r.route(keys.PHOTO, photo_key, lambda: "p1") == TAKE
    assert r.release() == ["clicks"] and not r.parked
    assert r.route(keys.ANCHORS, anchors, lambda: None) == TAKE
    phones = [f"ph{i}" for i in range(200)]
    taken = [ph for ph in phones if r.route(keys.PHOTO, keys.key(keys.PHOTO, site=SITE), lambda ph=ph: ph) == TAKE]
    assert taken == [ph for ph in phones if p.owns_phone_photo(ph)] and 50 < len(taken) < 150
    reg_key = keys.key(keys.REGISTRATION, site=SITE, camera=None, photo=phones[0])
    assert r.route(keys.REGISTRATION, reg_key, lambda: None) == (TAKE if phones[0] in taken else SKIP)
    assert r.route(keys.BIM_MODEL, keys.key(keys.BIM_MODEL, site=SITE), lambda: None) == TAKE
    for i in range(5):
        r.park(f"x{i}", i)
    assert len(r.parked) == 3 and r.parked_dropped == 2


class _Cfg(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = SITE


class _Counting:
    """Counts handled photos and anchors per worker (shared dict)."""

    seen: Counter[str] = Counter()
    anchors: Counter[str] = Counter()
    lock = threading.Lock()

    def __init__(self, config: _Cfg, ctx: NodeContext) -> None:
        self.ctx = ctx

    def on_photo(self, msg: Photo, key: str) -> None:
        with self.lock:
            self.seen[msg.photo_id] += 1
        reg = Registration(site=SITE, photo_id=msg.photo_id, camera_id=msg.camera_id, status="failed")
        self.ctx.publish(keys.key(keys.REGISTRATION, site=SITE, camera=msg.camera_id, photo=msg.photo_id), reg)

    def on_anchors(self, msg: AnchorClicks, key: str) -> None:
        with self.lock:
            self.anchors[msg.photo_id] += 1


SPEC = NodeSpec(
    "counting",
    "test",
    _Cfg,
    _Counting,
    (Input(keys.PHOTO, Photo, "on_photo", check_images=False), Input(keys.ANCHORS, AnchorClicks, "on_anchors")),
)


@pytest.mark.parametrize("known_cameras", [True, False])
def test_two_workers_handle_every_photo_once_and_anchors_follow_their_photo(known_cameras: bool) -> None:
    _Counting.seen.clear()
    _Counting.anchors.clear()
    cams = ["cam-north", "cam-east", "cam-south", "cam-west"]
    bus = LocalBus()
    regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
    parts = [Partition.parse(f"{i}/2", cams if known_cameras else None) for i in range(2)]
    photos = [
        Photo(site=SITE, photo_id=f"{cam or 'ph'}-{k}", camera_id=cam, capture_time_ns=k, data=b"x")
        for k in range(6)
        for cam in (*cams, None)
    ]
    pt = AnchorPoint(pixel_px=(1.0, 2.0), point_in_world_m=(0.0, 0.0, 0.0))
    with start_node(SPEC, _Cfg(), bus, partition=parts[0]) as w0, start_node(SPEC, _Cfg(), bus, partition=parts[1]):
        for ph in photos[:10]:  # clicks before their photo (parked) for the first ten, after it for the rest
            bus.publish(
                keys.key(keys.ANCHORS, site=SITE, photo=ph.photo_id),
                AnchorClicks(site=SITE, photo_id=ph.photo_id, points=(pt,) * 4),
            )
        for ph in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera=ph.camera_id), ph)
        for ph in photos[10:]:
            bus.publish(
                keys.key(keys.ANCHORS, site=SITE, photo=ph.photo_id),
                AnchorClicks(site=SITE, photo_id=ph.photo_id, points=(pt,) * 4),
            )
        regs.wait(len(photos), timeout=10)
        assert w0.wait_idle(10)
    assert dict(_Counting.seen) == {ph.photo_id: 1 for ph in photos}
    assert dict(_Counting.anchors) == {ph.photo_id: 1 for ph in photos}
    assert len(regs.items) == len(photos)
    assert 0 < w0.processed < 2 * len(photos)
