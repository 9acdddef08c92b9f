"""Bundle adjustment of a reconstruction (constrained, anchors held), the final anchor release and the accuracy
target.
"""

from __future__ import annotations

from collections.abc import Callable

import msgspec
import numpy as np

from constructaide import camera as cam
from constructaide.anchorsolve import DegenerateAnchors
from nodes.register.bundle import BundleOptions, BundleProblem, bundle_adjust
from nodes.register.config import MapperConfig
from nodes.register.mapper import register_anchor
from nodes.register.recon import (
    Clicks,
    Reconstruction,
    flat_obs,
    focal_prior,
    focal_sigma_frac,
    matched_track_count,
    obs_pixels,
    obs_threshold_per_image,
    principal_point_groups,
    restore,
    snapshot,
)
from nodes.register.triangulation import drop_runaway_points, triangulate_tracks
from schemas.messages import Intrinsics


def bundle(
    recon: Reconstruction,
    cfg: MapperConfig,
    window: list[int] | None = None,
    fixed_anchors: set[int] | None = None,
    covariance: bool = False,
) -> dict[str, float]:
    """Constrained bundle adjustment over all registered images, or a local one where only images in ``window``
    (and the points they see) move. Then drops observations beyond threshold and points left with < 2 views.
    ``covariance`` (with ``cfg.ba_solver == "schur"``): set each moved camera's ``centre_sigma_m``.
    An anchor whose clicks the adjustment moved further than ``cfg.max_anchor_click_drift_px`` beyond its click
    solve's RMS gets its lens held at that solve's (:func:`drifted_anchors`) and the adjustment is redone.
    Returns stats (initial/final rms px, observations removed, points, observations, initial/final total squared
    error of features and clicks px^2 and the number of those residuals)."""
    watched = _drift_candidates(recon, cfg, window)
    snap = snapshot(recon) if watched else None
    stats = _bundle(recon, cfg, window, fixed_anchors, covariance)
    drifted = drifted_anchors(recon, cfg, watched) if snap is not None and stats else []
    if not drifted:
        return stats
    assert snap is not None
    restore(recon, snap)
    for i in drifted:
        im = recon.images[i]
        assert im.anchor is not None
        im.lens_held = True
        im.intrinsics = im.anchor.intrinsics
        im.message += "; lens held at the clicks' solve (the tracks pulled the clicks off)"
    return _bundle(recon, cfg, window, fixed_anchors, covariance)


def _drift_candidates(recon: Reconstruction, cfg: MapperConfig, window: list[int] | None) -> list[int]:
    """Registered anchors (of ``window``; None: all) with accepted clicks and a lens not yet held: those an
    adjustment could pull off their clicks (none when ``cfg.max_anchor_click_drift_px`` is None)."""
    if cfg.max_anchor_click_drift_px is None:
        return []
    out = []
    for i in recon.registered_indices() if window is None else window:
        im = recon.images[i]
        clicks = im.accepted_clicks
        if not (im.lens_held or im.anchor is None or clicks is None or im.world_from_camera is None) and len(clicks[0]):
            out.append(i)
    return out


def drifted_anchors(recon: Reconstruction, cfg: MapperConfig, anchors: list[int] | None = None) -> list[int]:
    """Of ``anchors`` (None: every registered anchor with clicks and a free lens), those whose accepted clicks now
    lie further from their points (RMS px) than their click solve left them plus ``cfg.max_anchor_click_drift_px``."""
    out = []
    for i in _drift_candidates(recon, cfg, anchors):
        im = recon.images[i]
        assert im.anchor is not None and im.accepted_clicks is not None and cfg.max_anchor_click_drift_px is not None
        rms = cam.rms_click_error_px(im.camera, im.pose, *im.accepted_clicks)
        if not rms <= im.anchor.rms_px + cfg.max_anchor_click_drift_px:
            out.append(i)
    return out


