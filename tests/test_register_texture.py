"""A camera scored and refined on a registered photo's texture carried through the model (nodes/register/texture.py)
and a phone photo found that way (phonesearch.phone_anchor_by_texture), on seeded textured box buildings: mortar
joints every half metre (a repeat that matches a camera one joint aside) and a few unique blotches. Truth is read by
the tests only (they are the scoring)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from constructaide import camera as cam
from constructaide.modelview import ModelView
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.phonesearch import (
    PhoneSearchParams,
    bay_scan,
    model_axes_yaw,
    phone_anchor_by_texture,
    retexture,
)
from nodes.register.texture import (
    TextureParams,
    carry,
    local_ncc,
    refine_by_texture,
    texture_score,
    texture_source,
    work_gray,
)
from tests.test_register_modelsearch import _building, _error_pct

W, H, F = 800, 600, 640.0
INTR = cam.centered_intrinsics(W, H, F)


def _blotches(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, n: int = 250) -> np.ndarray:
    """(n, 5): centre (3) m, radius m, amplitude (grey levels) of unique marks on and around the building."""
    c = rng.uniform(lo - [4, 4, 0], hi + [4, 4, 0], (n, 3))
    c[: n // 4, 2] = 0.0  # some on the ground
    return np.c_[c, rng.uniform(0.1, 0.4, n), rng.choice([-1, 1], n) * rng.uniform(30, 60, n)]


def _textured_photo(
    view: ModelView, wfc: np.ndarray, marks: np.ndarray, gain: float, rng: np.random.Generator
) -> np.ndarray:
    """A grey photo whose every surface point X shows the same texture from any view: joints on the planes
    x, y, z = k * 0.5 m, the blotches; sky above; ``gain`` scales it (another day's light), plus noise."""
    depth = view.depth_map(wfc, INTR, None, 0.0)
    vv, uu = np.nonzero(depth > 0)
    z = depth[vv, uu].astype(np.float64)
    xy = cam.pixels_to_normalized(INTR, np.c_[uu, vv].astype(np.float64))
    X = np.c_[xy * z[:, None], z] @ wfc[:3, :3].T + wfc[:3, 3]
    joint = np.any(np.abs(((X + 0.25) % 0.5) - 0.25) < 0.02, axis=1)
    val = 120.0 - 45.0 * joint
    for cx, cy, cz, r, amp in marks:
        val += amp * np.exp(-np.sum((X - [cx, cy, cz]) ** 2, axis=1) / (2 * r * r))
    img = np.full((H, W), 215.0)
    img[vv, uu] = gain * val
    img += rng.normal(0, 3, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _scene(seed: int):  # noqa: ANN202
    """A seeded building's view (closed by the caller), its vertices, a fixed camera's pose and photo (the source),
    and a phone's pose and photo 8-12 m from the building at hand height."""
    rng = np.random.default_rng(seed)
    _, view, allv, lo, hi = _building(rng)
    marks = _blotches(rng, lo, hi)
    mid = (lo + hi) / 2
    side = rng.uniform(0, 2 * np.pi)
    far = mid + np.r_[30 * np.cos(side), 30 * np.sin(side), 0.0]
    fixed = cam.look_at(np.r_[far[:2], 9.0], np.r_[mid[:2], 3.0])
    half = np.hypot(*(hi[:2] - lo[:2])) / 2
    a = side + rng.uniform(-0.5, 0.5)
    centre = np.r_[mid[:2] + (half + rng.uniform(8, 12)) * np.array([np.cos(a), np.sin(a)]), rng.uniform(1.45, 1.8)]
    phone = cam.look_at(centre, np.r_[mid[:2] + rng.uniform(-1.5, 1.5, 2), rng.uniform(2.5, 4.0)])
    src = _textured_photo(view, fixed, marks, 1.0, rng)
    dst = _textured_photo(view, phone, marks, rng.uniform(0.75, 0.9), rng)
    return view, allv, fixed, src, phone, dst


def _moved(wfc: np.ndarray, shift_m: np.ndarray, turn_deg: float) -> np.ndarray:
    out = wfc.copy()
    out[:3, 3] += shift_m
    a = math.radians(turn_deg)
    out[:3, :3] = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]) @ out[:3, :3]
    return out


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_carried_texture_matches_at_the_true_pose_and_not_a_joint_aside(seed: int) -> None:
    """The fixed camera's texture carried to the phone's true pose correlates with the phone photo (another light);
    half a metre aside (one joint period: the joints line up again) and a metre aside it does not."""
    view, _, fixed, src, phone, dst = _scene(seed)
    try:
        sources = [texture_source(view, src, INTR, fixed, None, 0.0)]
        photo = work_gray(dst, 480)
        true_score, n = texture_score(view, photo, INTR, phone, None, 0.0, sources)
        assert n > 5000 and true_score > 0.5, (true_score, n)
        for step in (0.5, 1.0):
            aside = _moved(phone, step * phone[:3, 0], 0.0)
            score, _ = texture_score(view, photo, INTR, aside, None, 0.0, sources)
            assert score < true_score - 0.25, (step, score, true_score)
        # local_ncc itself: an image against a brighter copy of itself correlates fully where both vary
        ncc, ok = local_ncc(photo, 1.3 * photo + 7.0, np.ones(photo.shape, bool), 9, 4.0)
        assert ok.mean() > 0.2 and np.allclose(ncc[ok], 1.0, atol=1e-3)  # not the flat sky
        # carry: the carried pixels are model points the phone sees (its depth render), where the source sees them
        wi = cam.centered_intrinsics(480, 360, F * 480 / W)
        c = carry(view, wi, phone, None, 0.0, sources)
        assert c.valid.sum() > 0.3 * c.valid.size and np.all(c.image[~c.valid] == 0)
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_large_structures_line_up_at_the_true_pose_only(seed: int) -> None:
    """The structure score (blurred images: the joints gone, the blotches and the building's outline kept) is high at
    the phone's true pose and clearly lower a joint period (0.5 m) or two metres aside; the bay scan from a camera
    moved 2 m along one of the model's axes (what the fine texture of like bays confuses) returns the true camera,
    from the true camera nothing."""
    view, _, fixed, src, phone, dst = _scene(seed)
    try:
        sources = [texture_source(view, src, INTR, fixed, None, 0.0)]
        photo = work_gray(dst, 480)
        true_score, n = texture_score(view, photo, INTR, phone, None, 0.0, sources, structures=True)
        assert n > 5000 and true_score > 0.5, (true_score, n)
        for step in (0.5, 2.0):
            aside, _ = texture_score(
                view, photo, INTR, _moved(phone, step * phone[:3, 0], 0.0), None, 0.0, sources, structures=True
            )
            assert aside < true_score - 0.2, (step, aside, true_score)
        yaw = math.radians(model_axes_yaw(view))
        moved = _moved(phone, 2.0 * np.array([math.cos(yaw), math.sin(yaw), 0.0]), 0.0)
        gps = (float(phone[0, 3]), float(phone[1, 3]))
        p, tp = PhoneSearchParams(), TextureParams()
        back, _ = bay_scan(view, photo, INTR, moved, None, 0.0, sources, gps, p, tp)
        assert back is not None and np.linalg.norm(back[:3, 3] - phone[:3, 3]) < 1e-6
        assert bay_scan(view, photo, INTR, phone, None, 0.0, sources, gps, p, tp)[0] is None
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_refinement_on_the_texture_reaches_the_true_pose(seed: int) -> None:
    """From a camera 0.3-0.4 m and a degree off (what the outline search hands over), the flow + PnP steps land within
    0.5 % of the width (the issue's bar; 0.1-0.35 % on these seeds); from a camera that sees none of what the
    source saw, None."""
    view, allv, fixed, src, phone, dst = _scene(seed)
    try:
        rng = np.random.default_rng(100 + seed)
        sources = [texture_source(view, src, INTR, fixed, None, 0.0)]
        photos = {w: work_gray(dst, w) for w in TextureParams().levels_px}
        off = rng.normal(0, 1, 3)
        start = _moved(phone, rng.uniform(0.3, 0.4) * off / np.linalg.norm(off), rng.choice([-1.0, 1.0]))
        assert _error_pct(start, INTR, phone, INTR, allv) > 0.5
        got = refine_by_texture(view, photos, INTR, start, None, 0.0, sources)
        assert got is not None
        assert _error_pct(got, INTR, phone, INTR, allv) < 0.5
        away = cam.look_at(phone[:3, 3], phone[:3, 3] - 10.0 * phone[:3, 2] + [0, 0, 3.0])  # turned to the sky
        assert refine_by_texture(view, photos, INTR, away, None, 0.0, sources) is None
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_found_phone_refined_again_on_the_final_source_poses(seed: int) -> None:
    """A phone camera found on a fixed frame whose pose has moved since (the camera 0.15 m and 0.3 deg off, as
    found on the frame's pose of then) is refined again on the frame at its final (here true) pose: its model-point
    clicks put it within 0.3 % of the width, at most half as far off as it was; no frames, or a camera turned to the
    sky: None."""
    view, allv, fixed, src, phone, dst = _scene(seed)
    try:
        rng = np.random.default_rng(300 + seed)
        off = rng.normal(0, 1, 3)
        found = _moved(phone, 0.15 * off / np.linalg.norm(off), 0.3)
        before = _error_pct(found, INTR, phone, INTR, allv)
        lookup = _Lookup(view)
        frames = [(src, INTR, fixed, 0)]
        clicks = retexture(lookup, dst, INTR, found, 0, frames)
        assert clicks is not None
        px, pts = clicks
        _, rvec, tvec = cv2.solvePnP(pts, px, cam.K_matrix(INTR), None)
        again = cam.invert_rigid(cam.rigid(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        after = _error_pct(again, INTR, phone, INTR, allv)
        assert after < 0.3 and after < 0.5 * before, (before, after)  # 0.54-0.68 % -> 0.06-0.21 % on these seeds
        assert retexture(lookup, dst, INTR, found, 0, []) is None
        away = cam.look_at(phone[:3, 3], phone[:3, 3] - 10.0 * phone[:3, 2] + [0, 0, 3.0])
        assert retexture(lookup, dst, INTR, away, 0, frames) is None
    finally:
        view.close()


class _Lookup(MeshDepthLookup):
    """The depth lookup over a test view (every element standing, the terrain at 0)."""

    def __init__(self, view: ModelView) -> None:
        self.view = view
        self.elements_at = None
        self.ground_height_m = 0.0
        self.max_relative_spread = 0.03
        self.site_gps = None
        self.origin_offset_m = (0.0, 0.0, 0.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_phone_found_by_the_texture_near_its_gps(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole phone search: rotation from the photo's lines, cameras around a GPS position 3 m off, each refined
    on the fixed camera's texture: the clicks it returns put the camera within 0.5 % of the width; a photo of another
    building near the same GPS position is refused, saying why."""
    view, allv, fixed, src, phone, dst = _scene(seed)
    try:
        rng = np.random.default_rng(200 + seed)
        off = rng.normal(0, 1, 2)
        gps_xy = phone[:2, 3] + 3.0 * off / np.linalg.norm(off)
        monkeypatch.setattr(
            "nodes.register.phonesearch.gps_in_model", lambda _lookup, _gps: ((float(gps_xy[0]), float(gps_xy[1])), "")
        )
        lookup = _Lookup(view)
        sources = [texture_source(view, src, INTR, fixed, None, 0.0)]
        prior = cam.centered_intrinsics(W, H, F)
        clicks, why = phone_anchor_by_texture(lookup, dst, prior, None, 0, sources)
        assert clicks is not None, why
        px, pts = clicks
        _, rvec, tvec = cv2.solvePnP(pts, px, cam.K_matrix(prior), None)
        found = cam.invert_rigid(cam.rigid(cv2.Rodrigues(rvec)[0], tvec.ravel()))
        assert _error_pct(found, prior, phone, INTR, allv) < 0.5, why
        other_view, *_, other_phone, other_photo = _scene(seed + 50)  # another building seen from elsewhere
        other_view.close()
        clicks, why = phone_anchor_by_texture(lookup, other_photo, prior, None, 0, sources)
        assert clicks is None and "texture" in why
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_phone_found_a_bay_along_the_facade_is_moved_to_the_bay_that_lines_up_better(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A long facade of like bays (most marks repeat every 3 m along it, a few are unique) photographed obliquely
    from 8-10 m. A phone first found one bay along the facade from where it stands (its texture lines up there too)
    is moved to the bay that lines up better (``ambiguity_take_better``: the ambiguity test's moves, across the view
    and along the model's axes, start refinements that land there): within 0.5 % of the width. Without it the
    search keeps the wrong bay or refuses."""
    from nodes.register.modelsearch import Hypothesis
    from tests.test_register_modelsearch import _box

    rng = np.random.default_rng(seed)
    meshes = {"wall": _box(np.array([0.0, 0.0, 0.0]), np.array([36.0, 0.4, 9.0]))}
    view = ModelView(meshes)
    bay = 3.0
    unique = np.c_[rng.uniform([0, -0.3, 0], [36, 0.0, 9], (30, 3)), rng.uniform(0.2, 0.4, 30), np.full(30, 60.0)]
    base = np.c_[rng.uniform([0, -3, 0], [bay, 0, 9], (40, 3)), rng.uniform(0.1, 0.4, 40), rng.uniform(-60, 60, 40)]
    marks = np.concatenate([unique, *(base + [k * bay, 0, 0, 0, 0] for k in range(-1, 13))])
    d, turn = rng.uniform(8, 10), math.radians(rng.uniform(30, 40)) * (1 if seed % 2 else -1)
    centre = np.array([18.0, -d, 1.6])
    phone = cam.look_at(centre, np.array([18.0 + d * math.tan(turn), 0.0, 3.5]))
    fixed = cam.look_at(np.array([18.0, -30.0, 9.0]), np.array([18.0, 0.0, 3.5]))
    src = _textured_photo(view, fixed, marks, 1.0, rng)
    dst = _textured_photo(view, phone, marks, 0.85, rng)
    wrong = phone.copy()
    wrong[0, 3] += bay * (1 if seed < 3 else -1)
    monkeypatch.setattr(
        "nodes.register.phonesearch.gps_in_model", lambda _l, _g: ((float(centre[0]), float(centre[1])), "")
    )
    monkeypatch.setattr(
        "nodes.register.phonesearch.search_phone",
        lambda *_a, **_k: [Hypothesis(world_from_camera=wrong, intrinsics=INTR, coarse=1.0)],
    )
    monkeypatch.setattr("nodes.register.phonesearch.bay_scan", lambda *a, **_k: (None, 0.0))
    try:
        lookup = _Lookup(view)
        sources = [texture_source(view, src, INTR, fixed, None, 0.0)]
        errors, whys = {}, {}
        for on in (True, False):
            p = PhoneSearchParams(ambiguity_model_axes=on, ambiguity_take_better=on, ambiguity_steps_m=(bay,))
            clicks, whys[on] = phone_anchor_by_texture(lookup, dst, INTR, None, 0, sources, params=p)
            if clicks is None:
                errors[on] = math.inf
                continue
            px, pts = clicks
            _, rvec, tvec = cv2.solvePnP(pts, px, cam.K_matrix(INTR), None)
            found = cam.invert_rigid(cam.rigid(cv2.Rodrigues(rvec)[0], tvec.ravel()))
            errors[on] = _error_pct(found, INTR, phone, INTR, pts)  # the clicked points: in front of both
        assert errors[True] < 0.5, (errors, whys)
        assert errors[False] > 2.0, (errors, whys)
    finally:
        view.close()
