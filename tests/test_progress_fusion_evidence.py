"""Progress: fusion over time (monotone, change intervals, deviations) and each evidence cue on seeded scenes."""

from __future__ import annotations

import numpy as np
import pytest

from constructaide.camera import look_at
from constructaide.schedule4d import ElementWindow
from nodes.progress.evidence import EvidenceParams, PhotoCache, photo_evidence, to_lab
from nodes.progress.fusion import NS_PER_DAY, ElementTrack, FusionParams, Observation, estimate
from nodes.progress.modelview import LayerRenderer
from schemas.messages import Intrinsics

D = NS_PER_DAY
SPAN = (0, 20 * D)


def track(window: ElementWindow | None, obs: list[Observation]) -> ElementTrack:
    tr = ElementTrack("e", window, SPAN)
    for o in obs:
        tr.add(o)
    return tr


def daily(change_day: int | None, days: range, strength: float = 4.0) -> list[Observation]:
    """Fixed-camera transition evidence: strong change on the day the element appears, none on the others."""
    return [
        Observation(f"p{d}", d * D, llr_change=strength if d == change_day else -strength, reference_ns=(d - 1) * D)
        for d in days
    ]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fusion_is_monotone_for_construction_and_demolition(seed: int) -> None:
    rng = np.random.default_rng(seed)
    obs = [
        Observation(
            f"p{k}",
            int(t),
            llr_state=float(rng.normal(0, 2)),
            llr_change=float(rng.normal(0, 2)),
            reference_ns=int(t) - D,
        )
        for k, t in enumerate(np.sort(rng.uniform(2 * D, 18 * D, 12)))
    ]
    times = np.linspace(0, 20 * D, 60).astype(np.int64)
    build = track(ElementWindow(build_start_ns=8 * D, build_finish_ns=9 * D), obs).posterior(FusionParams())
    p = [build.present_at(int(t)) for t in times]
    assert np.all(np.diff(p) >= -1e-9), "a constructed element never disappears"
    demolish = track(ElementWindow(remove_start_ns=8 * D, remove_finish_ns=9 * D), obs).posterior(FusionParams())
    q = [demolish.present_at(int(t)) for t in times]
    assert np.all(np.diff(q) <= 1e-9), "a demolished element never comes back"
    temp = track(
        ElementWindow(build_start_ns=3 * D, build_finish_ns=4 * D, remove_start_ns=14 * D, remove_finish_ns=15 * D), obs
    ).posterior(FusionParams())
    r = np.array([temp.present_at(int(t)) for t in times])
    assert r[0] < r[len(r) // 2] and r[-1] < r[len(r) // 2], "a temporary element stands in between"


def test_fusion_places_the_change_and_the_evidence_overrules_the_plan() -> None:
    params = FusionParams()
    # planned on day 5, seen appearing between day 11 and 12: behind, finish in (11, 12]
    tr = track(ElementWindow(build_start_ns=4 * D, build_finish_ns=5 * D), daily(12, range(1, 16)))
    e = estimate(tr, tr.posterior(params), 15 * D, params)
    assert e.state == "built" and e.last_absent_ns == 11 * D and e.first_present_ns == 12 * D
    assert e.deviation == "behind" and 11 * D < (e.finish_ns or 0) <= 12 * D
    assert e.finish_probability > 0.5
    assert tr.posterior(params).present_at(10 * D) < 0.3 < 0.7 < tr.posterior(params).present_at(13 * D)
    # planned on day 10, seen on day 3: ahead
    tr = track(ElementWindow(build_start_ns=9 * D, build_finish_ns=10 * D), daily(3, range(1, 16)))
    assert estimate(tr, tr.posterior(params), 15 * D, params).deviation == "ahead"
    # planned on day 5, never appears but looks absent every day: not built
    absent = [
        Observation(f"p{d}", d * D, llr_state=-1.0, llr_change=-4.0, reference_ns=(d - 1) * D) for d in range(1, 16)
    ]
    tr = track(ElementWindow(build_start_ns=4 * D, build_finish_ns=5 * D), absent)
    e = estimate(tr, tr.posterior(params), 15 * D, params)
    assert e.state == "not_built" and e.deviation == "not_built"
    # on the plan: on time
    tr = track(ElementWindow(build_start_ns=6 * D, build_finish_ns=8 * D), daily(7, range(1, 16)))
    assert estimate(tr, tr.posterior(params), 15 * D, params).deviation == "on_time"
    # no evidence at all: unknown
    tr = track(ElementWindow(build_start_ns=6 * D, build_finish_ns=8 * D), [])
    assert estimate(tr, tr.posterior(params), 15 * D, params).deviation == "unknown"


def test_a_deviation_needs_one_photo_that_shows_it() -> None:
    """Many weak looks add up to a confident late change, but ``behind`` / ``ahead`` are only said when one photo
    shows the element absent after its planned finish (or standing before its start) by itself: a pile of weak
    cues must not raise a false alarm on an element that is on time."""
    weak = [Observation(f"p{d}", d * D, llr_state=-0.6 if d < 12 else 0.6) for d in range(6, 16)]
    window = ElementWindow(build_start_ns=4 * D, build_finish_ns=5 * D)
    for proof, want in ((0.0, "behind"), (1.0, "on_time")):
        params = FusionParams(proof_llr=proof)
        tr = track(window, weak)
        e = estimate(tr, tr.posterior(params), 15 * D, params)
        assert e.state == "built" and e.deviation == want, proof
    # one clear look at the empty slot on day 9 is enough
    params = FusionParams(proof_llr=1.0)
    tr = track(window, [*weak, Observation("clear", 9 * D + 1, llr_state=-1.5)])
    assert estimate(tr, tr.posterior(params), 15 * D, params).deviation == "behind"
    # and for ahead: standing on day 2, planned from day 9
    early = [Observation(f"p{d}", d * D, llr_state=-0.6 if d < 2 else 0.6) for d in range(0, 12)]
    window = ElementWindow(build_start_ns=9 * D, build_finish_ns=10 * D)
    tr = track(window, early)
    assert estimate(tr, tr.posterior(params), 12 * D, params).deviation == "on_time"
    tr = track(window, [*early, Observation("clear", 3 * D, llr_state=2.0)])
    assert estimate(tr, tr.posterior(params), 12 * D, params).deviation == "ahead"


def test_fusion_is_incremental_and_order_free() -> None:
    """A track's posterior depends on its observations only, not on the order they arrived in."""
    obs = daily(9, range(1, 15))
    w = ElementWindow(build_start_ns=8 * D, build_finish_ns=9 * D)
    a = track(w, obs).posterior(FusionParams())
    b = track(w, obs[::-1]).posterior(FusionParams())
    assert [a.present_at(d * D) for d in range(15)] == pytest.approx([b.present_at(d * D) for d in range(15)])


# --------------------------------------------------------------------------------------------- cues

W, H = 160, 120
INTR = Intrinsics(width_px=W, height_px=H, f_px=140.0, cx_px=79.5, cy_px=59.5)


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(bounds=np.array([lo, hi]))
    return np.asarray(m.vertices), np.asarray(m.faces, np.int32)


@pytest.fixture(scope="module")
def scene() -> tuple[LayerRenderer, np.ndarray]:
    """A wall (1), a column (2) beside and behind it, a slab (3) to the other side, seen from 8 m."""
    r = LayerRenderer()
    r.set_model(
        ["wall", "col", "slab"],
        {
            "wall": box((-1.5, -0.1, 0.0), (0.5, 0.1, 2.0)),
            "col": box((-2.6, 0.5, 0.0), (-1.9, 1.2, 2.5)),
            "slab": box((1.0, -1.0, 0.0), (2.8, 1.0, 0.4)),
        },
    )
    T = look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.0))
    return r, T