def _bundle(
    recon: Reconstruction,
    cfg: MapperConfig,
    window: list[int] | None,
    fixed_anchors: set[int] | None,
    covariance: bool,
) -> dict[str, float]:
    reg = recon.registered_indices()
    if not reg:
        return {}
    cam_of = {i: c for c, i in enumerate(reg)}
    movable = set(reg if window is None else [i for i in window if i in cam_of])
    anchors = {i for i in reg if recon.images[i].status == "anchor"} if cfg.fix_anchor_poses else set()
    if fixed_anchors is not None:
        anchors = {i for i in fixed_anchors if i in cam_of}
    tri = np.nonzero(np.all(np.isfinite(recon.points), axis=1))[0]
    n_img = len(recon.images)
    cam_arr = -np.ones(n_img, dtype=np.int64)
    cam_arr[reg] = np.arange(len(reg))
    movable_mask = np.zeros(n_img, bool)
    movable_mask[list(movable)] = True
    anchor_mask = np.zeros(n_img, bool)
    anchor_mask[list(anchors)] = True
    # Observations of triangulated tracks in registered images (flat, in each track's dict order).
    o_t, o_i, o_f = flat_obs(recon, tri)
    on_reg = cam_arr[o_i] >= 0 if len(o_i) else np.zeros(0, bool)
    o_t, o_i, o_f = o_t[on_reg], o_i[on_reg], o_f[on_reg]
    # Usable tracks: >= 2 registered views and (in a window) at least one movable view.
    n_tr = len(recon.track_obs)
    views_per_track = np.bincount(o_t, minlength=n_tr)
    usable_mask = views_per_track >= 2
    if window is not None:
        usable_mask &= np.bincount(o_t, weights=movable_mask[o_i], minlength=n_tr) > 0
    usable_tracks = np.nonzero(usable_mask)[0]
    # Points in the adjustment: per image, its longest tracks (up to ba_points_per_image); the others are
    # re-triangulated from the adjusted cameras afterwards.
    sel_u = usable_mask[o_t]
    u_t, u_i = o_t[sel_u], o_i[sel_u]
    if cfg.ba_points_per_image and len(usable_tracks) > cfg.ba_points_per_image * max(1, len(movable)):
        order = np.lexsort((u_t, -views_per_track[u_t], u_i))
        img_sorted = u_i[order]
        start = np.searchsorted(img_sorted, img_sorted, side="left")
        rank = np.arange(len(order)) - start
        chosen_mask = np.zeros(n_tr, bool)
        chosen_mask[u_t[order][rank < cfg.ba_points_per_image]] = True
        left_out = usable_tracks[~chosen_mask[usable_tracks]].tolist()
    else:
        chosen_mask = usable_mask
        left_out = []
    pt_arr = np.nonzero(chosen_mask)[0]
    pt_list = pt_arr.tolist()
    point_of_track = -np.ones(n_tr, dtype=np.int64)
    point_of_track[pt_arr] = np.arange(len(pt_arr))
    sel_c = chosen_mask[o_t]
    obs_track_a, obs_img_a, obs_feat_a = o_t[sel_c], o_i[sel_c], o_f[sel_c]
    obs_p_a = point_of_track[obs_track_a]
    obs_x_a = obs_pixels(recon, obs_img_a, obs_feat_a)
    # Reference anchor ray of each point: its first observation (dict order) in a fixed anchor.
    ref_cam = -np.ones(len(pt_arr), dtype=np.int64)
    ref_px = np.zeros((len(pt_arr), 2))
    is_anc = anchor_mask[obs_img_a]
    if is_anc.any():
        rows = np.nonzero(is_anc)[0]
        _, first = np.unique(obs_p_a[rows], return_index=True)
        r = rows[first]
        ref_cam[obs_p_a[r]] = cam_arr[obs_img_a[r]]
        ref_px[obs_p_a[r]] = obs_x_a[r]
    obs_c = cam_arr[obs_img_a]
    obs_track, obs_img = obs_track_a, obs_img_a
    intr = [recon.images[i].camera for i in reg]
    click_c, click_w, click_x = [], [], []
    click_s: list[float] = []
    for i in reg:
        im = recon.images[i]
        if im.clicks is not None:
            keep = im.click_inliers if im.click_inliers is not None else np.ones(len(im.clicks[0]), bool)
            click_c += [cam_of[i]] * int(keep.sum())
            click_w.append(im.clicks[1][keep])
            click_x.append(im.clicks[0][keep])
            click_s += [im.click_sigma_px] * int(keep.sum())
    point_ref = ref_cam
    # In a local window, points fixed when they are not seen by a movable image (already filtered), anchors'
    # rays are used only for movable anchors.
    pose_fixed = np.array([(i in anchors) or (i not in movable) for i in reg])
    centre_fixed = np.array([recon.images[i].centre_source in anchors for i in reg])
    intr_fixed = np.array([i not in movable or recon.images[i].lens_held for i in reg])
    prob = BundleProblem(
        camera_from_world=np.stack([cam.invert_rigid(recon.images[i].pose) for i in reg]),
        f_px=np.array([x.f_px for x in intr]),
        cx_px=np.array([x.cx_px for x in intr]),
        cy_px=np.array([x.cy_px for x in intr]),
        k1=np.array([x.k1 for x in intr]),
        k2=np.array([x.k2 for x in intr]),
        fy_over_fx=np.array([x.fy_over_fx for x in intr]),
        pose_fixed=pose_fixed,
        intrinsics_fixed=intr_fixed,
        points_in_world=recon.points[pt_list] if pt_list else np.zeros((0, 3)),
        point_fixed=recon.point_from_model[pt_arr].copy(),
        point_ref_cam=np.where(point_ref >= 0, point_ref, -1) if len(point_ref) else np.zeros(0, int),
        point_ref_px=ref_px,
        obs_cam=obs_c,
        obs_point=obs_p_a,
        obs_px=obs_x_a,
        click_cam=np.array(click_c, int),
        click_world=np.vstack(click_w) if click_w else np.zeros((0, 3)),
        click_px=np.vstack(click_x) if click_x else np.zeros((0, 2)),
        click_sigma_px=np.array(click_s, np.float64),
        centre_fixed=centre_fixed,
        pp_group=principal_point_groups(recon, reg) if cfg.share_principal_point else None,
        intr_group=principal_point_groups(recon, reg) if cfg.share_intrinsics else None,
    )
    # Focal priors: the external ones (user / EXIF) only. A focal solved from an image's clicks is not a prior:
    # the clicks are residuals of this adjustment already (counting them twice pinned a focal that absorbed
    # model error, e.g. an off-centre principal point, at the user's tight sigma).
    reg_ims = [recon.images[i] for i in reg]
    f_prior = np.array([focal_prior(im, cfg) for im in reg_ims])
    sigma = np.array([focal_sigma_frac(recon.images[i], cfg) for i in reg]) * f_prior
    d_centre = np.zeros((len(reg), 2))
    d_sigma = np.full(len(reg), np.nan)
    for c, i in enumerate(reg):
        src = recon.images[i].lens_source
        if src is not None and recon.images[src].intrinsics is not None:
            d_centre[c] = (recon.images[src].camera.k1, recon.images[src].camera.k2)
            d_sigma[c] = cfg.inherited_distortion_sigma
    opts = BundleOptions(
        distortion_prior_centre=d_centre,
        distortion_prior_sigma=d_sigma,
        focal_prior_px=f_prior,
        focal_prior_sigma_px=sigma,
        loss_scale_px=cfg.loss_scale_px,
        refine_distortion=cfg.refine_distortion,
        refine_principal_point=cfg.refine_principal_point,
        principal_point_prior_px=np.array([[(im.width_px - 1) / 2, (im.height_px - 1) / 2] for im in reg_ims]),
        principal_point_prior_sigma_px=np.array([im.width_px for im in reg_ims], float)
        * (cfg.principal_point_sigma_frac if cfg.principal_point_sigma_frac is not None else np.inf),
        max_nfev=cfg.ba_max_nfev,
        lsmr_maxiter=cfg.ba_lsmr_maxiter,
        solver=cfg.ba_solver,
        refine_aspect=cfg.refine_aspect,
        aspect_prior_sigma=cfg.aspect_sigma,
        covariance=covariance,
    )
    res = bundle_adjust(prob, opts)
    lim = cfg.max_abs_distortion
    moved = np.array([i in movable for i in reg])
    broken = moved & ~((res.f_px > 0) & (np.abs(res.k1) <= lim) & (np.abs(res.k2) <= lim))
    if broken.any() or not np.isfinite(res.final_rms_px):
        # A camera's lens went implausible (outliers a robust loss did not hold): the adjustment is not applied.
        return {"rejected": 1.0}
    if res.centre_cov_m2 is not None:
        sig = np.sqrt(np.einsum("cii->c", res.centre_cov_m2))
        for c, i in enumerate(reg):
            recon.images[i].centre_sigma_m = float(sig[c])
    for c, i in enumerate(reg):
        if i not in movable:
            continue
        im = recon.images[i]
        im.intrinsics = Intrinsics(
            width_px=im.width_px,
            height_px=im.height_px,
            f_px=float(res.f_px[c]),
            cx_px=float(res.cx_px[c]),
            cy_px=float(res.cy_px[c]),
            k1=float(res.k1[c]),
            k2=float(res.k2[c]),
            fy_over_fx=float(res.fy_over_fx[c]) if res.fy_over_fx is not None else im.camera.fy_over_fx,
        )
        if i not in anchors:
            im.world_from_camera = cam.invert_rigid(res.camera_from_world[c])
    if pt_list:
        recon.points[pt_list] = res.points_in_world
    # Outlier observations.
    thr_img = obs_threshold_per_image(recon, cfg)
    e_all = res.obs_error_px
    drop = ~np.isfinite(e_all) | (e_all > thr_img[obs_img])
    removed = int(drop.sum())
    for t, i in zip(obs_track[drop].tolist(), obs_img[drop].tolist(), strict=True):
        f = recon.track_obs[t].pop(i, None)
        if f is not None:
            recon.feature_track[i][f] = -1
    # Points left with < 2 registered views (views outside the adjustment count too).
    if len(pt_arr):
        remaining = views_per_track[pt_arr] - np.bincount(obs_p_a[drop], minlength=len(pt_arr))
        lost = pt_arr[(remaining < 2) & ~recon.point_from_model[pt_arr]]
        recon.points[lost] = np.nan
        drop_runaway_points(recon, pt_arr[~recon.point_from_model[pt_arr]])
    if left_out:
        triangulate_tracks(recon, cfg, retriangulate=True, only=left_out)
    keep = ~drop
    n_keep = np.bincount(obs_img[keep], minlength=n_img)
    sq_keep = np.bincount(obs_img[keep], weights=e_all[keep] ** 2, minlength=n_img)
    for i in reg:
        if i in movable and n_keep[i]:
            im = recon.images[i]
            if im.status != "anchor":
                im.num_inliers = int(n_keep[i])
            im.rms_px = float(np.sqrt(sq_keep[i] / n_keep[i]))
    return {
        "initial_rms_px": res.initial_rms_px,
        "final_rms_px": res.final_rms_px,
        "removed_observations": float(removed),
        "points": float(len(pt_list)),
        "observations": float(len(obs_img)),
        "initial_sse_px2": res.initial_sse_px2,
        "final_sse_px2": res.final_sse_px2,
        "residuals": float(2 * (len(obs_img) + len(prob.click_cam))),
        "principal_point_wald": res.principal_point_wald,
        "principal_point_groups": float(res.principal_point_groups),
        "aspect_wald": res.aspect_wald,
        "aspect_groups": float(res.aspect_groups),
        "iterations": float(res.num_iterations),
    }


