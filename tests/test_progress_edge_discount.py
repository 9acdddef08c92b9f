"""Progress: the outline (edge) cue on seeded scenes, and a fixed camera's unchanged look counted once."""

from __future__ import annotations

import numpy as np
import pytest
from test_progress_fusion_evidence import INTR, H, W, box

from constructaide.camera import look_at
from constructaide.schedule4d import ElementWindow
from nodes.progress.engine import ProgressEngine
from nodes.progress.evidence import ElementCue, EvidenceParams, photo_evidence, to_lab
from nodes.progress.fusion import NS_PER_DAY, ElementTrack
from nodes.progress.modelview import LayerRenderer

D = NS_PER_DAY


@pytest.fixture(scope="module")
def scene() -> tuple[LayerRenderer, np.ndarray]:
    """A wall (1) in front of a built slab (2) that reaches beyond it on the right, seen from 8 m."""
    r = LayerRenderer()
    r.set_model(
        ["wall", "slab"],
        {"wall": box((-1.5, -0.1, 0.0), (0.5, 0.1, 2.0)), "slab": box((-0.5, 1.0, 0.0), (2.5, 1.4, 1.2))},
    )
    return r, look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.0))


def textured(rng: np.random.Generator, rgb: tuple[int, int, int], amp: float) -> np.ndarray:
    """(H, W, 3) uint8: a colour with smooth blotches (a surface's texture) and sensor noise."""
    blotch = rng.normal(0, amp, (H // 8 + 1, W // 8 + 1, 1)).repeat(8, 0).repeat(8, 1)[:H, :W]
    noise = rng.normal(0, 3.0, (H, W, 1))
    return np.clip(np.asarray(rgb, np.float64) + blotch + noise, 0, 255).astype(np.uint8)


def edge_cues(scene, img: np.ndarray, occluded: np.ndarray | None = None, **kw: float) -> dict[int, ElementCue]:  # noqa: ANN001
    r, T = scene
    layers = r.render(INTR, T, np.array([False, False, True]), np.array([False, True, False]))
    occ = np.zeros((H, W), bool) if occluded is None else occluded
    params = EvidenceParams(appearance=False, **kw)  # type: ignore[arg-type]
    return {c.index: c for c in photo_evidence(to_lab(img), occ, layers, ["", "brick", "concrete"], params)}


def paint(scene, rng: np.random.Generator, wall_rgb: tuple[int, int, int] | None) -> np.ndarray:  # noqa: ANN001
    """Grass, the built slab, and (unless None) the wall in front of both."""
    r, T = scene
    layers = r.render(INTR, T, np.array([False, True, True]), np.zeros(3, bool))
    img = textured(rng, (90, 140, 80), 6.0)
    slab = layers.ids_built == 2
    img[slab] = textured(rng, (150, 150, 145), 4.0)[slab]
    if wall_rgb is not None:
        wall = layers.ids_built == 1
        img[wall] = textured(rng, wall_rgb, 6.0)[wall]
    return img


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_cue_reads_the_outline_of_a_standing_candidate(scene, seed: int) -> None:  # noqa: ANN001
    """A brick wall that stands shows its outline against the grass and the slab behind it: a positive edge LLR;
    absent, the grass and the slab continue across its outline: a negative one (kept at ``edge_negative_scale``);
    a wall that looks exactly like what surrounds it shows no edge either (why a negative counts less)."""
    rng = np.random.default_rng(seed)
    standing = edge_cues(scene, paint(scene, rng, (160, 70, 50)))[1]
    absent = edge_cues(scene, paint(scene, rng, None))[1]
    raw = edge_cues(scene, paint(scene, rng, None), edge_negative_scale=1.0)[1]
    assert standing.edge_samples >= EvidenceParams().edge_full_samples
    assert standing.edge_fraction > 0.8 and standing.llr_edge > 1.5
    assert absent.edge_fraction < 0.25 and absent.llr_edge < 0.0
    assert raw.llr_edge < -0.8
    assert absent.llr_edge == pytest.approx(raw.llr_edge * EvidenceParams().edge_negative_scale, abs=0.15)
    assert edge_cues(scene, paint(scene, rng, (160, 70, 50)))[2].llr_edge == 0.0, "built elements get no edge cue"


@pytest.mark.parametrize("seed", [0, 1])
def test_edge_cue_skips_the_masked_part_of_the_outline(scene, seed: int) -> None:  # noqa: ANN001
    """An occluder over the wall's left half: only the outline samples outside the mask count, with the same
    verdict; an occluder over all of it leaves no edge evidence."""
    rng = np.random.default_rng(seed)
    img = paint(scene, rng, (160, 70, 50))
    full = edge_cues(scene, img)[1]
    left = np.zeros((H, W), bool)
    left[:, : W // 2 - 4] = True
    half = edge_cues(scene, img, left)[1]
    assert 0 < half.edge_samples < full.edge_samples
    assert half.edge_fraction > 0.8 and half.llr_edge > 0.5
    every = np.ones((H, W), bool)
    assert edge_cues(scene, img, every)[1].llr_edge == 0.0


def _engine(discount: bool, floor: float = 0.0) -> ProgressEngine:
    from nodes.progress.engine import EngineParams

    eng = ProgressEngine(EngineParams(unchanged_discount=discount, unchanged_floor=floor))
    eng.global_ids, eng.index_of = ["a"], {"a": 1}
    eng.tracks = {"a": ElementTrack("a", ElementWindow(build_start_ns=15 * D, build_finish_ns=16 * D), (0, 30 * D))}
    return eng


@pytest.mark.parametrize("changed", [0.0, 0.05])
def test_a_fixed_cameras_unchanged_look_counts_once(changed: float) -> None:
    """A fixed camera shows, every day, pixels that look like an element planned for day 15 (a background of its
    colour and lines) and never change: the first frame's look counts, the repeats do not, so the element is not
    called built from the repetition (without the discount it would be); pixels that changed (an appearance) keep
    their look's full weight."""
    results = {}
    for discount in (True, False):
        eng = _engine(discount)
        for d in range(1, 11):
            ref = 0 if d == 1 else (d - 1) * D
            cue = ElementCue(1, 400, 400, 0.0, changed_fraction=changed if ref else float("nan"), reference_ns=ref)
            cue.llr_appearance, cue.llr_edge, cue.llr_change = 1.0, 1.0, (-3.0 if ref else 0.0)
            eng._observe(f"p{d}", d * D, [cue])
        results[discount] = eng.estimate("a", 10 * D)
        obs = sorted(eng.tracks["a"].observations.values(), key=lambda o: o.time_ns)
        assert obs[0].llr_state == pytest.approx(2.0)
        assert all(o.llr_state == pytest.approx(0.0 if discount else 2.0) for o in obs[1:])
    assert results[True].state != "built"
    assert results[False].state == "built"
    eng = _engine(True)
    cue = ElementCue(1, 400, 400, 0.0, changed_fraction=0.9, reference_ns=D)
    cue.llr_appearance, cue.llr_edge, cue.llr_change = 1.0, 1.0, 4.0
    eng._observe("p2", 2 * D, [cue])
    assert eng.tracks["a"].observations["p2"].llr_state == pytest.approx(2.0)
    # with a floor (the shipped 0.25: another day's light is partly a new look) an unchanged repeat keeps that share
    eng = _engine(True, floor=0.25)
    cue = ElementCue(1, 400, 400, 0.0, changed_fraction=changed, reference_ns=D)
    cue.llr_appearance, cue.llr_edge, cue.llr_change = 1.0, 1.0, -3.0
    eng._observe("p2", 2 * D, [cue])
    assert eng.tracks["a"].observations["p2"].llr_state == pytest.approx(0.5)
