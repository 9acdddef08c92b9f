"""Constrained bundle adjustment on a seeded synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

import nodes.register.bundle as bundle_mod
from constructaide import camera as cam
from nodes.register import schur
from nodes.register.bundle import BundleOptions, BundleProblem, bundle_adjust

W, H, F = 800, 600, 700.0


def problem(seed: int = 0, perturb: bool = True):
    rng = np.random.default_rng(seed)
    poses = [cam.invert_rigid(cam.look_at([x, -12, 2], [0, 0, 1])) for x in (-4, -1.5, 1.5, 4)]
    X = rng.uniform([-3, -2, 0], [3, 2, 3], (150, 3))
    intr = cam.centered_intrinsics(W, H, F, 0.03, -0.01)
    obs_c, obs_p, obs_x = [], [], []
    for c, T in enumerate(poses):
        px, z = cam.project_points(intr, T, X)
        ok = np.nonzero((z > 0) & (px[:, 0] > 0) & (px[:, 0] < W) & (px[:, 1] > 0) & (px[:, 1] < H))[0]
        obs_c += [c] * len(ok)
        obs_p += ok.tolist()
        obs_x.append(px[ok] + rng.normal(0, 0.3, (len(ok), 2)))
    obs_x = np.vstack(obs_x)
    C = len(poses)
    clicks = X[:8]
    click_px = cam.project_points(intr, poses[0], clicks)[0]
    ref = np.where(np.arange(len(X)) < 60, 0, -1)  # the anchor (camera 0) carries the first 60 points on its rays
    ref_px = cam.project_points(intr, poses[0], X)[0]
    T0 = np.stack(poses)
    X0 = X.copy()
    f0 = np.full(C, F)
    if perturb:
        for c in (1, 2):
            dR = cam.rodrigues_to_matrix(rng.normal(0, 0.01, 3))
            T0[c, :3, :3] = dR @ T0[c, :3, :3]
            T0[c, :3, 3] += rng.normal(0, 0.1, 3)
        X0 = X + rng.normal(0, 0.05, X.shape)
        f0 = f0 * (1 + rng.normal(0, 0.01, C))
    prob = BundleProblem(
        camera_from_world=T0,
        f_px=f0,
        cx_px=np.full(C, (W - 1) / 2),
        cy_px=np.full(C, (H - 1) / 2),
        k1=np.r_[0.03, np.zeros(C - 1)],  # the anchor's rays start from its true distortion
        k2=np.r_[-0.01, np.zeros(C - 1)],
        pose_fixed=np.array([True, False, False, True]),  # two anchors fix the gauge (scale included)
        intrinsics_fixed=np.zeros(C, bool),
        points_in_world=X0,
        point_fixed=np.zeros(len(X), bool),
        point_ref_cam=ref,
        point_ref_px=ref_px,
        obs_cam=np.array(obs_c),
        obs_point=np.array(obs_p),
        obs_px=obs_x,
        click_cam=np.zeros(len(clicks), int),
        click_world=clicks,
        click_px=click_px,
    )
    return prob, poses, X


def test_bundle_recovers_cameras_with_anchors_fixed():
    prob, poses, X = problem()
    res = bundle_adjust(prob, BundleOptions(max_nfev=100))
    assert res.final_rms_px < 0.5 < res.initial_rms_px
    assert np.allclose(res.camera_from_world[0], poses[0])  # anchor pose untouched
    assert np.allclose(res.camera_from_world[3], poses[3])
    for c in (1, 2):
        Tw, Tw_true = cam.invert_rigid(res.camera_from_world[c]), cam.invert_rigid(poses[c])
        assert cam.viewing_angle_deg(Tw, Tw_true) < 0.1
        assert np.linalg.norm(Tw[:3, 3] - Tw_true[:3, 3]) < 0.1  # 0.8 % of 12 m with a free focal
    assert np.allclose(res.f_px, F, rtol=0.02)
    assert np.median(np.linalg.norm(res.points_in_world - X, axis=1)) < 0.05  # 0.4 % of 12 m


def test_anchor_ray_points_stay_on_their_rays():
    prob, poses, X = problem(seed=1)
    res = bundle_adjust(prob, BundleOptions(max_nfev=100))
    # Points carried by the anchor project exactly onto their anchor pixel under the starting anchor intrinsics.
    intr0 = cam.centered_intrinsics(W, H, prob.f_px[0], prob.k1[0], prob.k2[0])
    px, _ = cam.project_points(intr0, poses[0], res.points_in_world[:60])
    assert np.abs(px - prob.point_ref_px[:60]).max() < 1e-6


def test_analytic_jacobian_matches_finite_differences(monkeypatch):
    prob, _, _ = problem(seed=2)
    captured = {}

    class Stop(Exception):
        pass

    def fake(fun, x0, jac=None, **kw):
        captured.update(fun=fun, jac=jac, x0=x0)
        raise Stop

    monkeypatch.setattr(bundle_mod, "least_squares", fake)
    pp_prior = BundleOptions(
        refine_principal_point=True,
        principal_point_prior_px=np.tile([(W - 1) / 2, (H - 1) / 2], (4, 1)),
        principal_point_prior_sigma_px=np.full(4, 8.0),
    )
    centre_fixed = BundleProblem(**{**prob.__dict__, "centre_fixed": np.array([False, True, False, False])})
    cases = [
        (prob, BundleOptions()),
        (prob, BundleOptions(refine_principal_point=True, refine_distortion=False)),
        (prob, pp_prior),
        (centre_fixed, BundleOptions()),
        (BundleProblem(**{**prob.__dict__, "pp_group": np.array([0, 0, 1, -1])}), pp_prior),
        (BundleProblem(**{**prob.__dict__, "intr_group": np.array([0, 0, 0, -1])}), BundleOptions()),
        (
            BundleProblem(**{**prob.__dict__, "intr_group": np.array([0, 1, 0, 1])}),
            BundleOptions(focal_prior_px=np.full(4, F), focal_prior_sigma_px=np.full(4, 7.0)),
        ),
    ]
    for pr, opts in cases:
        try:
            bundle_adjust(pr, opts)
        except Stop:
            pass
        x = captured["x0"]
        Ja = captured["jac"](x).toarray()
        Jn = approx_derivative(captured["fun"], x, method="3-point")
        assert np.abs(Ja - Jn).max() < 1e-3 * np.abs(Jn).max()


def test_focal_prior_holds_focal():
    prob, _, _ = problem(seed=3)
    prob.f_px[:] = F * 1.05
    opts = BundleOptions(max_nfev=100, focal_prior_px=np.full(4, F * 1.05), focal_prior_sigma_px=np.full(4, 0.01))
    res = bundle_adjust(prob, opts)
    assert np.allclose(res.f_px, F * 1.05, rtol=1e-3)


def test_fixed_centre_camera_only_rotates():
    """A camera tied to a known centre (a rotation-homography sibling of an anchor) recovers its rotation and
    keeps its centre exactly."""
    prob, poses, _ = problem(seed=4)
    true_T1 = poses[1]
    T0 = prob.camera_from_world.copy()
    centre = cam.invert_rigid(true_T1)[:3, 3]
    R_off = cam.rodrigues_to_matrix([0.01, -0.02, 0.015]) @ true_T1[:3, :3]
    T0[1, :3, :3] = R_off
    T0[1, :3, 3] = -R_off @ centre
    fixed = BundleProblem(**{**prob.__dict__, "camera_from_world": T0, "centre_fixed": np.array([0, 1, 0, 0], bool)})
    res = bundle_adjust(fixed, BundleOptions(max_nfev=100))
    Tw = cam.invert_rigid(res.camera_from_world[1])
    assert np.allclose(Tw[:3, 3], centre, atol=1e-9)
    assert cam.viewing_angle_deg(Tw, cam.invert_rigid(true_T1)) < 0.05
    assert res.final_rms_px < 0.5


def test_principal_point_prior_limits_the_shift():
    """Cameras with a principal point 12 px off centre: refined freely it is found; a tight prior keeps it near
    the centre; the squared errors reported fall accordingly."""
    prob, poses, X = problem(seed=5, perturb=False)
    intr = cam.centered_intrinsics(W, H, F, 0.03, -0.01)
    shifted = cam.centered_intrinsics(W, H, F, 0.03, -0.01)
    shifted = type(intr)(**{**{f: getattr(intr, f) for f in intr.__struct_fields__}, "cx_px": intr.cx_px + 12.0})
    obs = np.vstack([cam.project_points(shifted, poses[c], X[prob.obs_point[prob.obs_cam == c]])[0] for c in range(4)])
    prob = BundleProblem(**{**prob.__dict__, "obs_px": obs, "click_px": prob.click_px + [12.0, 0.0]})
    centre = np.tile([(W - 1) / 2, (H - 1) / 2], (4, 1))
    # Linear loss: SciPy applies a robust loss to prior residuals too, which would cap a far-violated prior.
    free = bundle_adjust(prob, BundleOptions(max_nfev=100, refine_principal_point=True, loss="linear"))
    held = bundle_adjust(
        prob,
        BundleOptions(
            max_nfev=100,
            loss="linear",
            refine_principal_point=True,
            principal_point_prior_px=centre,
            principal_point_prior_sigma_px=np.full(4, 0.01),
        ),
    )
    assert np.abs(free.cx_px - centre[:, 0] - 12.0).max() < 1.0
    assert np.abs(held.cx_px - centre[:, 0]).max() < 0.5  # vs 12 px free
    assert free.final_sse_px2 < held.final_sse_px2
    assert free.final_sse_px2 < free.initial_sse_px2


def test_schur_solver_matches_trust_region():
    prob, poses, X = problem(seed=6)
    trf = bundle_adjust(prob, BundleOptions(max_nfev=100))
    lm = bundle_adjust(prob, BundleOptions(max_nfev=100, solver="schur"))
    assert lm.final_rms_px < 0.5 < lm.initial_rms_px
    assert lm.final_sse_px2 <= 1.01 * trf.final_sse_px2
    for c in (1, 2):
        Tw, Tw_true = cam.invert_rigid(lm.camera_from_world[c]), cam.invert_rigid(poses[c])
        assert cam.viewing_angle_deg(Tw, Tw_true) < 0.1
        assert np.linalg.norm(Tw[:3, 3] - Tw_true[:3, 3]) < 0.1
    assert np.median(np.linalg.norm(lm.points_in_world - X, axis=1)) < 0.05


def test_shared_principal_point_found_with_exact_steps():
    """Four cameras of one physical camera whose principal point is (9, -6) px off centre: one shared principal
    point, solved with the Schur steps, recovers it (per camera it would trade off with each rotation)."""
    prob, poses, X = problem(seed=7, perturb=False)
    intr = cam.centered_intrinsics(W, H, F, 0.03, -0.01)
    fields = {f: getattr(intr, f) for f in intr.__struct_fields__}
    shifted = type(intr)(**{**fields, "cx_px": intr.cx_px + 9.0, "cy_px": intr.cy_px - 6.0})
    rng = np.random.default_rng(8)
    obs = np.vstack(
        [cam.project_points(shifted, poses[c], X[prob.obs_point[prob.obs_cam == c]])[0] for c in range(4)]
    ) + rng.normal(0, 0.3, prob.obs_px.shape)
    clicks = cam.project_points(shifted, poses[0], prob.click_world)[0]
    prob = BundleProblem(
        **{
            **prob.__dict__,
            "obs_px": obs,
            "click_px": clicks,
            "pose_fixed": np.array([False, False, False, True]),
            "point_ref_cam": np.full(len(X), -1),
            "pp_group": np.zeros(4, int),
        }
    )
    res = bundle_adjust(prob, BundleOptions(max_nfev=100, refine_principal_point=True, solver="schur"))
    assert np.ptp(res.cx_px) == 0 and np.ptp(res.cy_px) == 0  # one shared principal point
    assert res.cx_px[0] - (W - 1) / 2 == pytest.approx(9.0, abs=1.5)
    assert res.cy_px[0] - (H - 1) / 2 == pytest.approx(-6.0, abs=1.5)


def test_shared_intrinsics_one_focal_per_group_and_priors_counted_once():
    """Cameras of one group share one focal and k1, k2 (recovered from a start spread by 1 %); the focal prior of a
    group is counted once: a group of three under a 1 px prior 5 % off lands where a single camera under the same
    prior would, not three times closer to it."""
    prob, poses, X = problem(seed=9)
    shared = BundleProblem(**{**prob.__dict__, "intr_group": np.zeros(4, int)})
    res = bundle_adjust(shared, BundleOptions(max_nfev=100))
    assert np.ptp(res.f_px) == 0 and np.ptp(res.k1) == 0 and np.ptp(res.k2) == 0
    assert res.f_px[0] == pytest.approx(F, rel=0.005)
    assert res.k1[0] == pytest.approx(0.03, abs=0.01)
    free = bundle_adjust(prob, BundleOptions(max_nfev=100))
    assert np.ptp(free.f_px) > 0
    # prior counting: a group's focal prior acts once (the same as when only its first member had one)
    group = BundleProblem(
        **{**prob.__dict__, "intrinsics_fixed": np.array([True, False, False, False]), "intr_group": np.r_[-1, 0, 0, 0]}
    )
    fits = [
        bundle_adjust(
            group,
            BundleOptions(max_nfev=100, loss="linear", focal_prior_px=np.full(4, F * 1.05), focal_prior_sigma_px=sig),
        ).f_px[1]
        for sig in (np.ones(4), np.r_[1.0, 1.0, np.inf, np.inf])
    ]
    assert fits[0] == pytest.approx(fits[1], abs=1e-6)
    assert F < fits[0] < 1.05 * F  # between the data and the prior


def test_centre_covariance_is_calibrated_over_noise_draws():
    """Every pose free, held by features (0.3 px noise) and by two anchors' clicks (12 each, 1 px noise) that fix
    the frame: over 30 noise draws the predicted centre covariances match the actual centre errors (mean of
    |error|^2 / trace(cov) near 1: neither over- nor under-confident); a fixed pose gets NaN."""
    base, poses, X = problem(seed=11, perturb=False)
    intr = cam.centered_intrinsics(W, H, F, 0.03, -0.01)
    clean = np.vstack([cam.project_points(intr, poses[c], X[base.obs_point[base.obs_cam == c]])[0] for c in range(4)])
    click_world = np.vstack([X[:12], X[-12:]])
    click_cam = np.r_[np.zeros(12, int), np.full(12, 3)]
    click_clean = np.vstack(
        [cam.project_points(intr, poses[0], X[:12])[0], cam.project_points(intr, poses[3], X[-12:])[0]]
    )
    z2 = []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        # The focal priors are measurements too (an EXIF focal 1 % off): drawn like the pixels.
        opts = BundleOptions(
            max_nfev=50,
            ftol=1e-10,
            solver="schur",
            covariance=True,
            refine_distortion=False,
            focal_prior_px=F * (1 + rng.normal(0, 0.01, 4)),
            focal_prior_sigma_px=np.full(4, 0.01 * F),
        )
        prob = BundleProblem(
            **{
                **base.__dict__,
                "obs_px": clean + rng.normal(0, 0.3, clean.shape),
                "click_cam": click_cam,
                "click_world": click_world,
                "click_px": click_clean + rng.normal(0, 1.0, click_clean.shape),
                "pose_fixed": np.zeros(4, bool),
                "point_ref_cam": np.full(len(X), -1),
                "k1": np.full(4, 0.03),
                "k2": np.full(4, -0.01),
                "f_px": np.full(4, F),
            }
        )
        res = bundle_adjust(prob, opts)
        assert res.centre_cov_m2 is not None and res.centre_cov_m2.shape == (4, 3, 3)
        for c in range(4):
            err = cam.invert_rigid(res.camera_from_world[c])[:3, 3] - cam.invert_rigid(poses[c])[:3, 3]
            z2.append(float(err @ err) / float(np.trace(res.centre_cov_m2[c])))
    assert 0.6 < np.mean(z2) < 1.6
    prob = BundleProblem(**{**base.__dict__, "pose_fixed": np.array([True, False, False, True])})
    res = bundle_adjust(prob, BundleOptions(max_nfev=20, solver="schur", covariance=True))
    assert res.centre_cov_m2 is not None
    assert np.isnan(res.centre_cov_m2[[0, 3]]).all()
    assert np.isfinite(res.centre_cov_m2[[1, 2]]).all()


def test_click_noise_is_estimated_apart_from_the_features():
    """Feature residuals of 0.3 px and click residuals of 1 px: two variances, the clicks' corrected for the 7
    parameters of the frame they fix and never below the features'."""
    rng = np.random.default_rng(0)
    n_obs, n_clk = 5000, 24
    r = np.r_[rng.normal(0, 0.3, 2 * n_obs), rng.normal(0, 1.0, 2 * n_clk)]
    s2_obs, s2_clk = schur.noise_variances(r, np.ones_like(r), n_obs, n_clk, n_params=0, click_weight=1.0)
    assert s2_obs == pytest.approx(0.09, rel=0.1)
    assert s2_clk == pytest.approx(1.0 * 48 / 41, rel=0.35)
    r[2 * n_obs :] *= 0.01
    assert schur.noise_variances(r, np.ones_like(r), n_obs, n_clk, 0, 1.0)[1] == s2_obs