ANCHOR_RELEASE_THRESHOLD = 9.0


def release_anchors_if_significant(recon: Reconstruction, cfg: MapperConfig) -> float:
    """One bundle adjustment with the well-tracked anchors' poses free (held by their clicks, like the other
    cameras by their tracks) and the principal points and pixel aspect ratios refined (shared per camera, under
    their priors), kept when the data support it; otherwise the fixed-anchor solution is restored.

    An anchor's pose is solved from a dozen clicks under the centred-principal-point, square-pixel model; a real
    camera whose principal point is off centre (fountain-P11: 22 px) or whose pixels are not square (fountain-P11:
    fy / fx = 1.0017), or click noise, leaves a pose error that a fixed anchor hands on to every image registered
    from it. Anchors observing fewer than ``release_min_observations`` triangulated points stay fixed (their tracks
    cannot check their clicks). The principal points (2 per group) and the aspect ratios (1 per group) stay refined
    only when their offsets from the centre / from 1 are significant (Wald statistic > 9 per parameter); otherwise
    the release is redone without them. The release adds 6 parameters per released anchor plus those; with total
    squared errors (features and clicks, px^2) S0 before and S1 after over m residuals, it is kept when
    ``(S0 - S1) / (k s^2) > 9`` with k added parameters and s^2 = S1 / m the noise variance per residual. Returns
    that statistic (NaN when there is nothing to release)."""
    reg = recon.registered_indices()
    held = held_anchors(recon, cfg)
    tracked = [i for i in reg if recon.images[i].status == "anchor" and i not in held]
    n_anchors = sum(1 for i in reg if recon.images[i].status == "anchor")
    if not tracked or len(reg) < 2 or n_anchors < cfg.release_min_anchors:
        # One photo's clicks fix its pose but hardly the reconstruction's scale: that anchor stays held.
        return float("nan")
    n_grp = len(set(principal_point_groups(recon, reg).tolist())) if cfg.share_principal_point else len(reg)
    snap = snapshot(recon)
    # Exact steps (Schur complement): the shared principal point and the anchors' rotations form a soft mode that
    # capped, inexact LSMR steps barely move (fountain-P11: 2 px of a 22 px offset found with the cap, 20 without).
    use_pp, use_asp = True, bool(cfg.release_aspect)
    # One anchor's clicks lie in one photo: a principal point shared by the photos then trades with their common
    # rotation more than with two anchors facing apart, and its Wald statistic overstates the evidence (a seeded
    # arc with a centred lens: a spurious 13 px offset at Wald 29 for 2 parameters). One anchor needs
    # cfg.single_anchor_wald_factor times the evidence.
    n_anchor = sum(1 for i in reg if recon.images[i].status == "anchor")
    strict = cfg.single_anchor_wald_factor if n_anchor < 2 else 1.0

    def adjust(share: bool = False) -> dict[str, float]:
        release = {
            "refine_principal_point": use_pp,
            "refine_aspect": use_asp,
            "ba_solver": "schur",
            "ba_points_per_image": cfg.release_points_per_image,
            "share_intrinsics": share,
        }
        recon.release_settings = release
        return bundle(recon, msgspec.structs.replace(cfg, **release), fixed_anchors=held, covariance=True)

    stats = adjust()
    wald = stats.get("principal_point_wald", float("nan"))
    wald_a = stats.get("aspect_wald", float("nan"))
    # Parameters whose offsets are not significant are dropped and the release redone without them (a centred lens
    # would only trade its principal point for a common rotation of the cameras within the clicks' noise).
    for _ in range(2):
        drop_pp = use_pp and not (stats.get("principal_point_wald", np.nan) > 9.0 * strict * 2 * n_grp)
        drop_asp = use_asp and not (stats.get("aspect_wald", np.nan) > 9.0 * strict * n_grp)
        if not (drop_pp or drop_asp):
            break
        restore(recon, snap)
        snap = snapshot(recon)
        use_pp, use_asp = use_pp and not drop_pp, use_asp and not drop_asp
        stats = adjust()
    recon.principal_point_wald = float(wald)
    recon.aspect_wald = float(wald_a)
    n_added = 6 * len(tracked) + n_grp * (2 * int(use_pp) + int(use_asp))
    s0, s1, m = stats.get("initial_sse_px2", 0.0), stats.get("final_sse_px2", 0.0), stats.get("residuals", 0.0)
    if not stats or m <= 0 or s1 <= 0:
        restore(recon, snap)
        return float("nan")
    score = (s0 - s1) / (n_added * s1 / m)
    if not score > ANCHOR_RELEASE_THRESHOLD:
        restore(recon, snap)
        recon.release_settings = {}
        return float(score)
    recon.shared_intrinsics_lr = float("nan")
    n_tied = len(reg) - len(set(principal_point_groups(recon, reg).tolist()))
    if cfg.release_shared_intrinsics and n_tied > 0:
        # Likelihood ratio of shared vs per-image focal, k1, k2: the per-image fit has dof more parameters; the
        # shared one is kept unless its extra squared error exceeds 9 noise variances per parameter (the rule of
        # the other tests here; the squared errors include the heavy tail of feature mismatches, so the chi-square
        # quantile would reject sharing for any real set: fountain-P11, one calibrated camera, gives ~4 per
        # parameter, whereas a zoom change of 1 % under the same EXIF focal gives thousands).
        free = snapshot(recon)
        restore(recon, snap)
        snap = snapshot(recon)
        shared = adjust(share=True)
        dof = n_tied * (3 if cfg.refine_distortion else 1)
        lr = (shared.get("final_sse_px2", np.inf) - s1) / (s1 / max(m - dof, 1.0))
        recon.shared_intrinsics_lr = float(lr)
        recon.shared_intrinsics = bool(lr <= 9.0 * dof)
        if not recon.shared_intrinsics:
            restore(recon, free)
            recon.release_settings = {**recon.release_settings, "share_intrinsics": False}
    return float(score)


