"""Densification after registration: epipolar-guided matching, track verification and extension.

Seeded synthetic views with known geometry, and the synthetic site's photos with their true cameras (accuracy
of the densified points against the true depth maps, a tolerance band)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from constructaide import camera as cam
from nodes.register.densify import (
    DensifyParams,
    View,
    densify,
    guided_matches,
    select_pairs,
    verify_tracks,
    viewpoint_clusters,
)
from nodes.register.features import extract_features, match_features
from schemas.messages import Intrinsics

INTR = Intrinsics(width_px=960, height_px=540, f_px=800.0, cx_px=479.5, cy_px=269.5, k1=-0.05, k2=0.0)


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 128)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _facade(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on a facade y = 0, x in [-8, 8], z in [0, 9] (world metres)."""
    return np.stack([rng.uniform(-8, 8, n), np.zeros(n), rng.uniform(0, 9, n)], axis=1)


def _view(wfc: np.ndarray, pts: np.ndarray, desc: np.ndarray, rng, noise_px: float = 0.3, t_ns: int = 0) -> View:
    px, z = cam.project_points(INTR, cam.invert_rigid(wfc), pts)
    px = px + rng.normal(0, noise_px, px.shape)
    d = desc + rng.normal(0, 0.02, desc.shape).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scales = 2.5 * 25.0 / np.maximum(z, 1e-3)  # SIFT scale shrinks with depth
    return View(INTR, wfc, px, d.astype(np.float32), scales, t_ns, float(np.median(z)))


def test_guided_matching_disambiguates_repeated_texture() -> None:
    rng = np.random.default_rng(3)
    base = _facade(rng, 300)
    twins = base + np.array([0.0, 0.0, 1.5])  # the same "letter" printed again 1.5 m higher
    desc = _unit(rng, 300)
    pts = np.concatenate([base, twins])
    d = np.concatenate([desc, desc])
    a = _view(cam.look_at((-3.0, -25.0, 4.0), (0.0, 0.0, 4.0)), pts, d, rng)
    b = _view(cam.look_at((6.0, -24.0, 4.0), (0.0, 0.0, 4.0)), pts, d, rng)
    inside = lambda v: np.all((v.keypoints_px >= 0) & (v.keypoints_px < [960, 540]), axis=1)  # noqa: E731
    ok = inside(a) & inside(b)
    ia, ib = np.flatnonzero(ok), np.flatnonzero(ok)
    m = guided_matches(a, b, DensifyParams(), ia, ib)
    correct = m[:, 0] == m[:, 1]
    assert len(m) >= 0.6 * ok.sum()
    assert correct.mean() >= 0.97
    # blind matching (ratio test over the whole image) cannot tell a letter from its twin
    from nodes.register.features import Features

    fa = Features(a.keypoints_px[ia].astype(np.float32), a.descriptors[ia], a.scales_px[ia], 960, 540)
    fb = Features(b.keypoints_px[ib].astype(np.float32), b.descriptors[ib], b.scales_px[ib], 960, 540)
    blind = match_features(fa, fb, ratio=0.8)
    assert len(blind) < 0.1 * ok.sum()


def test_pairs_skip_one_cameras_frames_and_wide_angles() -> None:
    rng = np.random.default_rng(4)
    pts, desc = _facade(rng, 50), _unit(rng, 50)
    fixed0 = _view(cam.look_at((0.0, -30.0, 8.0), (0.0, 0.0, 3.0)), pts, desc, rng, t_ns=1)
    fixed1 = _view(cam.look_at((0.0, -30.0, 8.0), (0.3, 0.0, 3.1)), pts, desc, rng, t_ns=2)  # same mast, jitter
    phone = _view(cam.look_at((8.0, -15.0, 1.6), (0.0, 0.0, 3.0)), pts, desc, rng, t_ns=2)
    side = _view(cam.look_at((-30.0, 2.0, 3.0), (0.0, 0.0, 3.0)), pts, desc, rng, t_ns=2)  # ~90 deg away
    views = [fixed0, fixed1, phone, side]
    depths = [v.scene_depth_m for v in views]
    clusters = viewpoint_clusters(views, depths)
    assert clusters[0] == clusters[1] and len(set(clusters.tolist())) == 3
    pairs = select_pairs(views, depths, DensifyParams())
    assert (0, 1) not in pairs
    assert all(3 not in p for p in pairs)  # too wide for SIFT
    assert (1, 2) in pairs and (0, 2) not in pairs  # one pair per pair of viewpoints, nearest in time


def _three_views(rng: np.random.Generator, n: int = 400):
    pts, desc = _facade(rng, n), _unit(rng, n)
    wa = cam.look_at((0.0, -30.0, 8.0), (0.0, 0.0, 3.0))
    wa2 = cam.look_at((0.0, -30.0, 8.0), (0.2, 0.0, 3.05))  # the same fixed camera the next day
    wb = cam.look_at((10.0, -18.0, 1.6), (0.0, 0.0, 3.0))
    return pts, desc, wa, wa2, wb


