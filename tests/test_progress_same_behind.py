"""Appearance cue: a candidate in front of a believed-built element of its own material (a concrete column before a
concrete wall) is not read as standing from the colours that element shows where the candidate is absent
(``EvidenceParams.appearance_same_behind``, on by default)."""

from __future__ import annotations

import numpy as np
import pytest

from constructaide.camera import look_at
from nodes.progress.evidence import EvidenceParams, photo_evidence, to_lab
from nodes.progress.modelview import LayerRenderer
from tests.test_progress_fusion_evidence import INTR, H, W, box


@pytest.fixture(scope="module")
def scene() -> tuple[LayerRenderer, np.ndarray]:
    """A concrete column (1) whose lower half stands before a concrete wall (2) and whose upper half shows the sky
    behind it; a brick block (3) aside; seen from 8 m."""
    r = LayerRenderer()
    r.set_model(
        ["col", "wall", "brick"],
        {
            "col": box((-0.3, -0.3, 0.0), (0.3, 0.3, 3.0)),
            "wall": box((-2.0, 1.0, 0.0), (2.0, 1.3, 1.2)),
            "brick": box((2.5, -0.5, 0.0), (3.5, 0.5, 1.5)),
        },
    )
    return r, look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.2))


def textured(rng: np.random.Generator, rgb: tuple[int, int, int], amp: float) -> np.ndarray:
    return np.clip(np.asarray(rgb, np.float64) + rng.normal(0, amp, (H, W, 1)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_candidate_before_its_own_material_reads_only_where_something_else_shows(scene, seed: int) -> None:  # noqa: ANN001
    r, T = scene
    rng = np.random.default_rng(seed)
    built = np.array([False, False, True, True])  # the wall and the brick block stand: concrete's look is known
    cand = np.array([False, True, False, False])
    layers = r.render(INTR, T, built, cand)
    ids = layers.ids_all.astype(np.int64)
    col = ids == 1
    before_wall = col & (layers.ids_built == 2)
    assert before_wall.sum() > 150 and (col & (layers.ids_built == 0)).sum() > 150, "the scene is as described"
    sky, concrete = textured(rng, (150, 185, 235), 6.0), textured(rng, (150, 150, 145), 12.0)
    brick = textured(rng, (160, 70, 50), 14.0)
    absent = sky.copy()
    absent[layers.ids_built == 2] = concrete[layers.ids_built == 2]
    absent[ids == 3] = brick[ids == 3]
    present = absent.copy()
    present[col] = concrete[col]
    mats = ["", "concrete", "concrete", "brick"]
    confirmed = np.array([0.0, 0.0, 1.0, 1.0])
    occ = np.zeros((H, W), bool)

    def llr(img: np.ndarray, same: bool, hide: np.ndarray = occ) -> float:
        p = EvidenceParams(
            appearance_min_reference_px=30,
            appearance_full_pixels=0,
            appearance_max_llr=50.0,
            appearance_same_behind=same,
        )
        cues = photo_evidence(to_lab(img), hide, layers, mats, p, confirmed=confirmed)
        return next(c for c in cues if c.index == 1).llr_appearance

    # absent, with only its part before the wall in view: that part shows concrete either way
    only_wall = col & ~before_wall
    assert llr(absent, False, only_wall) > 0.5, "without the rule the wall's concrete reads as the column"
    assert llr(absent, True, only_wall) == pytest.approx(0.0, abs=1e-9)
    # the part before the sky still tells: standing reads positive, absent negative
    assert llr(present, True) > 0.3
    assert llr(absent, True) < 0.0 < llr(present, True)
    assert llr(present, True) < llr(present, False), "its part before the wall no longer adds to it"


def test_the_rule_is_on_by_default() -> None:
    assert EvidenceParams().appearance_same_behind
