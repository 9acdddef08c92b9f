"""Anchor clicks that fit several cameras: three distinct clicked points (a fourth on the same spot) pin a camera only
up to the discrete solutions of three points. The solve reports the others (``AnchorSolution.ambiguous``) instead
of publishing one of them silently; the mapper picks the one the photo's GPS agrees with, or asks for more clicks."""

from __future__ import annotations

import numpy as np
import pytest
from test_register_batch_sfm import F, make_features, scene_points
from test_register_gps import gps_at

from constructaide import camera as cam
from constructaide.anchorsolve import AnchorSolution, DegenerateAnchors, solve_anchor
from nodes.register import config, mapper
from nodes.register import recon as rc
from schemas.messages import GeoPoint

W, H = 800, 600


def three_point_clicks(rng: np.random.Generator):
    """A phone 10-20 m from a building, clicking three corners of it and one of them again 5 cm off (two elements
    meeting there), 1 px noise. Returns (true world_from_camera, pixels (4, 2), points (4, 3))."""
    eye = np.r_[rng.uniform(-8, 8), rng.uniform(-20, -10), rng.uniform(1.2, 1.8)]
    T = cam.look_at(eye, [rng.uniform(-2, 2), 0.0, rng.uniform(3, 5)])
    pts = np.array([[rng.uniform(-6, -2), 0.0, rng.uniform(4, 7)], [rng.uniform(2, 6), 0.0, rng.uniform(4, 7)]])
    pts = np.vstack([pts, [rng.uniform(3, 9), rng.uniform(3, 6), rng.uniform(2, 4)], pts[1] + [-0.05, 0.05, 0.0]])
    px, z = cam.project_points(cam.centered_intrinsics(W, H, 700.0), cam.invert_rigid(T), pts)
    assert np.all(z > 0)
    return T, px + rng.normal(0, 1.0, px.shape), pts


def test_three_distinct_clicks_never_give_a_silently_wrong_camera() -> None:
    """60 seeded click sets: the solved camera is the true one (within 5 deg), or the true one is among the
    reported alternatives; a wrong camera without alternatives never comes out."""
    rng = np.random.default_rng(0)
    silent, reported = 0, 0
    for _ in range(60):
        T, px, pts = three_point_clicks(rng)
        try:
            sol = solve_anchor(px, pts, W, H, focal_px=700.0)
        except DegenerateAnchors:
            continue
        right = cam.viewing_angle_deg(sol.world_from_camera, T) < 5.0
        among = any(cam.viewing_angle_deg(A, T) < 5.0 for A, _ in sol.ambiguous)
        silent += not (right or among)
        reported += bool(sol.ambiguous)
    assert silent == 0
    assert reported >= 30, "three points nearly always have a second solution that fits as well"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_well_spread_clicks_are_not_ambiguous(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = cam.look_at([12.0, -22.0, 6.0], [0.0, 0.0, 2.5])
    pts = rng.uniform([-5, -5, 0], [5, 5, 6], (12, 3))
    px, _ = cam.project_points(cam.centered_intrinsics(1920, 1080, 1500.0), cam.invert_rigid(T), pts)
    sol = solve_anchor(px + rng.normal(0, 1.5, px.shape), pts, 1920, 1080, focal_px=1500.0)
    assert sol.ambiguous == []
    assert cam.viewing_angle_deg(sol.world_from_camera, T) < 0.5


def _site(with_references: bool, phone_gps: GeoPoint):
    """A reconstruction of three registered fixed cameras (model frame = east / north / up metres) with GPS, and an
    unregistered phone photo with ``phone_gps``."""
    rng = np.random.default_rng(3)
    pts = scene_points(rng, 200)
    desc = rng.normal(size=(len(pts), 128))
    recon = rc.Reconstruction()
    if with_references:
        for name, (e, n) in {"north": (0.0, 45.0), "east": (46.0, -11.0), "west": (-46.0, 5.0)}.items():
            T = cam.look_at([e, n, 9.0], [0.0, 0.0, 3.0])
            rc.add_image(recon, name, make_features(rng, pts, desc, T)[0], gps=gps_at(e, n))
            im = recon.images[-1]
            im.world_from_camera, im.intrinsics = T, cam.centered_intrinsics(im.width_px, im.height_px, F)
            im.status, im.method = "anchor", "anchor"
    T_phone = cam.look_at([5.0, -18.0, 1.6], [0.0, 0.0, 4.0])
    rc.add_image(recon, "phone", make_features(rng, pts, desc, T_phone)[0], gps=phone_gps)
    return recon, len(recon.images) - 1, T_phone


def _ambiguous_solution(T_true: np.ndarray) -> tuple[AnchorSolution, np.ndarray, np.ndarray]:
    """The solve's pick is a camera 25 m away looking elsewhere; the true one is its reported alternative."""
    wrong = cam.look_at([-20.0, 10.0, 1.6], [0.0, 0.0, 4.0])
    intr = cam.centered_intrinsics(1024, 768, F)
    pts = np.array([[-3.0, 0.0, 5.0], [3.0, 0.0, 5.0], [6.0, 4.0, 3.0], [2.95, 0.05, 5.0]])
    px, _ = cam.project_points(intr, cam.invert_rigid(T_true), pts)
    sol = AnchorSolution(
        intrinsics=intr,
        world_from_camera=wrong,
        residuals_px=np.ones(4),
        rms_px=1.0,
        focal_solved=False,
        outlier_mask=np.zeros(4, bool),
        ambiguous=[(T_true, F)],
    )
    return sol, px, pts


def test_gps_picks_the_camera_it_agrees_with() -> None:
    recon, idx, T_phone = _site(True, gps_at(5.0 + 2.0, -18.0 - 1.5))
    sol, px, pts = _ambiguous_solution(T_phone)
    out = mapper.disambiguate_anchor(recon, idx, sol, px, pts, config.MapperConfig(focal_px=F))
    assert cam.viewing_angle_deg(out.world_from_camera, T_phone) < 1e-6
    assert out.ambiguous == [] and out.rms_px < 1e-6


def test_ambiguous_clicks_ask_for_more_when_gps_cannot_decide() -> None:
    recon, idx, T_phone = _site(False, gps_at(5.0, -18.0))  # no registered photo with GPS to compare with
    sol, px, pts = _ambiguous_solution(T_phone)
    with pytest.raises(DegenerateAnchors, match="GPS cannot decide.*add clicks"):
        mapper.disambiguate_anchor(recon, idx, sol, px, pts, config.MapperConfig(focal_px=F))
