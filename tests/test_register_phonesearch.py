"""Phone photos found by the model (nodes/register/vanishing.py, nodes/register/phonesearch.py): the rotation from
straight lines and the position search around GPS on seeded box scenes; the matches' word before a camera is taken.
Truth is read by the tests only (they are the scoring)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from constructaide import camera as cam
from nodes.register.phonesearch import phone_anchor, search_phone
from nodes.register.vanishing import camera_from_world, model_axes_yaw_deg, vanishing_rotations
from schemas.messages import GeoPoint
from tests.test_register_modelsearch import H, W, _building, _error_pct, _photo

F = 560.0


def _phone_camera(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A person 9-14 m from the building's side, at hand height, looking at a point of it, rolled a few degrees."""
    mid = (lo + hi) / 2
    ang = rng.uniform(0, 2 * np.pi)
    half = np.hypot(*(hi[:2] - lo[:2])) / 2
    centre = np.r_[mid[:2] + (half + rng.uniform(9, 14)) * np.array([np.cos(ang), np.sin(ang)]), rng.uniform(1.45, 1.8)]
    aim = np.r_[mid[:2] + rng.uniform(-0.25, 0.25, 2) * (hi[:2] - lo[:2]), rng.uniform(2.5, 5.0)]
    wfc = cam.look_at(centre, aim)
    a = math.radians(rng.uniform(-4, 4))
    wfc[:3, :3] = wfc[:3, :3] @ np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return wfc


def _view_photo_gps(seed: int, gps_off_m: float):  # noqa: ANN202
    """A seeded frame building's view (the caller closes it), its vertices (N, 3), a phone camera (4, 4), its photo
    and a GPS position (x, y) m ``gps_off_m`` from the camera."""
    rng = np.random.default_rng(seed)
    _, view, allv, lo, hi = _building(rng)
    wfc = _phone_camera(rng, lo, hi)
    gray = _photo(view, wfc, rng)
    off = rng.normal(0, 1, 2)
    return view, allv, wfc, gray, wfc[:2, 3] + gps_off_m * off / np.linalg.norm(off)


def test_model_axes_follow_the_walls() -> None:
    """The heading of a model's axes (mod 90 deg) from its vertical faces, whatever the area of each."""
    rng = np.random.default_rng(0)
    for yaw in (0.0, 17.0, 62.5, 89.0):
        a = np.radians(yaw + 90.0 * rng.integers(0, 4, 40))
        n = np.c_[np.cos(a), np.sin(a), np.zeros(40)]
        flat = np.tile([0.0, 0.0, 1.0], (10, 1))  # slabs do not count
        got = model_axes_yaw_deg(np.r_[n, flat], rng.uniform(0.5, 9.0, 50))
        assert abs((got - yaw + 45.0) % 90.0 - 45.0) < 1e-6


def test_camera_from_world_looks_where_it_is_told() -> None:
    rot = camera_from_world(np.radians(30.0), np.radians(10.0), 0.0)
    fwd = rot[2]  # the optical axis in the world
    pitch, heading = math.radians(10), math.radians(30)
    c10, s10, c30, s30 = math.cos(pitch), math.sin(pitch), math.cos(heading), math.sin(heading)
    assert np.allclose(fwd, [c10 * c30, c10 * s30, s10])
    assert abs(rot[0, 2]) < 1e-12  # level: the image's x axis is horizontal


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_rotation_from_vanishing_lines(seed: int) -> None:
    """A phone view of a seeded frame building (columns, slabs, core; clutter strokes around): one of the returned
    rotations within 2 deg of the truth, with the focal prior 3 % off (these views hold a few dozen lines; on the
    default synthetic site's 30 phone photos the median is 0.4 deg)."""
    rng = np.random.default_rng(seed)
    _, view, _, lo, hi = _building(rng)
    try:
        wfc = _phone_camera(rng, lo, hi)
        gray = _photo(view, wfc, rng)
        rots = vanishing_rotations(gray, cam.centered_intrinsics(W, H, F * 1.03), 0.0)
        assert len(rots) % 4 == 0 and rots
        err = min(cam.rotation_angle_deg(r.T, wfc[:3, :3]) for r, _ in rots)
        assert err < 2.0, err
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_phone_search_finds_the_camera_near_its_gps(seed: int) -> None:
    """The same views, GPS 3.5 m off, focal prior 3 % off: a camera within 0.5 % of the width among the three best
    the search returns, and none of them inside the building."""
    view, allv, wfc, gray, gps = _view_photo_gps(seed, 3.5)
    try:
        prior = cam.centered_intrinsics(W, H, F * 1.03)
        found = search_phone(view, gray, prior, (float(gps[0]), float(gps[1])), None, 0.0)
        truth = cam.centered_intrinsics(W, H, F)
        errs = [_error_pct(h.world_from_camera, h.intrinsics, wfc, truth, allv) for h in found[:3]]
        assert errs and min(errs) < 0.5, errs
        for h in found:
            c = h.world_from_camera[:3, 3]
            assert not (np.all(c[:2] > allv.min(axis=0)[:2]) and np.all(c[:2] < allv.max(axis=0)[:2]))
    finally:
        view.close()


