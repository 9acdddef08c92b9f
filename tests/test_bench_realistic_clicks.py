"""The realistic-click variant for the real sets (bench/_datasets.py): a person clicks strong image corners that
ground truth triangulates, with 1.5 px noise and ~1 in 20 gross mis-clicks; the model point is ground truth."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest
from conftest import ROOT, require_data

from constructaide.anchorsolve import solve_anchor
from constructaide.synth.clicker import NOISE_PX

sys.path.insert(0, str(ROOT))

from bench import _datasets as ds  # noqa: E402


@pytest.fixture(scope="module")
def temple() -> list:
    require_data("middlebury", "templeSparseRing")
    return ds.load_temple()


def test_realistic_clicks_are_strong_corners_within_the_noise(temple) -> None:
    for i in (0, 5, 11):
        targets = ds.realistic_click_targets(temple, i)
        assert len(targets[0]) >= 12
        c = ds.realistic_click_set(temple, i, seed=0, targets=targets)
        px, world, mis = ds.simulate_realistic_clicks(temple, i, seed=0, targets=targets)
        assert np.array_equal(px, c.pixels_px) and np.array_equal(mis, c.mis_clicked)
        assert len(px) == 12 and world.shape == (12, 3)
        proj, z = temple[i].project(world)
        assert np.all(z > 0) and np.allclose(proj, c.target_px)
        good = np.setdiff1d(np.arange(12), mis)
        assert np.all(np.linalg.norm(px[good] - proj[good], axis=1) < 5 * NOISE_PX)
        # Each clicked point is a strong corner: a Shi-Tomasi response >= 5 % of the image's strongest next to it.
        gray = cv2.imread(str(temple[i].path), cv2.IMREAD_GRAYSCALE)
        resp = cv2.cornerMinEigenVal(gray, 5)
        uv = np.round(proj).astype(int)
        local = [resp[v - 1 : v + 2, u - 1 : u + 2].max() for u, v in uv]
        assert np.all(np.asarray(local) >= 0.05 * resp.max())
        again = ds.simulate_realistic_clicks(temple, i, seed=0, targets=targets)
        other = ds.simulate_realistic_clicks(temple, i, seed=1, targets=targets)
        assert np.array_equal(again[0], px) and not np.allclose(other[0], px)


def test_anchor_solve_flags_a_mis_click_on_the_temple(temple) -> None:
    focal = float(np.mean([(c.K[0, 0] + c.K[1, 1]) / 2 for c in temple]))
    c = ds.realistic_click_set(temple, 0, seed=2, miss_rate=0.0)
    px = c.pixels_px.copy()
    px[4] += [18.0, -18.0]  # a slip of 25 px
    sol = solve_anchor(px, c.points_in_world_m, temple[0].width_px, temple[0].height_px, focal_px=focal)
    assert sol.outlier_mask.tolist() == [k == 4 for k in range(len(px))]
