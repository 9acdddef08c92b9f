"""Constrained bundle adjustment (paper Sec. 6) with scipy's sparse least squares.

Unknowns: per camera a pose update (axis-angle applied on the left of the current rotation, and the
translation of ``camera_from_world``; rotation only for cameras whose centre is held) unless the pose is fixed
(anchor cameras, or cameras outside a local window); per camera focal f_px and radial k1, k2 unless the
intrinsics are fixed; optionally principal points and pixel aspect ratios (fy / fx), one per camera or shared by
a group of cameras; per point either a world position (3) or, for points seen by a fixed anchor camera, the depth
along that anchor's ray through its observed pixel (1). Residuals (pixels): feature observations, anchor clicks
(model points, fixed), a weak prior pulling k1, k2 towards 0, optional focal, principal-point and aspect priors.
Robust loss; analytic sparse Jacobian; SciPy's trust-region solver with LSMR steps, or Levenberg-Marquardt with
exact steps from the Schur complement on the camera parameters (``BundleOptions.solver``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from nodes.register.schur import (
    camera_covariance,
    centre_jacobian,
    noise_variances,
    reduced_system,
    rodrigues_batch,
    schur_lm,
    single_thread_blas,
    skew,
)


def undistort_batch(xy_d: np.ndarray, k1: np.ndarray, k2: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Invert radial distortion on (N, 2) normalised coords with per-row k1, k2 (N,)."""
    xy = xy_d.copy()
    for _ in range(iterations):
        r2 = np.sum(xy * xy, axis=1)
        xy = xy_d / (1.0 + k1 * r2 + k2 * r2 * r2)[:, None]
    return xy


@dataclass
class CameraArrays:
    """Per-camera arrays of a bundle adjustment: ``camera_from_world`` (C, 4, 4), intrinsics (C,)."""

    camera_from_world: np.ndarray
    f_px: np.ndarray
    cx_px: np.ndarray
    cy_px: np.ndarray
    k1: np.ndarray
    k2: np.ndarray


@dataclass
class BundleProblem(CameraArrays):
    """Arrays of a bundle adjustment. C cameras, P points, M observations, K clicks.

    ``camera_from_world`` (C, 4, 4); intrinsics arrays (C,); ``points_in_world`` (P, 3);
    ``point_ref_cam`` (P,) anchor camera whose ray carries the point (-1: free xyz) and ``point_ref_px`` (P, 2) the
    pixel of that ray; observations ``obs_cam``, ``obs_point`` (M,) int and ``obs_px`` (M, 2); clicks
    ``click_cam`` (K,), ``click_world`` (K, 3), ``click_px`` (K, 2); ``centre_fixed`` (C,) bool: rotation-only
    pose updates about the current camera centre.
    """

    pose_fixed: np.ndarray
    intrinsics_fixed: np.ndarray
    points_in_world: np.ndarray
    point_fixed: np.ndarray
    point_ref_cam: np.ndarray
    point_ref_px: np.ndarray
    obs_cam: np.ndarray
    obs_point: np.ndarray
    obs_px: np.ndarray
    click_cam: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    click_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    click_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    # (C,) int or None: with refine_principal_point, cameras with the same non-negative id share one principal
    # point (one physical camera); -1 or None: each camera its own.
    pp_group: np.ndarray | None = None
    # (C,) bool or None: cameras whose centre stays where it is (only their rotation moves; e.g. a photo that a
    # rotation homography ties to an anchor's viewpoint).
    centre_fixed: np.ndarray | None = None
    # (C,) pixel aspect ratios fy / fx (v = f * fy_over_fx * y_d + cy), or None: square pixels (1.0).
    fy_over_fx: np.ndarray | None = None
    # (C,) int or None: cameras with free intrinsics and the same non-negative id share one focal and one k1, k2
    # (one physical camera at one zoom setting); -1 or None: each camera its own.
    intr_group: np.ndarray | None = None
    # (K,) standard deviation (px) of each click relative to a user's click (None: 1 each); clicks carried into a
    # photo by image matching are less sure than clicked ones.
    click_sigma_px: np.ndarray | None = None