class _Lookup:
    """What phone_anchor reads of the register node's depth lookup: the view, the site's GPS reference at the model's
    origin, standing elements and the terrain."""

    def __init__(self, view) -> None:  # noqa: ANN001
        self.view = view
        self.site_gps = GeoPoint(lat_deg=51.0, lon_deg=5.0)
        self.origin_offset_m = (0.0, 0.0, 0.0)
        self.ground_height_m = 0.0

    def elements(self, capture_time_ns: int) -> None:
        return None


def _gps_at(xy: np.ndarray) -> GeoPoint:
    r = 6371008.8  # constructaide.geo's Earth radius
    lat = 51.0 + math.degrees(xy[1] / r)
    return GeoPoint(lat_deg=lat, lon_deg=5.0 + math.degrees(xy[0] / (r * math.cos(math.radians(0.5 * (lat + 51.0))))))


@pytest.mark.parametrize("seed", [1, 2])
def test_a_camera_is_taken_only_when_the_matches_agree(seed: int) -> None:
    """phone_anchor takes the first camera (by outline contrast) that the photo's matches confirm: with simulated
    matches that agree only near the true camera it returns clicks of that camera (pixels within 0.5 % of the width
    of the model points' true projections); with matches that agree with nothing it refuses and says so."""
    view, allv, wfc, gray, xy = _view_photo_gps(seed, 3.0)
    try:
        gps = _gps_at(xy)
        lookup = _Lookup(view)
        prior = cam.centered_intrinsics(W, H, F * 1.03)
        truth = cam.centered_intrinsics(W, H, F)

        def near_truth(intr, world_from_camera, tolerance_rel):  # noqa: ANN001, ANN202
            """Matches with a registered frame as they would agree: many where the camera lays the model where the
            truth does (within the tolerance's scale), few elsewhere."""
            err = _error_pct(world_from_camera, intr, wfc, truth, allv)
            return (60 if err < (0.5 if tolerance_rel < 0.01 else 10.0) else 5), "cam-a/frame.jpg"

        clicks, why = phone_anchor(lookup, gray, prior, gps, 0, near_truth, 25, 0.06)  # type: ignore[arg-type]
        assert clicks is not None, why
        px, pts = clicks
        true_px, _ = cam.project_points(truth, cam.invert_rigid(wfc), pts)
        assert 100.0 * np.median(np.linalg.norm(px - true_px, axis=1)) / W < 0.5
        assert "60 matches with cam-a/frame.jpg agree" in why
        clicks, why = phone_anchor(lookup, gray, prior, gps, 0, lambda i, w, t: (3, "cam-a/frame.jpg"), 25, 0.06)  # type: ignore[arg-type]
        assert clicks is None and "at most 3 of the photo's matches agree roughly" in why
        clicks, why = phone_anchor(lookup, gray, prior, None, 0, near_truth, 25, 0.06)  # type: ignore[arg-type]
        assert clicks is None and "no GPS" in why
    finally:
        view.close()


@pytest.mark.parametrize("seed", [1, 2])
def test_refinement_on_matches_and_outline(seed: int) -> None:
    """A camera found 0.4 m and 0.6 deg off, refined on the photo's outline and its matches with a registered camera
    elsewhere (exact projections of model points, a third of them mismatched): back within 0.15 % of the width, and
    the matches agree with it."""
    from nodes.register.modelsearch import Hypothesis
    from nodes.register.phonesearch import epipolar_distances_px, refine_on_matches

    rng = np.random.default_rng(seed)
    _, view, allv, lo, hi = _building(rng)
    try:
        wfc = _phone_camera(rng, lo, hi)
        gray = _photo(view, wfc, rng)
        truth = cam.centered_intrinsics(W, H, F)
        other = cam.look_at(wfc[:3, 3] + np.r_[rng.uniform(-25, 25, 2), 8.0], (lo + hi) / 2)
        pts = lo + rng.uniform(0, 1, (300, 3)) * (hi - lo)
        px_this, _ = cam.project_points(truth, cam.invert_rigid(wfc), pts)
        px_other, _ = cam.project_points(truth, cam.invert_rigid(other), pts)
        bad = rng.random(len(pts)) < 0.33
        px_this[bad] += rng.uniform(-80, 80, (int(bad.sum()), 2))
        x_other = cam.pixels_to_normalized(truth, px_other)
        start = wfc.copy()
        a = np.radians(0.6)
        start[:3, :3] = wfc[:3, :3] @ np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        start[:3, 3] += rng.normal(0, 1, 3) * 0.4 / np.sqrt(3)
        h = Hypothesis(start, truth, 0.0)
        before = _error_pct(start, truth, wfc, truth, allv)
        got = refine_on_matches(view, gray, h, None, 0.0, [(x_other, other, px_this)], near_rel=0.05)
        after = _error_pct(got.world_from_camera, truth, wfc, truth, allv)
        assert after < 0.15 < before, (before, after)
        d = epipolar_distances_px(x_other, other, px_this, truth, got.world_from_camera)
        assert np.mean(d[~bad] < 2.0) > 0.9
        assert got.contrast > 0.1
    finally:
        view.close()