def held_anchors(recon: Reconstruction, cfg: MapperConfig) -> set[int]:
    """Registered anchors observing fewer than ``cfg.release_min_observations`` triangulated points: the final
    adjustment keeps their poses fixed (their tracks cannot check their clicks)."""
    return {
        i
        for i in recon.registered_indices()
        if recon.images[i].status == "anchor" and matched_track_count(recon, i) < cfg.release_min_observations
    }


def add_clicks_for_accuracy(
    recon: Reconstruction, cfg: MapperConfig, clicks_for: Callable[[int, str], Clicks | None]
) -> tuple[list[str], tuple[int, str] | None]:
    """Meet ``cfg.target_centre_sigma`` after a kept release: while the largest camera-centre standard deviation
    exceeds it, the registered image with the largest one among those without clicks gets clicks
    (``clicks_for(index, reason)``, None: try the next image) and becomes an anchor that keeps its pose (its clicks
    checked for mis-clicks by the anchor solve), and the release's adjustment is redone with them. Stops after
    ``cfg.accuracy_max_anchors`` images or when no image can get clicks. Returns the names of the images clicked
    and, when the target is still missed for want of clicks, the image to click next and why (else None)."""
    added: list[str] = []
    target = cfg.target_centre_sigma
    if target is None or not recon.anchors_released:
        return added, None
    release_cfg = msgspec.structs.replace(cfg, **recon.release_settings)
    while len(added) < cfg.accuracy_max_anchors:
        sig = {i: recon.images[i].centre_sigma_m for i in recon.registered_indices()}
        worst = max((v for v in sig.values() if np.isfinite(v)), default=float("nan"))
        if not worst > target:
            break
        todo = sorted(
            (i for i, v in sig.items() if np.isfinite(v) and recon.images[i].status != "anchor"), key=lambda i: -sig[i]
        )
        got = -1
        reason = f"accuracy: camera centres known to {worst:.3g} (target {target:.3g}); clicks here fix the frame"
        for i in todo:
            clicks = clicks_for(i, reason)
            if clicks is None:
                continue
            im = recon.images[i]
            kept = (im.world_from_camera, im.intrinsics, im.solved_focal_px, im.focal_prior_rejected, im.message)
            try:
                register_anchor(recon, i, clicks, cfg)
            except DegenerateAnchors as e:
                im.message = f"{kept[4]}; accuracy clicks rejected: {e}"
                continue
            # The anchor solve flagged mis-clicks; the pose, intrinsics and focal prior from the tracks stay (the
            # clicks join them in the adjustment below).
            im.world_from_camera, im.intrinsics, im.solved_focal_px, im.focal_prior_rejected = kept[:4]
            im.message += "; clicked for accuracy"
            got = i
            break
        if got < 0:
            return added, ((todo[0], reason) if todo else None)
        added.append(recon.images[got].name)
        bundle(recon, release_cfg, fixed_anchors=held_anchors(recon, cfg), covariance=True)
    return added, None