@dataclass
class BundleOptions:
    loss: str = "soft_l1"
    loss_scale_px: float = 2.0
    refine_distortion: bool = True
    refine_principal_point: bool = False
    # Zero-mean prior on k1 and k2: their standard deviation (dimensionless, despite the name).
    distortion_prior_px: float = 0.05
    # Optional per-camera distortion priors: centres (C, 2) of (k1, k2) and standard deviations (C,); cameras
    # with a NaN sigma take the zero-mean prior above (e.g. a photo that inherits its lens from the photo it was
    # transferred from is held near that lens).
    distortion_prior_centre: np.ndarray | None = None
    distortion_prior_sigma: np.ndarray | None = None
    click_weight: float = 1.0
    max_nfev: int = 50
    ftol: float = 1e-4
    # "trf": SciPy's trust-region reflective with LSMR steps; "schur": Levenberg-Marquardt with iteratively
    # reweighted robust loss (soft_l1 or linear only) and exact steps from the Schur complement on the camera
    # parameters (points eliminated block by block) -- exact steps move weakly determined camera parameters
    # (a shared principal point) that capped LSMR steps hardly move, at a fraction of an exact LSMR's cost.
    solver: str = "trf"
    # Iteration cap of the inner LSMR solve of each trust-region step (None: SciPy's default, min(m, n)); an
    # inexact step is fine for a trust-region method and most of the time is spent there.
    lsmr_maxiter: int | None = None
    # Optional focal prior per camera (C,) px and its standard deviation (C,) px (inf = no prior).
    focal_prior_px: np.ndarray | None = None
    focal_prior_sigma_px: np.ndarray | None = None
    # With refine_principal_point: optional prior on each camera's principal point, centre (C, 2) px (usually
    # the image centre) and standard deviation (C,) px (inf = no prior): the data move it only as far as they
    # support it.
    principal_point_prior_px: np.ndarray | None = None
    principal_point_prior_sigma_px: np.ndarray | None = None
    # Pixel aspect ratio fy / fx, one per principal-point group (pp_group; shared like the principal point), under
    # a prior centred on 1 (square pixels) of standard deviation ``aspect_prior_sigma`` (None = no prior). With an
    # aspect refined, the focal prior applies to the mean focal (fx + fy) / 2.
    refine_aspect: bool = False
    aspect_prior_sigma: float | None = None
    # With the "schur" solver: also estimate each camera centre's covariance (BundleResult.centre_cov_m2) from the
    # reduced normal matrix at the solution, with the noise of the feature residuals and of the clicks each
    # estimated from their own residuals (see noise_variances).
    covariance: bool = False


@dataclass
class BundleResult(CameraArrays):
    """Adjusted arrays (same layout as the problem) and per-observation residual norms (M,) in px."""

    points_in_world: np.ndarray
    obs_error_px: np.ndarray
    click_error_px: np.ndarray
    initial_rms_px: float
    final_rms_px: float
    num_iterations: int
    # Sum of squared pixel residuals of observations and clicks (unweighted by the robust loss) before and after.
    initial_sse_px2: float = float("nan")
    final_sse_px2: float = float("nan")
    # Solver "schur" with principal points refined: Wald statistic of the principal points' offsets from their
    # prior centres, sum over groups of d^T Cov^-1 d (Cov from the reduced normal matrix and the residual
    # variance), and the number of groups; NaN / 0 otherwise.
    principal_point_wald: float = float("nan")
    principal_point_groups: int = 0
    # (C,) adjusted aspect ratios fy / fx (None: the problem's, unchanged), and with refine_aspect and the "schur"
    # solver the Wald statistic of the aspects' offsets from 1 (sum over groups) and the number of groups.
    fy_over_fx: np.ndarray | None = None
    aspect_wald: float = float("nan")
    aspect_groups: int = 0
    # (C, 3, 3) covariance of each camera centre in world units^2 (with BundleOptions.covariance and the "schur"
    # solver; NaN for cameras whose centre does not move: fixed poses, rotation-only updates), or None.
    centre_cov_m2: np.ndarray | None = None