def test_streaming_registrar_searches_a_phone_once_when_on(monkeypatch) -> None:  # noqa: ANN001
    """With ``phone_search`` on, a phone photo that needs clicks goes to ``phone_anchor_in`` once (not again on its
    next try, only once more fixed cameras carry texture) and a camera it returns registers the photo by the model
    (no request); off, nothing is searched."""
    import cv2
    from test_register_modelalign import INTR, _true_camera
    from test_register_modelalign import _photo as _box_photo
    from test_register_modelalign import _scene as _boxes

    from constructaide.modelview import ModelView
    from nodes.register import streaming
    from nodes.register.bimdepth import MeshDepthLookup
    from nodes.register.config import MapperConfig
    from nodes.register.modelsearch import virtual_clicks
    from nodes.register.photo import FrameImage, PhotoInput
    from nodes.register.streaming import Outcome, StreamConfig, StreamingRegistrar

    meshes = _boxes(0)
    lookup = MeshDepthLookup(meshes, ground_height_m=0.0)
    view = ModelView(meshes)
    try:
        T = _true_camera(0)
        clicks = virtual_clicks(view, INTR, T, None, 0.0, 24)
        calls: list[str] = []

        sources: list = []

        def found(recon, idx, lk, gray, intr, cfg, frames):  # noqa: ANN001, ANN202
            calls.append(recon.images[idx].name)
            assert gray.shape == (INTR.height_px, INTR.width_px)
            sources.extend(frames)
            return clicks, "test camera; 40 matches with cam-a/f.jpg agree"

        monkeypatch.setattr(streaming, "phone_anchor_in", found)
        jpeg = cv2.imencode(".jpg", cv2.cvtColor(_box_photo(view, T, 0), cv2.COLOR_GRAY2BGR))[1].tobytes()
        phone = PhotoInput("p0", FrameImage(jpeg), camera_id=None, focal_px=INTR.f_px)
        for on, expected in ((False, 0), (True, 1)):
            reg = StreamingRegistrar(StreamConfig(mapper=MapperConfig(phone_search=on)), depth_lookup=lookup, site="t")
            fixed = PhotoInput("f0", FrameImage(jpeg), camera_id="cam-a", focal_px=INTR.f_px, capture_time_ns=7)
            reg.register_anchor(fixed, *clicks)  # a fixed camera's frame: the texture source the search is given
            rec = reg.poses["f0"]
            as_registered = (rec.intrinsics, rec.world_from_camera.copy())
            reg._ensure_image(phone)
            asked = Outcome(reg._failed(phone, "needs clicks (test)", 0.0), needs_anchor="needs clicks (test)")
            got = reg._by_model(phone, asked)
            assert len(calls) == expected
            if not on:
                assert got is asked
                continue
            assert got.needs_anchor is None and got.registration.method == "model"
            assert "test camera" in got.registration.message
            [(pixels, intr_f, wfc_f, t_f)] = sources  # the fixed camera's latest registered frame, as registered
            assert pixels.shape == (INTR.height_px, INTR.width_px) and t_f == 7
            assert intr_f == as_registered[0] and np.array_equal(wfc_f, as_registered[1])
            reg._by_model(phone, asked)  # the same fixed cameras: the request stands, no second search
            assert len(calls) == 1
            other = PhotoInput("f1", FrameImage(jpeg), camera_id="cam-b", focal_px=INTR.f_px, capture_time_ns=8)
            reg.register_anchor(other, *clicks)  # one more fixed camera carries texture: searched again, with both
            sources.clear()
            reg._by_model(phone, asked)
            assert len(calls) == 2 and len(sources) == 2
            reg._by_model(phone, asked)
            assert len(calls) == 2
    finally:
        view.close()
        lookup.close()
