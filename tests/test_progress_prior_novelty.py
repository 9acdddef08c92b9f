"""Progress: the schedule prior over a task's window, appearance before a material's look is known, and the state
an element too small for a photo's own cues reports."""

from __future__ import annotations

import numpy as np
import pytest
from test_progress_fusion_evidence import box as _box

from constructaide.camera import look_at
from constructaide.schedule4d import ElementWindow
from nodes.progress.engine import ProgressEngine
from nodes.progress.evidence import EvidenceParams, photo_evidence, to_lab
from nodes.progress.fusion import NS_PER_DAY, ElementTrack, FusionParams, Observation, estimate, fit_slip_days
from nodes.progress.modelview import LayerRenderer
from schemas.messages import Intrinsics

D = NS_PER_DAY
SPAN = (0, 20 * D)
W, H = 160, 120
INTR = Intrinsics(width_px=W, height_px=H, f_px=140.0, cx_px=79.5, cy_px=59.5)


def test_schedule_prior_spreads_over_the_planned_window() -> None:
    """Without evidence an element of a 4-day task is as likely finished at any time of the window (blurred by the
    slip): little at the planned start, about half in the middle, most by the planned finish plus a few slips."""
    params = FusionParams()
    tr = ElementTrack("e", ElementWindow(build_start_ns=4 * D, build_finish_ns=8 * D), SPAN)
    tr.add(Observation("p", 15 * D))  # no evidence, just a time on the grid
    post = tr.posterior(params)
    at = [post.present_at(int(t)) for t in np.linspace(0, 20 * D, 81)]
    assert np.all(np.diff(at) >= -1e-9)
    assert post.present_at(4 * D) < 0.3
    assert 0.4 < post.present_at(6 * D) < 0.6
    assert post.present_at(8 * D + int(3 * params.schedule_width_days * D)) > 0.75
    # a zero-length window is the plain logistic slip around the planned date
    point = ElementTrack("e", ElementWindow(build_start_ns=8 * D, build_finish_ns=8 * D), SPAN)
    point.add(Observation("p", 15 * D))
    assert point.posterior(params).present_at(8 * D) == pytest.approx(0.5, abs=0.05)


def test_an_element_standing_before_the_first_photo_inside_its_window() -> None:
    """The first photo comes after the task's window: daily photos never see the element change and look weakly
    like it stands. It stood before the first photo (inside its window), not after the last."""
    params = FusionParams()
    obs = [Observation(f"s{d}", d * D, llr_state=0.3) for d in range(9, 15)]
    obs += [Observation(f"c{d}", d * D, llr_change=-4.0, reference_ns=(d - 1) * D) for d in range(10, 15)]
    tr = ElementTrack("e", ElementWindow(build_start_ns=4 * D, build_finish_ns=8 * D), SPAN)
    for o in obs:
        tr.add(o)
    post = tr.posterior(params)
    assert post.present_at(9 * D) > 0.8
    e = estimate(tr, post, 14 * D, params)
    assert e.state == "built" and e.finish_ns is not None and e.finish_ns <= 9 * D
    assert e.deviation == "on_time"


@pytest.fixture(scope="module")
def scene() -> tuple[LayerRenderer, np.ndarray]:
    """A column (1) and a slab (2) side by side, seen from 8 m."""
    r = LayerRenderer()
    r.set_model(
        ["col", "slab"],
        {"col": _box((-2.0, -0.3, 0.0), (-1.3, 0.4, 2.5)), "slab": _box((0.0, -1.0, 0.0), (2.5, 1.0, 0.5))},
    )
    return r, look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_appearance_before_any_look_of_the_material_is_known(scene, seed: int) -> None:  # noqa: ANN001
    """First frame of a site: nothing of concrete stands yet that could teach its look. A concrete slab that stands
    looks unlike the grass around it (positive); where it is absent the grass shows through (negative)."""
    r, T = scene
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.zeros(3, bool), np.array([False, True, True]))
    ids = layers.ids_all
    grass = np.clip(np.array([90.0, 140.0, 80.0]) + rng.normal(0, 20, (H, W, 1)), 0, 255).astype(np.uint8)
    concrete = np.clip(np.array([150.0, 150.0, 145.0]) + rng.normal(0, 10, (H, W, 1)), 0, 255).astype(np.uint8)
    standing = grass.copy()
    standing[ids == 2] = concrete[ids == 2]
    mats = ["", "steel", "concrete"]
    free = np.zeros((H, W), bool)
    raw = EvidenceParams(appearance_negative_scale=1.0, appearance_full_pixels=0)
    yes = {c.index: c for c in photo_evidence(to_lab(standing), free, layers, mats, raw)}
    no = {c.index: c for c in photo_evidence(to_lab(grass), free, layers, mats, raw)}
    assert yes[2].llr_appearance > 0.3, "the slab stands out from the grass"
    assert no[2].llr_appearance < -0.3 and no[1].llr_appearance < -0.3, "grass where they are absent"
    weak = EvidenceParams(appearance_negative_scale=1.0, appearance_full_pixels=0, appearance_novelty_weight=0.1)
    yes_weak = {c.index: c for c in photo_evidence(to_lab(standing), free, layers, mats, weak)}
    assert 0.0 < yes_weak[2].llr_appearance < yes[2].llr_appearance, "the weight scales the novelty evidence"
    off = EvidenceParams(appearance_novelty_weight=0.0)
    assert all(c.llr_appearance == 0.0 for c in photo_evidence(to_lab(standing), free, layers, mats, off))