def textured(
    rng: np.random.Generator, shape: tuple[int, int], rgb: tuple[int, int, int], amp: float = 25.0
) -> np.ndarray:
    noise = rng.normal(0, amp, (*shape, 1))
    return np.clip(np.asarray(rgb, np.float64) + noise, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_change_cue_attributes_appearance_to_the_right_element(scene, seed: int) -> None:  # noqa: ANN001
    r, T = scene
    rng = np.random.default_rng(seed)
    none = np.zeros(4, bool)
    cand = np.array([False, True, True, True])
    layers = r.render(INTR, T, none, cand)
    ids = layers.ids_all
    before = textured(rng, (H, W), (90, 140, 80))  # grass, nothing built
    after = before.copy()
    wall = ids == 1
    after[wall] = textured(rng, (H, W), (160, 70, 50))[wall]  # the brick wall appeared
    after = np.clip(after.astype(int) + rng.normal(0, 2, after.shape), 0, 255).astype(np.uint8)  # sensor noise
    lab0, lab1 = to_lab(before), to_lab(after)
    ref = (lab0, np.ones((H, W), bool), np.zeros((H, W), np.int64))
    cues = {
        c.index: c
        for c in photo_evidence(
            lab1, np.zeros((H, W), bool), layers, ["", "brick", "concrete", "concrete"], EvidenceParams(), reference=ref
        )
    }
    assert cues[1].llr_change > 3.0, "the wall appeared"
    assert cues[3].llr_change < -2.0, "the slab did not"
    assert cues[2].llr_change < -2.0, "nor did the column"
    # occlusion: a mask over the wall makes it occluded, not evidence
    occ = np.zeros((H, W), bool)
    occ[wall] = True
    masked = {
        c.index: c for c in photo_evidence(lab1, occ, layers, ["", "b", "c", "c"], EvidenceParams(), reference=ref)
    }
    assert masked[1].status == "occluded" and masked[1].llr_change == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cached_pass_with_settled_elements_reads_the_rest_alike(scene, seed: int) -> None:  # noqa: ANN001
    """A later reading pass of the same photo (one PhotoCache, earlier cues settled) gives the unsettled elements
    exactly the cues a fresh reading gives them, and leaves the settled ones without cues but with their status."""
    r, T = scene
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.zeros(4, bool), np.array([False, True, True, True]))
    before = textured(rng, (H, W), (90, 140, 80))
    after = before.copy()
    after[layers.ids_all == 1] = textured(rng, (H, W), (160, 70, 50))[layers.ids_all == 1]
    lab1 = to_lab(after)
    ref = (to_lab(before), np.ones((H, W), bool), np.zeros((H, W), np.int64))
    occ = np.zeros((H, W), bool)
    mats = ["", "brick", "concrete", "concrete"]
    fresh = {c.index: c for c in photo_evidence(lab1, occ, layers, mats, EvidenceParams(), reference=ref)}
    cache = PhotoCache(lab1)
    photo_evidence(lab1, occ, layers, mats, EvidenceParams(), reference=ref, cache=cache)  # the first pass
    again = {
        c.index: c
        for c in photo_evidence(lab1, occ, layers, mats, EvidenceParams(), reference=ref, cache=cache, settled=[1])
    }
    assert fresh[1].llr_change > 3.0 and abs(fresh[1].llr_edge) + abs(fresh[1].llr_appearance) > 0.0
    assert again[1].status == fresh[1].status == "seen"
    assert again[1].llr_change == again[1].llr_edge == again[1].llr_appearance == 0.0
    for i in (2, 3):
        assert again[i] == fresh[i]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_change_score_parts_shared_between_windows_and_read_at_some_pixels(seed: int) -> None:
    """The change score's parts at a second window, built from the first window's lightness and chroma, equal
    parts built from scratch; thresholding at some pixels gives the full map's values there. A grey site photo 1.8
    times brighter than its plate with one patch repainted: with the exposure gain (the median lightness ratio of
    the valid pixels) only the patch changed; without it, everything."""
    from nodes.progress.evidence import ChangeParts

    rng = np.random.default_rng(seed)
    plate = textured(rng, (H, W), (90, 90, 90), amp=15.0)
    photo = np.clip(plate.astype(np.float64) * 1.8, 0, 255).astype(np.uint8)
    photo[40:70, 50:90] = textured(rng, (30, 40), (160, 70, 50))
    lab, ref = to_lab(photo), to_lab(plate)
    cache = PhotoCache(lab)
    five, three = cache.change(ref, 5), cache.change(ref, 3)
    alone = ChangeParts(lab, ref, 3)
    assert np.array_equal(three.rest, alone.rest) and np.array_equal(three.ratio, alone.ratio)
    gain = five.gain(np.ones((H, W), bool))
    assert gain == pytest.approx(float(np.median(five.ratio))) and gain > 0.4
    full = three.changed(0.5, gain)
    where = rng.random((H, W)) < 0.3
    assert np.array_equal(three.changed(0.5, gain, where), full[where])
    outside = np.ones((H, W), bool)
    outside[30:80, 40:100] = False
    assert full[45:65, 55:85].mean() > 0.9 and full[outside].mean() < 0.05
    assert three.changed(0.5, 0.0)[outside].mean() > 0.9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_points_cue_on_surface_and_seen_through(scene, seed: int) -> None:  # noqa: ANN001
    r, T = scene
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.zeros(4, bool), np.array([False, True, True, True]))
    lab = to_lab(textured(rng, (H, W), (120, 120, 120)))
    ys, xs = np.nonzero(layers.ids_front == 1)
    pick = rng.choice(len(ys), 12, replace=False)
    px = np.column_stack([xs[pick], ys[pick]]).astype(np.float64)
    z_wall = layers.depth_front_m[ys[pick], xs[pick]].astype(np.float64)
    on = photo_evidence(
        lab,
        np.zeros((H, W), bool),
        layers,
        ["", "a", "b", "c"],
        EvidenceParams(),
        points=(px, z_wall + rng.normal(0, 0.03, 12), np.ones(12)),
    )
    through = photo_evidence(
        lab,
        np.zeros((H, W), bool),
        layers,
        ["", "a", "b", "c"],
        EvidenceParams(),
        points=(px, z_wall + 3.0 + rng.uniform(0, 2, 12), np.ones(12)),
    )
    assert next(c for c in on if c.index == 1).llr_points > 3.0
    assert next(c for c in through if c.index == 1).llr_points < -3.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_appearance_cue_against_its_material_and_what_is_behind(scene, seed: int) -> None:  # noqa: ANN001
    r, T = scene
    rng = np.random.default_rng(seed)
    built = np.array([False, False, False, True])  # the slab stands: its concrete look is known
    cand = np.array([False, True, True, False])
    layers = r.render(INTR, T, built, cand)
    ids = layers.ids_all
    base = textured(rng, (H, W), (90, 140, 80))  # grass
    concrete = textured(rng, (H, W), (150, 150, 145), 12.0)
    img = base.copy()
    img[ids == 3] = concrete[ids == 3]
    present_img = img.copy()
    present_img[ids == 2] = concrete[ids == 2]  # the concrete column stands (the wall in front is absent)
    mats = ["", "brick", "concrete", "concrete"]
    confirmed = np.array([0.0, 0.0, 0.0, 1.0])
    occ = ids == 1  # keep the wall out of it
    raw = EvidenceParams(appearance_min_reference_px=30, appearance_negative_scale=1.0, appearance_full_pixels=0)
    yes = {c.index: c for c in photo_evidence(to_lab(present_img), occ, layers, mats, raw, confirmed=confirmed)}
    no = {c.index: c for c in photo_evidence(to_lab(img), occ, layers, mats, raw, confirmed=confirmed)}
    assert yes[2].llr_appearance > 0.5
    assert no[2].llr_appearance < -0.5
    # shipped weighting: a negative look counts less than a positive one, and a small region less than a large one
    shipped = EvidenceParams(appearance_min_reference_px=30)
    yes_s = {c.index: c for c in photo_evidence(to_lab(present_img), occ, layers, mats, shipped, confirmed=confirmed)}
    no_s = {c.index: c for c in photo_evidence(to_lab(img), occ, layers, mats, shipped, confirmed=confirmed)}
    size = min(1.0, no[2].visible_px / shipped.appearance_full_pixels)
    assert yes_s[2].llr_appearance == pytest.approx(yes[2].llr_appearance * size, rel=1e-6)
    assert no_s[2].llr_appearance == pytest.approx(
        no[2].llr_appearance * shipped.appearance_negative_scale * size, rel=1e-6
    )


