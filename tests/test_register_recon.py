"""The reconstruction's bookkeeping: images taken out of the map (retired key frames) leave it consistent."""

from __future__ import annotations

import numpy as np

from nodes.register.features import Features
from nodes.register.recon import PairGeometry, Reconstruction, add_image, build_tracks, remove_images


def _features(n: int, rng: np.random.Generator) -> Features:
    return Features(
        keypoints_px=rng.uniform(0, 100, (n, 2)).astype(np.float32),
        descriptors=rng.normal(size=(n, 128)).astype(np.float32),
        scales=np.ones(n, np.float32),
        width_px=100,
        height_px=100,
    )


def _recon(seed: int) -> Reconstruction:
    """Four images of 10 features; feature k of every image is one scene point (pairs 0-1, 1-2, 2-3, 0-3)."""
    rng = np.random.default_rng(seed)
    r = Reconstruction()
    for i in range(4):
        add_image(r, f"im{i}", _features(10, rng), camera_id="cam")
    same = np.stack([np.arange(10), np.arange(10)], axis=1)
    for i, j in ((0, 1), (1, 2), (2, 3)):
        r.pairs[(i, j)] = PairGeometry(same.copy(), np.eye(3), 10)
    r.pairs[(0, 3)] = PairGeometry(same[:3].copy(), np.eye(3), 3)  # features 0-2 also seen 0-3
    build_tracks(r)
    r.points = rng.normal(size=(len(r.track_obs), 3))
    r.point_from_model = np.arange(len(r.track_obs)) % 2 == 0
    r.images[3].centre_source = 1
    r.images[2].lens_source = 3
    return r


def _consistent(r: Reconstruction) -> None:
    assert len(r.feature_track) == len(r.images)
    for t, d in enumerate(r.track_obs):
        assert d, "no empty tracks"
        for i, f in d.items():
            assert 0 <= i < len(r.images) and r.feature_track[i][f] == t
    for i, ft in enumerate(r.feature_track):
        for f in np.nonzero(ft >= 0)[0]:
            assert i in r.track_obs[ft[f]]
    for i, j in r.pairs:
        assert 0 <= i < j < len(r.images)
    assert len(r.points) == len(r.track_obs) == len(r.point_from_model)


def test_remove_images_renumbers_and_keeps_the_rest_consistent() -> None:
    for seed in (0, 1, 2):
        r = _recon(seed)
        before = {
            frozenset((r.images[i].name, f) for i, f in d.items()): r.points[t].copy()
            for t, d in enumerate(r.track_obs)
        }
        model = {k for k, t in zip(before, range(len(r.track_obs)), strict=True) if r.point_from_model[t]}
        new = remove_images(r, {1})
        assert new.tolist() == [0, -1, 1, 2]
        assert [im.name for im in r.images] == ["im0", "im2", "im3"] and r.index("im3") == 2
        assert sorted(r.pairs) == [(0, 2), (1, 2)]  # 1-2 and 2-3 renumbered, 0-1 gone with im1, 0-3 kept as 0-2
        _consistent(r)
        assert r.images[2].centre_source is None and r.images[1].lens_source == 2
        # every track keeps its observations in the remaining images and its point when two views remain
        for t, d in enumerate(r.track_obs):
            names = frozenset((r.images[i].name, f) for i, f in d.items())
            old = next(k for k in before if names <= k)
            if len(d) >= 2 or old in model:
                np.testing.assert_array_equal(r.points[t], before[old])
            else:
                assert np.isnan(r.points[t]).all()
        assert len(r.track_obs) == 10  # features 0-9 each still seen somewhere


def test_remove_images_drops_tracks_left_without_observations() -> None:
    r = _recon(3)
    remove_images(r, {0, 1, 2})
    _consistent(r)
    assert [im.name for im in r.images] == ["im3"] and r.pairs == {}
    assert len(r.track_obs) == 10 and all(len(d) == 1 for d in r.track_obs)
    assert np.isnan(r.points[~r.point_from_model]).all() and np.isfinite(r.points[r.point_from_model]).all()
    remove_images(r, {0})
    assert r.images == [] and r.track_obs == [] and len(r.points) == 0