class _Layout:
    def __init__(self, prob: BundleProblem, opts: BundleOptions):
        C = len(prob.f_px)
        P = len(prob.points_in_world)
        self.n_intr = 1 + (2 if opts.refine_distortion else 0)
        idx = 0
        self.pose_col = np.full(C, -1)
        self.rot_only = np.zeros(C, bool) if prob.centre_fixed is None else np.asarray(prob.centre_fixed, bool).copy()
        for c in range(C):
            if not prob.pose_fixed[c]:
                self.pose_col[c] = idx
                idx += 3 if self.rot_only[c] else 6
        self.intr_col = np.full(C, -1)
        ig = np.full(C, -1) if prob.intr_group is None else np.asarray(prob.intr_group, int)
        intr_key = np.where(ig >= 0, ig, -1 - np.arange(C))
        col_of_key: dict[int, int] = {}
        for c in range(C):
            if not prob.intrinsics_fixed[c]:
                k = int(intr_key[c])
                if k not in col_of_key:
                    col_of_key[k] = idx
                    idx += self.n_intr
                self.intr_col[c] = col_of_key[k]
        # One camera per intrinsics column (its first member): priors on shared intrinsics are counted once.
        _, lead = np.unique(np.where(self.intr_col >= 0, self.intr_col, -1), return_index=True)
        self.intr_lead = np.sort(lead[self.intr_col[lead] >= 0])
        # Principal points (two columns) and aspect ratios (one column) per group of cameras with free intrinsics
        # (a camera alone is its own group); pp_col[c] / asp_col[c] = the columns of camera c's group, -1 when not
        # refined.
        self.pp_col = np.full(C, -1)
        self.asp_col = np.full(C, -1)
        self.pp_groups: list[np.ndarray] = []  # member cameras of each group, in column order
        if opts.refine_principal_point or opts.refine_aspect:
            gid = np.full(C, -1) if prob.pp_group is None else np.asarray(prob.pp_group, int)
            key = np.where(gid >= 0, gid, -1 - np.arange(C))
            free = np.nonzero(prob.intrinsics_fixed == 0)[0]
            for g in dict.fromkeys(key[free].tolist()):
                members = free[key[free] == g]
                self.pp_groups.append(members)
                if opts.refine_principal_point:
                    self.pp_col[members] = idx
                    idx += 2
                if opts.refine_aspect:
                    self.asp_col[members] = idx
                    idx += 1
        self.point_col = np.full(P, -1)
        self.point_is_depth = (prob.point_ref_cam >= 0) & ~prob.point_fixed
        self.point_free = ~prob.point_fixed
        for p in range(P):
            if self.point_free[p]:
                self.point_col[p] = idx
                idx += 1 if self.point_is_depth[p] else 3
        self.n = idx


def _cam_from_world(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]


