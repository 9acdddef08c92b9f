"""The simulated user: clicks on visible element corners (the exact model vertex, the pixel within the click
noise of its projection), reproducible mis-clicks at about 1 in 20, the corner test on crafted images, and the
demo's answering loop on an in-process bus."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from constructaide import camera as cam
from constructaide.app.demo import _finished, _SimulatedUser
from constructaide.bimgeom import glb_to_meshes
from constructaide.runtime.local import LocalBus
from constructaide.synth.clicker import (
    NOISE_PX,
    SLIP_PX,
    SiteClicker,
    TooFewCorners,
    _looks_like_corner,
    click_points,
    simulated_clicks,
)
from constructaide.synth.truth import load_depth, load_ids, true_camera
from nodes.ingest.photos import photo_from_file
from schemas import codec, keys
from schemas.messages import AnchorClicks, NeedsAnchor, Registration


@pytest.fixture(scope="module", params=[0, 7], ids=["seed0", "seed7"])
def site(request, small_site: Path, small_site_seed7: Path) -> Path:
    return small_site if request.param == 0 else small_site_seed7


@pytest.fixture(scope="module")
def user(site: Path) -> SiteClicker:
    return SiteClicker(site)


def test_clicks_land_on_visible_corners(site: Path, user: SiteClicker) -> None:
    """On every photo: each model point is an exact model vertex (or a crossing of two elements' edges), the
    clicks that are not mis-clicks lie within the noise of its true projection, and the element it belongs to is
    what the photo shows there at the right depth."""
    meshes = glb_to_meshes((site / "model" / "building.glb").read_bytes())
    vertices = np.unique(np.round(np.vstack([v for v, _ in meshes.values()]), 4), axis=0)
    err, n_sets, n_vertex, n_points = [], 0, 0, 0
    for rel in sorted(user.cameras):
        try:
            c = user.clicks(rel)
        except TooFewCorners:
            continue
        n_sets += 1
        intr, world_from_camera = true_camera(site, rel, user.cameras)
        proj, z = cam.project_points(intr, cam.invert_rigid(world_from_camera), c.points_in_world_m)
        assert np.all(z > 0)
        assert np.allclose(proj, c.target_px, atol=1e-6)
        good = np.ones(len(proj), dtype=bool)
        good[c.mis_clicked] = False
        err += list(np.linalg.norm(c.pixels_px[good] - proj[good], axis=1))
        ids, depth = load_ids(site, rel), load_depth(site, rel)
        for (u, v), zz in zip(np.round(proj).astype(int), z, strict=True):
            win_ids, win_d = ids[v - 1 : v + 2, u - 1 : u + 2], depth[v - 1 : v + 2, u - 1 : u + 2]
            assert np.any(win_ids > 0)  # on an element
            assert np.min(np.abs(win_d - zz)) <= 0.02 * zz + 0.05  # visible: nothing in front of the corner
        d = np.abs(c.points_in_world_m[:, None] - vertices[None]).max(axis=-1).min(axis=1)
        n_vertex += int(np.sum(d < 1e-3))
        n_points += len(d)
        assert np.ptp(c.pixels_px[:, 0]) > 0.3 * intr.width_px  # spread over the image
    assert n_sets >= 20
    err = np.asarray(err)
    # Gaussian noise of 1.5 px per axis: radial rms 2.1 px; 5 sigma is never reached in a few hundred clicks.
    assert 1.7 < float(np.sqrt(np.mean(err**2))) < 2.5 and float(err.max()) < 5 * NOISE_PX
    assert n_vertex >= 0.9 * n_points  # model vertices, the rest edge crossings


def test_clicks_are_reproducible_per_seed(site: Path, user: SiteClicker) -> None:
    rel = sorted(user.cameras)[0]
    a, b, other = user.clicks(rel, seed=3), user.clicks(rel, seed=3), user.clicks(rel, seed=4)
    assert np.array_equal(a.pixels_px, b.pixels_px) and np.array_equal(a.points_in_world_m, b.points_in_world_m)
    assert np.array_equal(a.mis_clicked, b.mis_clicked)
    assert not np.array_equal(a.pixels_px, other.pixels_px)
    px, world = simulated_clicks(site, rel, seed=3, cameras=user.cameras)  # the old interface, same user
    assert np.array_equal(px, a.pixels_px) and np.array_equal(world, a.points_in_world_m)


def test_mis_click_rate_and_kinds_over_many_photos() -> None:
    """About 1 click in 20 is a gross mis-click: a slip 10-60 px off or a neighbouring corner clicked instead."""
    rng = np.random.default_rng(0)
    n_clicks = n_miss = 0
    kinds: dict[str, int] = {"neighbour": 0, "slip": 0}
    for k in range(3000):
        target = rng.uniform([20, 20], [940, 520], (40, 2))
        world = rng.normal(size=(40, 3))
        c = click_points(target, world, np.random.default_rng([k, 1]), (960, 540))
        n_clicks += len(c.pixels_px)
        n_miss += len(c.mis_clicked)
        good = np.setdiff1d(np.arange(len(c.pixels_px)), c.mis_clicked)
        assert np.all(np.linalg.norm(c.pixels_px[good] - c.target_px[good], axis=1) < 5 * NOISE_PX)
        for i, kind in zip(c.mis_clicked, c.miss_kinds, strict=True):
            kinds[kind] += 1
            off = np.linalg.norm(c.pixels_px[i] - c.target_px[i])
            if kind == "slip":
                assert SLIP_PX[0] - 1e-9 <= off <= SLIP_PX[1] + 1e-9
            else:  # the click lands on another clickable corner, within the noise
                d = np.linalg.norm(target - c.pixels_px[i], axis=1)
                assert d.min() < 5 * NOISE_PX and off > 5
    rate = n_miss / n_clicks
    assert 0.045 < rate < 0.055, rate  # 36000 clicks: standard error 0.0011
    assert kinds["neighbour"] > 0.3 * n_miss and kinds["slip"] > 0.3 * n_miss


def test_mis_click_rate_on_the_sites(small_site: Path, small_site_seed7: Path) -> None:
    n_clicks = n_miss = 0
    for site in (small_site, small_site_seed7):
        user = SiteClicker(site)
        for rel in sorted(user.cameras):
            for seed in range(4):
                try:
                    c = user.clicks(rel, seed=seed)
                except TooFewCorners:
                    continue
                n_clicks += len(c.pixels_px)
                n_miss += len(c.mis_clicked)
    assert n_clicks > 1500
    assert 0.03 < n_miss / n_clicks < 0.07, (n_miss, n_clicks)  # about 1700 clicks: standard error 0.005


def test_fewer_clicks_when_fewer_corners_are_visible() -> None:
    rng = np.random.default_rng(1)
    c = click_points(rng.uniform(0, 500, (5, 2)), rng.normal(size=(5, 3)), rng, (640, 480))
    assert len(c.pixels_px) == 5 and c.few and c.n_clickable == 5
    with pytest.raises(TooFewCorners):
        click_points(rng.uniform(0, 500, (3, 2)), rng.normal(size=(3, 3)), rng, (640, 480))


def _scene(ids: np.ndarray, depth: np.ndarray):
    return cam.centered_intrinsics(ids.shape[1], ids.shape[0], 500.0), ids.astype(np.uint16), depth


def test_corner_test_on_crafted_images() -> None:
    """An L corner of a square, a T junction and a crease corner are corners; points along a straight edge, inside a
    face, or on an edge a few pixels beside a corner are not."""
    H = W = 60
    ids = np.zeros((H, W), np.uint16)
    ids[20:50, 20:50] = 1  # a square: its corner at (19.5, 19.5) between pixel centres
    ids[35:50, 35:50] = 2  # another element inside: T junctions at (34.5, 49.5), (49.5, 34.5)...
    depth = np.full((H, W), 10.0, np.float32)
    intr, ids_u16, d = _scene(ids, depth)
    pts = np.array(
        [
            [19.5, 19.5],  # L corner of the square
            [34.5, 49.5],  # T: element 2's left edge meets the square's bottom edge
            [30.0, 19.5],  # along the square's top edge
            [30.0, 30.0],  # inside the square
            [22.5, 19.5],  # on the top edge, 3 px beside the corner
        ]
    )
    got = _looks_like_corner(intr, ids_u16, d, pts)
    assert got.tolist() == [True, True, False, False, False]
    # A crease: two faces of one element meeting at a ridge (depth from two planes), seen as one ID.
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    x = (xx - (W - 1) / 2) / 500.0
    ridge = np.where(xx < 30, 8.0 / (1 - 6 * x), 8.0 / (1 + 6 * x))  # planes z = 8 m +- 6 X, ridge at X = 0
    one = np.zeros((H, W), np.uint16)
    one[15:, :] = 1  # the element below row 15, sky above: corners where the ridge meets the top edge
    ridge = np.where(one > 0, ridge, 0.0).astype(np.float32)
    intr, one_u16, d = _scene(one, ridge)
    got = _looks_like_corner(intr, one_u16, d, np.array([[29.5, 14.5], [40.0, 14.5], [29.5, 40.0]]))
    assert got.tolist() == [True, False, False]  # ridge meets the outline; outline only; ridge only


def test_simulated_user_answers_each_request_once(small_site: Path) -> None:
    files = sorted((small_site / "photos" / "phone").rglob("*.jpg"))[:2]
    photos = {str(f.relative_to(small_site / "photos")): photo_from_file(f, None, "s", "UTC") for f in files}
    (rel_a, pa), (_, pb) = photos.items()
    with LocalBus() as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site="s"))
        clicks = bus.collect(keys.pattern(keys.ANCHORS, site="s"))
        failed = Registration(site="s", photo_id=pa.photo_id, status="failed", message="too few tracks")
        bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pa.photo_id), failed)
        with _SimulatedUser(bus, "s", small_site, photos, regs) as user:
            # Never asked for: a failed registration alone is final.
            assert _finished(regs.items, {pa.photo_id}, user) == {pa.photo_id}
            ask = NeedsAnchor(site="s", photo_id=pa.photo_id, reason="too few tracks")
            for _ in range(2):
                bus.publish(keys.key(keys.NEEDS_ANCHOR, site="s", photo=pa.photo_id), ask)
            clicks.wait(1, timeout=30)
            # Asked and answered: not final until a registration that did not fail arrives.
            assert _finished(regs.items, {pa.photo_id, pb.photo_id}, user) == set()
            done = Registration(site="s", photo_id=pa.photo_id, status="anchor")
            bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pa.photo_id), done)
            assert _finished(regs.items, {pa.photo_id, pb.photo_id}, user) == {pa.photo_id}
            # A request for a photo registered meanwhile is not clicked.
            ok_b = Registration(site="s", photo_id=pb.photo_id, status="auto")
            bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pb.photo_id), ok_b)
            ask_b = NeedsAnchor(site="s", photo_id=pb.photo_id, reason="too few tracks")
            bus.publish(keys.key(keys.NEEDS_ANCHOR, site="s", photo=pb.photo_id), ask_b)
        assert user.answered == {pa.photo_id} and user.requested == {pa.photo_id, pb.photo_id}
    assert len(clicks.items) == 1  # the repeated request is not answered twice
    msg = clicks.items[0][1]
    assert isinstance(msg, AnchorClicks) and msg.image_name == rel_a and len(msg.points) == 12
    want = SiteClicker(small_site).clicks(rel_a)  # the realistic user's clicks, mis-clicks included
    assert [p.pixel_px for p in msg.points] == [tuple(p) for p in want.pixels_px.tolist()]
    assert codec.decode(codec.encode(msg)) == msg
