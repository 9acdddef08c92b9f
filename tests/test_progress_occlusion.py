"""Progress: which occlusion-mask pixels hide elements from a fixed camera's cues (``nodes.progress.occlusion``, the
engine's default ``dynamic_hides_unseen=False``, ``dynamic_spares_material_like=True``)."""

from __future__ import annotations

import numpy as np
import pytest
from test_progress_edge_discount import paint, scene  # noqa: F401  (fixture)
from test_progress_fusion_evidence import INTR, H, W

from nodes.progress.evidence import NUM_BINS, EvidenceParams, colour_bins, photo_evidence, to_lab
from nodes.progress.occlusion import fixed_camera_hiding, hiding_mask, material_like

BUILT = np.array([False, False, True])  # the slab (2) stands
CAND = np.array([False, True, False])  # the wall (1) may be appearing


def blob(rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool: a random box over the middle of the image (where the wall and the slab are)."""
    x0, y0 = int(rng.integers(W // 4, W // 3)), int(rng.integers(H // 5, H // 3))
    out = np.zeros((H, W), bool)
    out[y0 : y0 + H // 2, x0 : x0 + W // 2] = True
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_time_lapse_mask_hides_only_what_was_seen_appearing(scene, seed: int) -> None:  # noqa: ANN001, F811
    """A dynamic mask over the wall (a candidate) and the slab: the wall shows through it; the slab shows through
    while no photo has seen it appear (the schedule's belief) and is hidden once one has; the background stays
    hidden; a static mask hides every element."""
    rng = np.random.default_rng(seed)
    r, T = scene
    layers = r.render(INTR, T, BUILT, CAND)
    dynamic, static = blob(rng), np.zeros((H, W), bool)
    wall, slab, ground = layers.ids_all == 1, layers.ids_all == 2, layers.ids_all == 0
    assert (dynamic & wall).sum() > 200 and (dynamic & slab).sum() > 200 and (dynamic & ground).sum() > 200
    unseen = np.zeros(3, bool)
    hide = hiding_mask(dynamic, static, layers.ids_front, layers.ids_all, unseen)
    assert not hide[wall].any() and not hide[slab].any()
    assert hide[dynamic & ground].all()
    slab_seen = np.array([False, False, True])
    hide = hiding_mask(dynamic, static, layers.ids_front, layers.ids_all, slab_seen)
    assert hide[dynamic & slab].all() and not hide[wall].any()
    wall_seen = np.array([False, True, True])  # a candidate is read even when seen appearing (it is re-read)
    assert not hiding_mask(dynamic, static, layers.ids_front, layers.ids_all, wall_seen)[wall].any()
    static = blob(rng)
    both = dynamic | static
    hide = hiding_mask(both, static, layers.ids_front, layers.ids_all, unseen)
    assert hide[static].all()
    assert not hide[dynamic & ~static & (wall | slab)].any()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_candidate_under_a_time_lapse_mask_gets_its_change_cue(scene, seed: int) -> None:  # noqa: ANN001, F811
    """The wall appeared since the camera's plate, wholly under the dynamic mask (with a margin): with the combined
    mask it is ``occluded`` and gets no change evidence; with the mask the fixed camera's cues use it is ``seen``
    and its change reads that it appeared."""
    rng = np.random.default_rng(seed)
    r, T = scene
    layers = r.render(INTR, T, BUILT, CAND)
    before, after = paint(scene, rng, None), paint(scene, rng, (160, 70, 50))
    ref = (to_lab(before), np.ones((H, W), bool), np.zeros((H, W), np.int64))
    dynamic = np.zeros((H, W), bool)
    ys, xs = np.nonzero(layers.ids_all == 1)
    dynamic[max(ys.min() - 6, 0) : ys.max() + 7, max(xs.min() - 6, 0) : xs.max() + 7] = True
    mats = ["", "brick", "concrete"]

    def cue(hide: np.ndarray):  # noqa: ANN202
        return {c.index: c for c in photo_evidence(to_lab(after), hide, layers, mats, EvidenceParams(), ref)}[1]

    masked = cue(dynamic)
    assert masked.status == "occluded" and masked.llr_change == 0.0
    read = cue(hiding_mask(dynamic, np.zeros((H, W), bool), layers.ids_front, layers.ids_all, np.zeros(3, bool)))
    assert read.status == "seen" and read.llr_change > 2.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_only_what_looks_like_the_elements_material_is_read_through(scene, seed: int) -> None:  # noqa: ANN001, F811
    """The wall (brick, a candidate) under a dynamic mask, its left half covered by a white truck: with the brick look
    learnt, the brick half is read through the mask and the truck half stays hidden; without a learnt look of brick
    nothing is read through."""
    rng = np.random.default_rng(seed)
    r, T = scene
    layers = r.render(INTR, T, BUILT, CAND)
    img = paint(scene, rng, (160, 70, 50))
    wall = layers.ids_all == 1
    ys, xs = np.nonzero(wall)
    truck = wall & (np.arange(W)[None, :] < (xs.min() + xs.max()) // 2)
    img[truck] = np.clip(rng.normal(235, 6, (int(truck.sum()), 3)), 0, 255).astype(np.uint8)
    lab = to_lab(img)
    brick = to_lab(paint(scene, np.random.default_rng(seed + 10), (160, 70, 50)))
    looks = {"brick": np.bincount(colour_bins(brick)[wall], minlength=NUM_BINS).astype(np.float64)}
    dynamic = np.zeros((H, W), bool)
    dynamic[max(ys.min() - 6, 0) : ys.max() + 7, max(xs.min() - 6, 0) : xs.max() + 7] = True
    mats = ["", "brick", "concrete"]
    like = material_like(colour_bins(lab), layers.ids_all, mats, looks, ~dynamic & (layers.ids_all == 0))
    assert like[wall & ~truck].mean() > 0.8 and like[truck].mean() < 0.05
    none = np.zeros((H, W), bool)
    hide = fixed_camera_hiding(colour_bins(lab), dynamic, none, layers, np.zeros(3, bool), mats, looks)
    assert hide[truck].mean() > 0.95 and hide[wall & ~truck].mean() < 0.2
    assert fixed_camera_hiding(colour_bins(lab), dynamic, none, layers, np.zeros(3, bool), mats, {})[wall].all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_elements_below_the_terrain_are_hidden_not_read_absent(seed: int) -> None:
    """A footing below the terrain shows soil whether it stands or not: its pixels are hidden (status occluded, no
    evidence), while an element above the ground (and the footing's part above it) is read; seeded camera heights.
    Without the terrain its soil-coloured pixels would be read as the footing's look."""
    from test_progress_fusion_evidence import box, textured

    from constructaide.camera import look_at
    from nodes.progress.modelview import LayerRenderer, below_terrain, surface_height_m

    rng = np.random.default_rng(seed)
    r = LayerRenderer()
    r.set_model(
        ["footing", "column", "wall"],
        {
            "footing": box((-2.0, -1.0, -1.2), (0.0, 1.0, -0.3)),  # wholly below the ground (z = 0)
            "column": box((0.5, -0.3, 0.0), (1.1, 0.3, 2.5)),
            "wall": box((1.6, -0.2, -1.0), (2.6, 0.2, 1.5)),  # a basement wall rising above the ground
        },
    )
    T = look_at((float(rng.uniform(-1, 1)), -9.0, float(rng.uniform(1.5, 3.5))), (0.0, 0.0, -0.3))
    layers = r.render(INTR, T, np.array([False, True, True, True]), np.zeros(4, bool))
    z = surface_height_m(layers, INTR, T)
    footing, column, wall = (layers.ids_built == i for i in (1, 2, 3))
    assert footing.sum() > 100 and column.sum() > 100 and wall.sum() > 100
    assert np.nanmax(z[footing]) < -0.25 and np.nanmin(z[footing]) > -1.25 and np.nanmin(z[column]) > -0.05
    hidden = below_terrain(layers, INTR, T, 0.0, 0.05)
    assert hidden[footing].all() and not hidden[column].any() and not hidden[layers.ids_built == 0].any()
    assert 0.1 < hidden[wall].mean() < 0.9  # only its part below the ground
    img = textured(rng, (H, W), (120, 95, 70))  # soil (and a grey column)
    img[column] = textured(rng, (H, W), (150, 150, 150))[column]
    mats = ["", "concrete", "concrete", "concrete"]
    seen = {c.index: c for c in photo_evidence(to_lab(img), hidden, layers, mats, EvidenceParams())}
    assert seen[1].status == "occluded" and seen[1].llr_edge == seen[1].llr_appearance == 0.0
    assert seen[2].status == "seen" and seen[3].status == "seen"
    unhidden = {c.index: c for c in photo_evidence(to_lab(img), np.zeros((H, W), bool), layers, mats, EvidenceParams())}
    assert unhidden[1].status == "seen"