def test_plate_pixel_map_on_a_grid_matches_the_exact_map() -> None:
    """The reference plate's warp is computed every 8 px and interpolated: within 0.05 px of the exact map for a
    distorted camera turned by a few degrees (a knocked mast camera), and exact on the grid."""
    from nodes.progress.plates import pixel_map

    intr = Intrinsics(width_px=640, height_px=360, f_px=520.0, cx_px=321.3, cy_px=178.9, k1=-0.12, k2=0.03)
    a = look_at((0.0, -20.0, 8.0), (0.0, 0.0, 2.0))
    b = look_at((0.02, -20.0, 8.0), (1.2, 0.3, 2.4))
    exact = pixel_map(intr, a, intr, b, step_px=1)
    coarse = pixel_map(intr, a, intr, b)
    assert coarse.shape == exact.shape == (360, 640, 2)
    assert np.abs(coarse - exact).max() < 0.05
    assert np.abs(coarse[::8, ::8] - exact[::8, ::8]).max() < 1e-3


def test_finish_is_the_posterior_median_not_the_widest_interval() -> None:
    """Hourly photos that see the element appear (fuzzy, on day 10 between 10:00 and 13:00, over several short
    intervals): the finish (posterior median) lands inside the window the evidence points at, between the last absent
    and first present times."""
    H = D // 24
    window = ElementWindow(build_start_ns=9 * D, build_finish_ns=10 * D + 12 * H)
    times = [d * D + h * H for d in range(8, 13) for h in range(8, 17)]
    obs = []
    for k, t in enumerate(times):
        if 10 * D + 10 * H < t <= 10 * D + 13 * H:
            obs.append(Observation(f"p{k}", t, llr_change=0.8, reference_ns=t - H))
        elif k:
            obs.append(Observation(f"p{k}", t, llr_change=-2.0, reference_ns=times[k - 1]))
        obs.append(Observation(f"s{k}", t, llr_state=0.4 if t > 10 * D + 13 * H else -0.4))
    tr = track(window, obs)
    params = FusionParams()
    post = tr.posterior(params)
    e = estimate(tr, post, times[-1], params)
    assert e.state == "built"
    assert e.finish_ns is not None and 10 * D + 9 * H <= e.finish_ns <= 10 * D + 14 * H
    assert e.last_absent_ns is not None and e.first_present_ns is not None
    assert e.last_absent_ns < e.finish_ns <= e.first_present_ns


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_change_cue_discounts_a_built_element_behind_that_appeared_since_the_plate(seed: int) -> None:
    """A candidate beam in front of a wall believed built: the beam's pixels changed since the plate. If the wall
    appeared after the plate's frame, that change may be the wall's; if it stood then, it is the beam's."""
    r = LayerRenderer()
    r.set_model(
        ["beam", "wall"],
        {"beam": box((-1.5, -0.2, 0.9), (1.5, 0.2, 1.6)), "wall": box((-3.0, 1.5, 0.0), (3.0, 1.8, 3.0))},
    )
    T = look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.0))
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.array([False, False, True]), np.array([False, True, False]))
    beam, wall = layers.ids_all == 1, layers.ids_all == 2
    assert beam.sum() > 300 and wall.sum() > 300
    grass = textured(rng, (H, W), (90, 140, 80))
    bricks = textured(rng, (H, W), (160, 70, 50))
    present = np.array([0.0, 0.3, 1.0])
    params = EvidenceParams(built_behind=True, neighbour_px=-1, change_ring_px=0)  # this discount alone
    ones, zeros = np.ones((H, W), bool), np.zeros((H, W), np.int64)

    def beam_llr(before: np.ndarray, after: np.ndarray, wall_then: float, p: EvidenceParams) -> float:
        ref = (to_lab(before), ones, zeros)
        cues = photo_evidence(
            to_lab(after),
            np.zeros((H, W), bool),
            layers,
            ["", "steel", "brick"],
            p,
            reference=ref,
            present=present,
            stood_at=lambda idx, t: np.full(len(idx), wall_then),
        )
        return next(c for c in cues if c.index == 1).llr_change

    # the wall went up since the plate, the beam did not: the beam's pixels show bricks where there was grass
    wall_up = np.where((beam | wall)[..., None], bricks, grass)
    unaware = beam_llr(grass, wall_up, 0.0, EvidenceParams(built_behind=False, neighbour_px=-1, change_ring_px=0))
    assert unaware > 3.0, "without the built element's history the wall's appearance reads as the beam's"
    assert beam_llr(grass, wall_up, 0.0, params) < 0.5 * unaware, "discounted: the wall may have changed them"
    # the wall stood already; the beam appeared in front of it: full evidence
    steel = textured(rng, (H, W), (70, 90, 160))
    walled = np.where(wall[..., None] | beam[..., None], bricks, grass)
    beam_up = np.where(beam[..., None], steel, walled)
    assert beam_llr(walled, beam_up, 1.0, params) > 3.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_thin_elements_get_a_change_cue_and_a_neighbours_change_is_not_theirs(seed: int) -> None:
    """A slab seen nearly edge-on (3-4 px tall at this size) gets no change cue on a 2 px interior, one on a 1 px
    interior when it appears; when it stays absent but the wall right beside it goes up and the photo's registration
    is 3 px off (the wall's new pixels spill onto the slab's), the neighbour discount keeps that change from
    reading as the slab's."""
    r = LayerRenderer()
    r.set_model(
        ["slab", "wall"],
        {"slab": box((-3.0, -0.2, 1.7), (3.0, 2.0, 1.85)), "wall": box((-3.0, -0.2, 0.0), (3.0, 0.0, 1.7))},
    )
    T = look_at((0.0, -8.0, 1.8), (0.0, 0.0, 1.8))
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.zeros(3, bool), np.array([False, True, True]))
    slab, wall = layers.ids_all == 1, layers.ids_all == 2
    rows = np.nonzero(slab.any(1))[0]
    assert 2 <= len(rows) <= 5 and wall.sum() > 1000, "a thin strip above a wall"
    sky = textured(rng, (H, W), (150, 180, 220), amp=6.0)
    concrete = textured(rng, (H, W), (120, 120, 125))
    bricks = textured(rng, (H, W), (160, 70, 50))
    ones, zeros = np.ones((H, W), bool), np.zeros((H, W), np.int64)
    present = np.array([0.0, 0.2, 0.2])
    off = EvidenceParams(thin_interior_px=-1, neighbour_px=-1)
    on = EvidenceParams(neighbour_px=-1)
    shipped = EvidenceParams()

    def cue(before: np.ndarray, after: np.ndarray, p: EvidenceParams) -> tuple[float, float]:
        cues = photo_evidence(
            to_lab(after),
            np.zeros((H, W), bool),
            layers,
            ["", "concrete", "brick"],
            p,
            reference=(to_lab(before), ones, zeros),
            present=present,
        )
        c = {c.index: c for c in cues}
        return c[1].llr_change, c[2].llr_change

    # the slab appears, the wall does not
    slab_up = np.where(slab[..., None], concrete, sky)
    assert cue(sky, slab_up, off)[0] == 0.0, "2 px interior: too thin for a change cue"
    assert cue(sky, slab_up, on)[0] > 3.0
    assert cue(sky, slab_up, shipped)[0] > 3.0, "the wall beside it did not change: no discount"
    # the wall appears, the slab does not, and the photo sits 3 px lower than the model says
    grown = np.roll(wall, -3, axis=0) | wall
    wall_up = np.where(grown[..., None], bricks, sky)
    naive, wall_llr = cue(sky, wall_up, on)
    assert wall_llr > 3.0 and naive > 1.0, "without the discount the wall's spill reads as the slab's"
    assert cue(sky, wall_up, shipped)[0] < 0.5 * naive


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_change_cue_is_discounted_when_the_surroundings_changed_too(scene, seed: int) -> None:  # noqa: ANN001
    """The slab stays absent while something unmodelled goes up behind it and around it (a stack of formwork
    panels filling its region and 20 px beyond): its pixels changed, but so did its surroundings, and the change
    cue says much less than when the slab alone changes; the wall appearing alone keeps its full cue."""
    r, T = scene
    rng = np.random.default_rng(seed)
    layers = r.render(INTR, T, np.zeros(4, bool), np.array([False, True, True, True]))
    ids = layers.ids_all
    slab, wall = ids == 3, ids == 1
    ys, xs = np.nonzero(slab)
    around = np.zeros((H, W), bool)
    around[max(ys.min() - 20, 0) : ys.max() + 21, max(xs.min() - 20, 0) : xs.max() + 21] = True
    grass = textured(rng, (H, W), (90, 140, 80))
    panels = textured(rng, (H, W), (200, 170, 60))
    concrete = textured(rng, (H, W), (120, 120, 125))
    ref = (to_lab(grass), np.ones((H, W), bool), np.zeros((H, W), np.int64))

    def llr(after: np.ndarray, p: EvidenceParams, index: int) -> float:
        cues = photo_evidence(to_lab(after), np.zeros((H, W), bool), layers, ["", "b", "c", "c"], p, reference=ref)
        return next(c for c in cues if c.index == index).llr_change

    off, shipped = EvidenceParams(change_ring_px=0), EvidenceParams()
    stacked = np.where(around[..., None], panels, grass)
    assert llr(stacked, off, 3) > 3.0, "without the ring the panels' change reads as the slab's"
    assert llr(stacked, shipped, 3) < 0.5 * llr(stacked, off, 3)
    slab_up = np.where(slab[..., None], concrete, grass)
    assert llr(slab_up, shipped, 3) > 0.9 * llr(slab_up, off, 3) > 3.0, "the slab alone appearing: full cue"
    wall_up = np.where(wall[..., None], panels, grass)
    assert llr(wall_up, shipped, 1) > 0.9 * llr(wall_up, off, 1) > 3.0