def test_densify_triangulates_and_extends_to_the_other_frames() -> None:
    rng = np.random.default_rng(5)
    pts, desc, wa, wa2, wb = _three_views(rng)
    moved = np.arange(len(pts)) < 100  # gone the next day: absent from the second frame
    a = _view(wa, pts, desc, rng, t_ns=1)
    b = _view(wb, pts, desc, rng, t_ns=1)
    a2 = _view(wa2, pts[~moved], desc[~moved], rng, t_ns=2)
    dense = densify([a, a2, b])
    assert (0, 1) not in dense.pairs and dense.num_points >= 0.6 * len(pts)
    # points from the (a, b) pair: feature index = true point index in a and b
    p_a, f_a = dense.observations_of(0)
    err = np.linalg.norm(dense.points_m[p_a] - pts[f_a], axis=1)
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.2
    p_a2, f_a2 = dense.observations_of(1)
    truth_of = np.flatnonzero(~moved)  # feature k of a2 shows point truth_of[k]
    got = {int(p): int(truth_of[f]) for p, f in zip(p_a2, f_a2, strict=True)}
    of_point = {int(p): int(f) for p, f in zip(p_a, f_a, strict=True)}
    agree = [of_point.get(p) == t for p, t in got.items()]
    assert len(got) >= 0.6 * (~moved).sum() and np.mean(agree) >= 0.98
    assert not any(moved[of_point[p]] for p in got if p in of_point)  # moved points are not extended


def test_verify_tracks_rejects_wrong_and_too_wide_matches() -> None:
    rng = np.random.default_rng(6)
    pts, desc, wa, _, wb = _three_views(rng, 200)
    a, b = _view(wa, pts, desc, rng), _view(wb, pts, desc, rng)
    side = _view(cam.look_at((-30.0, 2.0, 3.0), (0.0, 0.0, 3.0)), pts, desc, rng)
    perm = rng.permutation(100)
    obs = [[(0, i), (1, i)] for i in range(100, 200)]  # right
    obs += [[(0, i), (1, int(perm[i]))] for i in range(100) if perm[i] != i]  # wrong partner
    wide = [[(1, i), (2, i)] for i in range(100, 200)]  # right, but ~100 deg apart: not checkable
    views = [a, b, side]
    depths = [v.scene_depth_m for v in views]
    ok = verify_tracks(views, obs + wide, viewpoint_clusters(views, depths), DensifyParams())
    n_right = 100
    assert ok[:n_right].mean() >= 0.9
    assert ok[n_right : len(obs)].mean() <= 0.05
    assert not ok[len(obs) :].any()


@pytest.mark.slow
def test_densify_on_the_synthetic_site_with_true_cameras(small_site) -> None:
    """True cameras and real SIFT on the site's photos: the densified points agree with the true depth maps."""
    cams = json.loads((small_site / "truth" / "cameras.json").read_text())
    rels = sorted(cams)
    views = []
    for rel in rels:
        c = cams[rel]
        K = np.asarray(c["K"])
        intr = Intrinsics(
            width_px=c["width"], height_px=c["height"], f_px=K[0, 0], cx_px=K[0, 2], cy_px=K[1, 2], k1=c["k1"]
        )
        intr = Intrinsics(**{**{f: getattr(intr, f) for f in intr.__struct_fields__}, "k2": c["k2"]})
        f = extract_features(cv2.imread(str(small_site / "photos" / rel), cv2.IMREAD_GRAYSCALE), 4000)
        views.append(
            View(
                intr,
                np.asarray(c["world_from_camera"]),
                f.keypoints_px.astype(np.float64),
                f.descriptors,
                f.scales,
                int(c["capture_time_utc_ns"]),
                30.0 if c["camera_id"] else 10.0,
            )
        )
    dense = densify(views)
    assert dense.num_points >= 150
    good = total = 0
    for vi, rel in enumerate(rels):
        p, f = dense.observations_of(vi)
        if len(p) == 0:
            continue
        z_true = np.load(small_site / "truth" / "depth" / (rel[: -len(".jpg")] + ".npz"))["depth_m"]
        _, z = cam.project_points(
            views[vi].intrinsics, cam.invert_rigid(views[vi].world_from_camera), dense.points_m[p]
        )
        u, v = np.round(views[vi].keypoints_px[f]).astype(int).T
        zt = z_true[v, u]
        good += int(np.count_nonzero(np.abs(z - zt) < np.maximum(0.3, 0.02 * zt)))
        total += len(p)
    assert good / total >= 0.85