def bundle_adjust(prob: BundleProblem, opts: BundleOptions | None = None) -> BundleResult:
    """Run the constrained bundle adjustment; returns adjusted copies (the problem is not modified).

    Points carried by an anchor ray move along the ray fixed at the start of the call (anchor pose fixed, ray
    from the anchor's current intrinsics); the anchor's own observation of such a point then constrains the
    anchor's intrinsics. Analytic sparse Jacobian.
    """
    opts = opts or BundleOptions()
    lay = _Layout(prob, opts)
    C = len(prob.f_px)
    R0 = prob.camera_from_world[:, :3, :3].copy()
    t0 = prob.camera_from_world[:, :3, 3].copy()
    obs_cam, obs_point, obs_px = prob.obs_cam, prob.obs_point, prob.obs_px
    n_obs, n_clk = len(obs_cam), len(prob.click_cam)
    click_w = np.full(n_clk, float(opts.click_weight))
    if prob.click_sigma_px is not None and n_clk:
        click_w = click_w / np.asarray(prob.click_sigma_px, np.float64)
    distortion_cams = lay.intr_lead if opts.refine_distortion else np.zeros(0, int)
    dist_centre = np.zeros((C, 2))
    dist_sigma = np.full(C, float(opts.distortion_prior_px))
    if opts.distortion_prior_centre is not None and opts.distortion_prior_sigma is not None:
        own = np.isfinite(np.asarray(opts.distortion_prior_sigma, float))
        dist_centre[own] = np.asarray(opts.distortion_prior_centre, float).reshape(C, 2)[own]
        dist_sigma[own] = np.asarray(opts.distortion_prior_sigma, float)[own]
    if opts.focal_prior_px is not None and opts.focal_prior_sigma_px is not None:
        focal_cams = lay.intr_lead[np.isfinite(np.asarray(opts.focal_prior_sigma_px, float)[lay.intr_lead])]
        f_prior = np.asarray(opts.focal_prior_px, float)[focal_cams]
        f_sigma = np.asarray(opts.focal_prior_sigma_px, float)[focal_cams]
    else:
        focal_cams, f_prior, f_sigma = np.zeros(0, int), np.zeros(0), np.ones(0)
    if (
        opts.refine_principal_point
        and opts.principal_point_prior_px is not None
        and opts.principal_point_prior_sigma_px is not None
    ):
        # One prior per principal-point group (that of its first member).
        pp_sig_all = np.broadcast_to(np.asarray(opts.principal_point_prior_sigma_px, float), (C,))
        lead = np.array([m[0] for m in lay.pp_groups], int)
        pp_cams = lead[np.isfinite(pp_sig_all[lead])] if len(lead) else np.zeros(0, int)
        pp_prior = np.asarray(opts.principal_point_prior_px, float).reshape(C, 2)[pp_cams]
        pp_sigma = pp_sig_all[pp_cams]
    else:
        pp_cams, pp_prior, pp_sigma = np.zeros(0, int), np.zeros((0, 2)), np.ones(0)
    a0 = np.ones(C) if prob.fy_over_fx is None else np.asarray(prob.fy_over_fx, float).copy()
    # Aspect priors: one per group (its first member), centred on square pixels.
    if opts.refine_aspect and opts.aspect_prior_sigma is not None and np.isfinite(opts.aspect_prior_sigma):
        asp_cams = np.array([m[0] for m in lay.pp_groups], int)
        asp_sigma = float(opts.aspect_prior_sigma)
    else:
        asp_cams, asp_sigma = np.zeros(0, int), 1.0
    # The focal prior is on (fx + fy) / 2 when an aspect moves (a prior "focal" of a camera with non-square pixels).
    focal_mean = opts.refine_aspect or bool(np.any(a0 != 1.0))

    # Anchor rays (world) and initial depths.
    depth_pts = np.nonzero(lay.point_is_depth)[0]
    rc = prob.point_ref_cam[depth_pts]
    ray_origin = np.zeros((len(prob.points_in_world), 3))
    ray_dir = np.zeros((len(prob.points_in_world), 3))
    x0 = np.zeros(lay.n)
    if len(depth_pts):
        xy_d = (prob.point_ref_px[depth_pts] - np.stack([prob.cx_px[rc], prob.cy_px[rc]], axis=1)) / np.stack(
            [prob.f_px[rc], prob.f_px[rc] * a0[rc]], axis=1
        )
        xy = undistort_batch(xy_d, prob.k1[rc], prob.k2[rc])
        Rw = np.transpose(R0[rc], (0, 2, 1))
        ray_dir[depth_pts] = np.einsum("nij,nj->ni", Rw, np.c_[xy, np.ones(len(xy))])
        ray_origin[depth_pts] = -np.einsum("nij,nj->ni", Rw, t0[rc])
        pc = _cam_from_world(prob.camera_from_world[rc], prob.points_in_world[depth_pts])
        x0[lay.point_col[depth_pts]] = np.maximum(pc[:, 2], 1e-9)
    for c in lay.intr_lead:
        members = lay.intr_col == lay.intr_col[c]  # the cameras sharing these intrinsics start from their mean
        vals = [float(np.mean(prob.f_px[members]))]
        if opts.refine_distortion:
            vals += [float(np.mean(prob.k1[members])), float(np.mean(prob.k2[members]))]
        x0[lay.intr_col[c] : lay.intr_col[c] + lay.n_intr] = vals
    for c in range(C):
        if lay.pose_col[c] >= 0 and not lay.rot_only[c]:
            x0[lay.pose_col[c] + 3 : lay.pose_col[c] + 6] = t0[c]
    for members in lay.pp_groups:
        if lay.pp_col[members[0]] >= 0:
            x0[lay.pp_col[members[0]]] = float(np.mean(prob.cx_px[members]))
            x0[lay.pp_col[members[0]] + 1] = float(np.mean(prob.cy_px[members]))
        if lay.asp_col[members[0]] >= 0:
            x0[lay.asp_col[members[0]]] = float(np.mean(a0[members]))
    centre0 = -np.einsum("nji,nj->ni", R0, t0)  # camera centres (C, 3) world
    free_xyz = np.nonzero(lay.point_free & ~lay.point_is_depth)[0]
    if len(free_xyz):
        cols = lay.point_col[free_xyz]
        for k in range(3):
            x0[cols + k] = prob.points_in_world[free_xyz, k]

    def unpack(x: np.ndarray):
        T = prob.camera_from_world.copy()
        f, k1, k2 = prob.f_px.copy(), prob.k1.copy(), prob.k2.copy()
        cx, cy, a = prob.cx_px.copy(), prob.cy_px.copy(), a0.copy()
        pc_ = np.nonzero(lay.pose_col >= 0)[0]
        if len(pc_):
            cols = lay.pose_col[pc_]
            w = np.stack([x[cols], x[cols + 1], x[cols + 2]], axis=1)
            T[pc_, :3, :3] = rodrigues_batch(w) @ R0[pc_]
            six = ~lay.rot_only[pc_]
            c6, col6 = pc_[six], cols[six]
            T[c6, :3, 3] = np.stack([x[col6 + 3], x[col6 + 4], x[col6 + 5]], axis=1)
            c3 = pc_[~six]
            T[c3, :3, 3] = -np.einsum("nij,nj->ni", T[c3, :3, :3], centre0[c3])
        ic = np.nonzero(lay.intr_col >= 0)[0]
        if len(ic):
            cols = lay.intr_col[ic]
            f[ic] = x[cols]
            if opts.refine_distortion:
                k1[ic], k2[ic] = x[cols + 1], x[cols + 2]
        pc = np.nonzero(lay.pp_col >= 0)[0]
        if len(pc):
            cx[pc], cy[pc] = x[lay.pp_col[pc]], x[lay.pp_col[pc] + 1]
        ac = np.nonzero(lay.asp_col >= 0)[0]
        if len(ac):
            a[ac] = x[lay.asp_col[ac]]
        pts = prob.points_in_world.copy()
        if len(free_xyz):
            cols = lay.point_col[free_xyz]
            pts[free_xyz] = np.stack([x[cols], x[cols + 1], x[cols + 2]], axis=1)
        if len(depth_pts):
            d = x[lay.point_col[depth_pts]]
            pts[depth_pts] = ray_origin[depth_pts] + d[:, None] * ray_dir[depth_pts]
        return T, f, k1, k2, cx, cy, a, pts

    def project_full(T, f, k1, k2, cx, cy, a, cams, X):
        """Pixels (M, 2), camera points (M, 3), and pieces for the Jacobian."""
        p = _cam_from_world(T[cams], X)
        z = np.where(p[:, 2] > 1e-9, p[:, 2], 1e-9)
        # Bounded normalised coordinates: trial steps may throw points behind or far off a camera.
        xn, yn = np.clip(p[:, 0] / z, -1e3, 1e3), np.clip(p[:, 1] / z, -1e3, 1e3)
        r2 = xn * xn + yn * yn
        D = 1 + k1[cams] * r2 + k2[cams] * r2 * r2
        u = f[cams] * xn * D + cx[cams]
        v = f[cams] * a[cams] * yn * D + cy[cams]
        return np.stack([u, v], axis=1), p, z, xn, yn, r2, D

    def prior_residuals(f, k1, k2, cx, cy, a) -> np.ndarray:
        """Raw prior residuals (distortion k1 then k2, focal, principal points, aspects), in sigmas."""
        parts = []
        if len(distortion_cams):
            dc, ds = dist_centre[distortion_cams], dist_sigma[distortion_cams]
            parts.append(np.concatenate([(k1[distortion_cams] - dc[:, 0]) / ds, (k2[distortion_cams] - dc[:, 1]) / ds]))
        if len(focal_cams):
            f_eff = f[focal_cams] * (1 + a[focal_cams]) / 2 if focal_mean else f[focal_cams]
            parts.append((f_eff - f_prior) / f_sigma)
        if len(pp_cams):
            parts.append(((np.stack([cx[pp_cams], cy[pp_cams]], axis=1) - pp_prior) / pp_sigma[:, None]).ravel())
        if len(asp_cams):
            parts.append((a[asp_cams] - 1.0) / asp_sigma)
        return np.concatenate(parts) if parts else np.zeros(0)

    def residuals(x: np.ndarray) -> np.ndarray:
        T, f, k1, k2, cx, cy, a, pts = unpack(x)
        parts = [(project_full(T, f, k1, k2, cx, cy, a, obs_cam, pts[obs_point])[0] - obs_px).ravel()]
        if n_clk:
            r_clk = project_full(T, f, k1, k2, cx, cy, a, prob.click_cam, prob.click_world)[0] - prob.click_px
            parts.append((click_w[:, None] * r_clk).ravel())
        parts.append(prior_residuals(f, k1, k2, cx, cy, a))
        return np.concatenate(parts)

    def _centre_covariance(x: np.ndarray, r: np.ndarray, w: np.ndarray, system: tuple) -> np.ndarray:
        """(C, 3, 3) camera-centre covariances at the solution ``x`` with residuals ``r``, IRLS weights ``w`` and
        their reduced system (NaN where the centre does not move)."""
        m = 2 * (n_obs + n_clk)
        s2_obs, s2_clk = noise_variances(r, w, n_obs, n_clk, lay.n, np.repeat(click_w, 2))
        # Residual variances: the features' and the (weighted) clicks' as estimated; priors are in sigmas.
        var = np.ones_like(r)
        var[: 2 * n_obs] = s2_obs
        var[2 * n_obs : m] = s2_clk * np.repeat(click_w, 2) ** 2
        with single_thread_blas():
            cov = camera_covariance(system, w, var)
        out = np.full((C, 3, 3), np.nan)
        for c in np.nonzero((lay.pose_col >= 0) & ~lay.rot_only)[0]:
            col = lay.pose_col[c]
            Jc = centre_jacobian(x[col : col + 3], R0[c], x[col + 3 : col + 6])
            out[c] = Jc @ cov[col : col + 6, col : col + 6] @ Jc.T
        return out

    n_res = 2 * (n_obs + n_clk) + 2 * len(distortion_cams) + len(focal_cams) + 2 * len(pp_cams) + len(asp_cams)

    def jac_block(T, f, k1, k2, a, cams, X, weight):
        """Rows/cols/vals of the Jacobian of 2 residuals per (cams, X) w.r.t. pose, intrinsics, aspect; plus
        dpix/dX. ``weight``: a scalar or one per residual pair (M,)."""
        wv = np.asarray(weight, np.float64)
        w3, w2 = (wv.reshape(-1, 1, 1), wv.reshape(-1, 1)) if wv.ndim else (wv, wv)
        _, p, z, xn, yn, r2, D = project_full(T, f, k1, k2, prob.cx_px, prob.cy_px, a, cams, X)
        fc = f[cams]
        ac = a[cams]
        dD = k1[cams] + 2 * k2[cams] * r2  # dD/d(r2)
        # d(u,v)/d(xn,yn)
        J_uv_xy = np.zeros((len(cams), 2, 2))
        J_uv_xy[:, 0, 0] = fc * (D + xn * dD * 2 * xn)
        J_uv_xy[:, 0, 1] = fc * xn * dD * 2 * yn
        J_uv_xy[:, 1, 0] = fc * ac * yn * dD * 2 * xn
        J_uv_xy[:, 1, 1] = fc * ac * (D + yn * dD * 2 * yn)
        J_xy_p = np.zeros((len(cams), 2, 3))
        J_xy_p[:, 0, 0] = 1 / z
        J_xy_p[:, 0, 2] = -xn / z
        J_xy_p[:, 1, 1] = 1 / z
        J_xy_p[:, 1, 2] = -yn / z
        J_uv_p = w3 * (J_uv_xy @ J_xy_p)  # (M, 2, 3)
        # Rotation columns: p = R X + t with R = exp(w) R0, so dp/dw = -[R X]x; for a fixed centre C,
        # p = R (X - C) and dp/dw = -[p]x. Translation columns (unused for fixed centres): identity.
        rot_only = lay.rot_only[cams]
        Rp = np.where(rot_only[:, None], p, p - T[cams, :3, 3])
        J_pose = np.concatenate([J_uv_p @ -skew(Rp), J_uv_p], axis=2)  # (M, 2, 6)
        J_intr = [w2 * np.stack([xn * D, ac * yn * D], axis=1)]
        if opts.refine_distortion:
            J_intr += [w2 * fc[:, None] * np.stack([xn * r2, ac * yn * r2], axis=1)]
            J_intr += [w2 * fc[:, None] * np.stack([xn * r2 * r2, ac * yn * r2 * r2], axis=1)]
        J_intr_a = np.stack(J_intr, axis=2)  # (M, 2, n_intr)
        J_X = J_uv_p @ T[cams, :3, :3]  # (M, 2, 3)
        J_asp = w3 * np.stack([np.zeros_like(yn), fc * yn * D], axis=1)[:, :, None]  # (M, 2, 1)
        return J_pose, J_intr_a, J_X, J_asp

    def emit(rows, cols, vals, row0, col_start, J):
        """Add dense blocks J (M, 2, W) at rows 2*row0.. and columns col_start (M,) (skipping col_start < 0)."""
        ok = col_start >= 0
        if not ok.any():
            return
        M, _, W = J.shape
        r = (2 * row0[ok])[:, None, None] + np.arange(2)[None, :, None] + np.zeros((1, 1, W), int)
        c = col_start[ok][:, None, None] + np.zeros((1, 2, 1), int) + np.arange(W)[None, None, :]
        rows.append(r.ravel())
        cols.append(c.ravel())
        vals.append(J[ok].ravel())

    def emit_pose(rows, cols, vals, row0, cams, J_pose):
        """Pose blocks: 6 columns, or the 3 rotation columns of fixed-centre cameras."""
        ro = lay.rot_only[cams]
        col = lay.pose_col[cams]
        emit(rows, cols, vals, row0[~ro], col[~ro], J_pose[~ro])
        if ro.any():
            emit(rows, cols, vals, row0[ro], col[ro], np.ascontiguousarray(J_pose[ro][:, :, :3]))

    def jacobian(x: np.ndarray) -> sp.csr_matrix:
        T, f, k1, k2, cx, cy, a, pts = unpack(x)
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        if n_obs:
            J_pose, J_intr, J_X, J_asp = jac_block(T, f, k1, k2, a, obs_cam, pts[obs_point], 1.0)
            ar = np.arange(n_obs)
            emit_pose(rows, cols, vals, ar, obs_cam, J_pose)
            emit(rows, cols, vals, ar, lay.intr_col[obs_cam], J_intr)
            emit(rows, cols, vals, ar, lay.pp_col[obs_cam], np.broadcast_to(np.eye(2), (n_obs, 2, 2)))
            emit(rows, cols, vals, ar, lay.asp_col[obs_cam], J_asp)
            is_depth = lay.point_is_depth[obs_point]
            free = ~is_depth
            emit(rows, cols, vals, ar[free], lay.point_col[obs_point[free]], J_X[free])
            if is_depth.any():
                J_d = J_X[is_depth] @ ray_dir[obs_point[is_depth]][:, :, None]
                emit(rows, cols, vals, ar[is_depth], lay.point_col[obs_point[is_depth]], J_d)
        if n_clk:
            J_pose, J_intr, _, J_asp = jac_block(T, f, k1, k2, a, prob.click_cam, prob.click_world, click_w)
            ar = np.arange(n_clk) + n_obs
            emit_pose(rows, cols, vals, ar, prob.click_cam, J_pose)
            emit(rows, cols, vals, ar, lay.intr_col[prob.click_cam], J_intr)
            J_pp = click_w[:, None, None] * np.eye(2)[None]
            emit(rows, cols, vals, ar, lay.pp_col[prob.click_cam], J_pp)
            emit(rows, cols, vals, ar, lay.asp_col[prob.click_cam], J_asp)
        if len(distortion_cams):
            base = 2 * (n_obs + n_clk)
            nd = len(distortion_cams)
            ic = lay.intr_col[distortion_cams]
            rows += [base + np.arange(nd), base + nd + np.arange(nd)]
            cols += [ic + 1, ic + 2]
            vals += [1 / dist_sigma[distortion_cams]] * 2
        if len(focal_cams):
            base = 2 * (n_obs + n_clk) + 2 * len(distortion_cams)
            rows.append(base + np.arange(len(focal_cams)))
            cols.append(lay.intr_col[focal_cams])
            vals.append((1 + a[focal_cams]) / 2 / f_sigma if focal_mean else 1 / f_sigma)
            with_asp = lay.asp_col[focal_cams] >= 0
            if focal_mean and with_asp.any():
                rows.append(base + np.nonzero(with_asp)[0])
                cols.append(lay.asp_col[focal_cams[with_asp]])
                vals.append(f[focal_cams[with_asp]] / 2 / f_sigma[with_asp])
        if len(pp_cams):
            base = 2 * (n_obs + n_clk) + 2 * len(distortion_cams) + len(focal_cams)
            pc = lay.pp_col[pp_cams]
            rows += [base + 2 * np.arange(len(pp_cams)), base + 2 * np.arange(len(pp_cams)) + 1]
            cols += [pc, pc + 1]
            vals += [1 / pp_sigma, 1 / pp_sigma]
        if len(asp_cams):
            base = 2 * (n_obs + n_clk) + 2 * len(distortion_cams) + len(focal_cams) + 2 * len(pp_cams)
            rows.append(base + np.arange(len(asp_cams)))
            cols.append(lay.asp_col[asp_cams])
            vals.append(np.full(len(asp_cams), 1 / asp_sigma))
        if not rows:
            return sp.csr_matrix((n_res, lay.n))
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_res, lay.n))

    r0 = residuals(x0)
    init_rms = float(np.sqrt(np.mean(r0[: 2 * n_obs] ** 2) * 2)) if n_obs else 0.0
    nfev = 0
    x = x0
    pp_wald, pp_groups = float("nan"), 0
    asp_wald, asp_groups = float("nan"), 0
    centre_cov: np.ndarray | None = None
    if lay.n > 0 and n_res >= lay.n and opts.solver == "schur" and opts.loss in ("soft_l1", "linear"):
        n_cam_cols = int(lay.point_col[lay.point_free].min()) if lay.point_free.any() else lay.n
        free_pts = np.nonzero(lay.point_free)[0]
        starts = lay.point_col[free_pts] - n_cam_cols
        sizes = np.where(lay.point_is_depth[free_pts], 1, 3)
        with single_thread_blas():
            x, nfev = schur_lm(
                residuals,
                jacobian,
                x0,
                n_cam_cols,
                starts,
                sizes,
                opts.loss,
                opts.loss_scale_px,
                opts.max_nfev,
                opts.ftol,
            )
        want_pp = opts.refine_principal_point and opts.principal_point_prior_px is not None
        want_wald = bool(len(lay.pp_groups)) and (want_pp or opts.refine_aspect)
        if opts.covariance or want_wald:
            # One reduced system at the solution serves the centre covariances and the Wald statistics.
            r_fin = residuals(x)
            w_fin = np.ones_like(r_fin)
            if opts.loss == "soft_l1":
                w_fin = 1 / np.sqrt(1 + (r_fin / opts.loss_scale_px) ** 2)
            with single_thread_blas():
                system = reduced_system(jacobian(x), w_fin, n_cam_cols, starts, sizes)
        if opts.covariance:
            centre_cov = _centre_covariance(x, r_fin, w_fin, system)
        if want_wald:
            info = system[-1]  # inverse covariance of the camera unknowns up to the noise variance
            m = 2 * (n_obs + n_clk)
            s2 = float(np.sum(w_fin[:m] * r_fin[:m] ** 2)) / max(m - lay.n, 1)
            try:
                cov = np.linalg.pinv(info) * s2
                if want_pp:
                    centre_px = np.asarray(opts.principal_point_prior_px, float).reshape(C, 2)
                    wald = 0.0
                    for members in lay.pp_groups:
                        col = lay.pp_col[members[0]]
                        d = x[col : col + 2] - centre_px[members[0]]
                        wald += float(d @ np.linalg.solve(cov[col : col + 2, col : col + 2], d))
                    pp_wald, pp_groups = wald, len(lay.pp_groups)
                if opts.refine_aspect:
                    cols_a = np.array([lay.asp_col[m_[0]] for m_ in lay.pp_groups], int)
                    var_a = np.diag(cov)[cols_a]
                    asp_wald = float(np.sum((x[cols_a] - 1.0) ** 2 / np.maximum(var_a, 1e-300)))
                    asp_groups = len(cols_a)
            except np.linalg.LinAlgError:
                pass
    elif lay.n > 0 and n_res >= lay.n:
        # x_scale="jac" gives a parameter whose Jacobian column is nearly zero (a camera's k2 with every point near
        # the image centre) a huge scale; a trial step along it can overflow the step norm. The trust region then
        # rejects that step and shrinks, so the overflow is harmless and not reported.
        with single_thread_blas(), np.errstate(over="ignore"):
            sol = least_squares(
                residuals,
                x0,
                jac=jacobian,
                method="trf",
                tr_solver="lsmr",
                tr_options={} if opts.lsmr_maxiter is None else {"maxiter": opts.lsmr_maxiter},
                loss=opts.loss,
                f_scale=opts.loss_scale_px,
                x_scale="jac",
                max_nfev=opts.max_nfev,
                ftol=opts.ftol,
                xtol=1e-8,
            )
        x, nfev = sol.x, int(sol.nfev)
    T, f, k1, k2, cx, cy, a, pts = unpack(x)
    proj, p_all, *_ = project_full(T, f, k1, k2, cx, cy, a, prob.obs_cam, pts[prob.obs_point])
    obs_err = np.linalg.norm(proj - prob.obs_px, axis=1)
    obs_err[p_all[:, 2] <= 0] = np.inf
    clk_err = np.zeros(n_clk)
    if n_clk:
        clk_err = np.linalg.norm(
            project_full(T, f, k1, k2, cx, cy, a, prob.click_cam, prob.click_world)[0] - prob.click_px, axis=1
        )
    fin = np.isfinite(obs_err)
    final_rms = float(np.sqrt(np.mean(obs_err[fin] ** 2))) if fin.any() else 0.0
    r0_px = r0[: 2 * (n_obs + n_clk)].copy()
    r0_px[2 * n_obs :] /= np.where(np.repeat(click_w, 2) > 0, np.repeat(click_w, 2), 1.0)
    init_sse = float(np.sum(np.nan_to_num(r0_px, nan=0.0, posinf=0.0, neginf=0.0) ** 2))
    final_sse = float(np.sum(obs_err[fin] ** 2) + np.sum(clk_err[np.isfinite(clk_err)] ** 2))
    return BundleResult(
        T,
        f,
        cx,
        cy,
        k1,
        k2,
        pts,
        obs_err,
        clk_err,
        init_rms,
        final_rms,
        nfev,
        init_sse,
        final_sse,
        pp_wald,
        pp_groups,
        a,
        asp_wald,
        asp_groups,
        centre_cov,
    )