def test_an_element_too_small_for_the_photo_reports_the_fused_state() -> None:
    """An element in view with too few pixels for this photo's own cues (status ``unknown``) reports the fused
    estimate at the capture time; one the mask hides stays ``occluded``; one nothing was ever seen of, unknown."""
    eng = ProgressEngine()
    window = ElementWindow(build_start_ns=4 * D, build_finish_ns=5 * D)
    seen = ElementTrack("a", window, SPAN)
    for d in range(6, 12):
        seen.add(Observation(f"p{d}", d * D, llr_state=1.0, llr_change=-4.0, reference_ns=(d - 1) * D))
    eng.tracks = {"a": seen, "b": ElementTrack("b", window, SPAN)}
    state, conf = eng.photo_state("a", "unknown", 10 * D, 0.1)
    assert state == "built" and conf >= eng.params.fusion.built_probability
    assert eng.photo_state("a", "occluded", 10 * D, 0.9) == ("occluded", 0.9)
    assert eng.photo_state("b", "unknown", 10 * D, 0.1) == ("unknown", 0.0)


def _seen_appearing(slip_days: float, n: int, seed: int) -> list[ElementTrack]:
    """``n`` elements, one-day tasks over a month, each built at a time drawn around its window (logistic slip of
    ``slip_days``), seen appearing between two daily photos."""
    rng = np.random.default_rng(seed)
    tracks = []
    for k in range(n):
        start = int(rng.uniform(2, 28) * D)
        window = ElementWindow(build_start_ns=start, build_finish_ns=start + D)
        u = rng.uniform(1e-6, 1 - 1e-6)
        t_true = start + rng.uniform(0, D) + slip_days * D * np.log(u / (1 - u))
        day = int(np.ceil(t_true / D)) * D  # the first daily photo that shows it
        tr = ElementTrack(f"e{k}", window, (0, 30 * D))
        tr.add(Observation(f"p{k}", day, llr_change=5.0, reference_ns=day - D))
        tracks.append(tr)
    return tracks


@pytest.mark.parametrize("seed", [3, 4])
def test_the_slip_of_the_schedule_is_learnt_from_elements_seen_appearing(seed: int) -> None:
    """A site whose crews keep to the plan within hours gets a narrow prior, one that slips by days a wide one
    (near the true scale; daily photos censor the change times to a day); too few elements seen appearing: no fit."""
    params = FusionParams()
    tight = fit_slip_days(_seen_appearing(0.25, 80, seed), params)
    loose = fit_slip_days(_seen_appearing(2.0, 80, seed), params)
    assert tight is not None and loose is not None
    assert tight < 0.6 < 1.2 < loose < 3.0
    assert fit_slip_days(_seen_appearing(2.0, params.fit_min_elements - 1, seed), params) is None


def test_a_photo_shows_what_stands_behind_a_candidate_that_did_not_stand() -> None:
    """A candidate hid a believed-built wall when the photo was read; once every photo says the candidate did not
    stand then, the photo's rows include the wall (its fused state, status ``unknown``); not while the candidate
    most probably stood, nor with too few unoccluded pixels."""
    from nodes.progress.batch import observation_rows
    from nodes.progress.engine import PhotoRecord

    window = ElementWindow(build_start_ns=4 * D, build_finish_ns=5 * D)

    def engine(candidate_llr: float, visible_px: int) -> ProgressEngine:
        eng = ProgressEngine()
        eng.global_ids = ["cand", "wall"]
        eng.index_of = {"cand": 1, "wall": 2}
        cand, wall = ElementTrack("cand", window, SPAN), ElementTrack("wall", window, SPAN)
        for d in range(6, 12):
            cand.add(Observation(f"p{d}", d * D, llr_state=candidate_llr))
            wall.add(Observation(f"p{d}", d * D, llr_state=2.0))
        eng.tracks = {"cand": cand, "wall": wall}
        eng.records["p10"] = PhotoRecord(
            "p10", "cam", 10 * D, "p10.jpg", {1: ("seen", 900, 0.0)}, 1.0, {(1, 2): (100, visible_px)}
        )
        return eng

    eng = engine(-2.0, 80)
    assert eng.photo_cues(eng.records["p10"])[2] == ("unknown", 80, pytest.approx(0.2))
    rows = {r["global_id"]: r["state"] for r in observation_rows(eng)}
    assert rows == {"cand": "not_built", "wall": "built"}
    stood = engine(2.0, 80)
    assert 2 not in stood.photo_cues(stood.records["p10"])
    small = engine(-2.0, EvidenceParams().min_pixels - 1)
    assert 2 not in small.photo_cues(small.records["p10"])


def test_inside_a_wide_evidence_bracket_the_finish_follows_the_prior() -> None:
    """Absent on day 3, standing on day 7, nothing seen in between: the photos only bracket the change. With a
    tight slip the finish is the posterior median near the planned window (inside the bracket), not the bracket's
    middle; the middle is kept as an option."""
    obs = [Observation("a", 3 * D, llr_state=-3.0), Observation("b", 7 * D, llr_state=3.0)]
    window = ElementWindow(build_start_ns=int(3.5 * D), build_finish_ns=4 * D)
    tr = ElementTrack("e", window, SPAN)
    for o in obs:
        tr.add(o)
    tight = FusionParams(schedule_width_days=0.25)
    e = estimate(tr, tr.posterior(tight), 8 * D, tight)
    assert e.state == "built" and e.finish_ns is not None
    assert 3 * D < e.finish_ns <= 7 * D and abs(e.finish_ns - 3.75 * D) < 0.5 * D
    middle = FusionParams(schedule_width_days=0.25, finish_at_median=False)
    m = estimate(tr, tr.posterior(middle), 8 * D, middle)
    assert m.finish_ns == 5 * D
