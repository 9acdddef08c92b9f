"""Thresholds of the incremental mapper, shared by batch and streaming registration (one struct, TOML / --set)."""

from __future__ import annotations

import msgspec


class MapperConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Thresholds of the algorithm. Fractions are of the image width."""

    ratio: float = 0.8
    fundamental_threshold_frac: float = 0.0015
    min_pair_inliers: int = 20
    preemptive_features: int = 0
    preemptive_min_matches: int = 6
    homography_min_inlier_ratio: float = 0.8
    homography_min_matches: int = 30
    homography_threshold_frac: float = 0.005
    homography_max_rotation_deviation: float = 0.03
    # A homography transfer's rotation fit about the source camera's centre must explain its rays to this RMS (a
    # fraction of the width; a camera moved by 0.5 m 40 m from the building leaves 3x more).
    homography_max_rms_frac: float = 0.0015
    # Standard deviation of the prior holding an inherited lens's k1, k2 (ImageState.lens_source) in adjustments.
    inherited_distortion_sigma: float = 0.01
    # True: a photo registered through a rotation homography keeps its source's camera centre in the adjustments
    # (only its rotation and intrinsics move). Off: the centre starts at the source's and moves with the data (its
    # warped clicks, its tracks); held, it made the release refine a spurious principal point on a seeded scene
    # (tests/test_register_batch_sfm.py: 0.25 vs 0.13 deg).
    homography_shares_centre: bool = False
    min_track_matches: int = 60
    fallback_min_track_matches: int = 25
    pnp_inlier_frac: float = 0.01
    min_pnp_inliers: int = 20
    # A PnP pose must keep this fraction of the image's matches to triangulated tracks as inliers.
    min_pnp_inlier_fraction: float = 0.3
    # ... and, where the focal prior is trusted (EXIF / user), a focal within this fraction of it.
    max_focal_change: float = 0.3
    # Automatic poses whose image-up direction is further than this from world +z are refused (None: off; only a
    # z-up model frame, as a BIM's, makes it meaningful).
    max_tilt_from_upright_deg: float | None = None
    # Model points (BIM depth) serve only the camera that looked them up until a second view confirms them; True:
    # every photo (only where nothing unmodelled stands in front of the model).
    trust_model_points: bool = False
    # Plausibility of a registered camera (mapper.implausible): |k1|, |k2| at most this ...
    max_abs_distortion: float = 1.0
    # ... a focal within this fraction of a trusted prior (EXIF / user) ...
    max_focal_deviation: float = 0.2
    # ... and a reprojection RMS below this fraction of the width.
    max_rms_frac: float = 0.01
    # A model point is confirmed when a triangulation lands within this fraction of its distance to the camera.
    model_point_tolerance: float = 0.02
    # A PnP pose must explain this fraction of the verified matches to registered images (epipolar check).
    min_pose_pair_agreement: float = 0.7
    # ... over the pairs with photos within this distance by GPS (m; None: all pairs), when the photo has GPS. Off:
    # on the synthetic default site (repeated hoarding print everywhere) 40 m let two phone photos through 8 and
    # 16 deg off, which the check over all pairs refuses.
    agreement_max_gps_apart_m: float | None = None
    # Rotation test of an automatic pose (pose.pair_rotation_agreement): over the pairs of at least this many
    # verified matches, the match-weighted fraction whose own (essential-matrix) rotation lies within
    # rotation_check_max_deg of the candidate's must reach min_pair_rotation_agreement (None: off). On the
    # synthetic default site (seed 0) a phone photo matched only to the hoarding print on another side got a PnP
    # pose 68 deg wrong that explained 78 % of those pairs' matches epipolarly; their rotations differ by 21 deg.
    min_pair_rotation_agreement: float | None = 0.5
    rotation_check_min_matches: int = 100
    rotation_check_max_deg: float = 10.0
    epipolar_weight: float = 1.0
    min_triangulation_angle_deg: float = 2.0
    max_obs_error_frac: float = 0.005
    min_obs_error_px: float = 3.0
    refine_distortion: bool = True
    # Radial k1 in the anchor (click) solve: None = when the clicks constrain it (>= 8 spread, non-coplanar),
    # False = the paper's k1 = k2 = 0, True = always.
    anchor_distortion: bool | None = None
    # Principal points: False = image centres (the paper); True = refined in every bundle adjustment under the
    # prior below.
    refine_principal_point: bool = False
    # Standard deviation of a prior holding each principal point near the image centre, as a fraction of the
    # image width, used when principal points are refined (None = no prior).
    principal_point_sigma_frac: float | None = 0.01
    # Refined principal points are shared by the images of one physical camera, taken to be those with the same
    # size and focal prior (an image's own principal point is nearly a rotation of it, so per image it is hardly
    # observable; shared over many poses and held against the clicks it is).
    share_principal_point: bool = True
    # Pixel aspect ratio fy / fx: False = square pixels (the paper); True = refined in every bundle adjustment, one
    # per camera group like the principal point, under the prior below.
    refine_aspect: bool = False
    # Standard deviation of a prior holding each aspect ratio near 1 (square pixels), None = no prior.
    aspect_sigma: float | None = 0.01
    # The final release (release_anchors) also refines one aspect ratio per camera group, kept only when
    # significant (Wald test like the principal point's); False = square pixels to the end.
    release_aspect: bool = True
    # The final release also tries one focal and one k1, k2 per camera group (images with the same size and focal
    # prior, as for the principal point: one physical camera at one zoom) and keeps them shared unless the per-image
    # intrinsics fit much better (likelihood ratio > 9 per parameter, see release_anchors_if_significant). Off by
    # default (no gain measured, see BENCHMARKS.md).
    # ``share_intrinsics`` shares them in every adjustment (no test).
    release_shared_intrinsics: bool = False
    share_intrinsics: bool = False
    # The paper holds anchor poses fixed (and carries points on anchor rays); False lets them move, constrained by
    # their clicks and feature tracks like any camera, throughout.
    fix_anchor_poses: bool = True
    # With fixed anchors: after the last image, one bundle adjustment with the anchors free (held by their clicks)
    # and the (shared) principal points and aspect ratios refined is kept when the data support it (see
    # release_anchors_if_significant); False = the paper, fixed to the end.
    release_anchors: bool = True
    # An adjustment may move an anchor's clicks off their points by at most this much more (RMS, px) than its click
    # solve left them; beyond it the anchor's lens is held at the clicks' solve (recon.ImageState.lens_held) and the
    # adjustment redone (None: off). Matches on repeated texture can outvote a dozen clicks on the lens of a photo
    # whose pose they hold fixed (synthetic small seed 3: a phone's k1 -0.64, its clicks 1.5 -> 7.5 px RMS).
    max_anchor_click_drift_px: float | None = 1.0
    # A fixed camera's frame that would need anchor clicks is first searched for by the model's outlines around
    # its GPS position (nodes/register/modelsearch.py; needs the BIM view, the site's and the photo's GPS); found,
    # its camera gives the anchor solve model-point clicks in place of a person's.
    model_search: bool = True
    model_search_clicks: int = 24
    # A phone photo's automatic pose (PnP, relative pose) is kept only when the model's visible outline at it lies on
    # the photo's edges by at least this much more than when slid 12 px aside (modelsearch.OutlineCheck; needs the
    # BIM view; None: off). Chosen on the batch registrations of small seeds 0 / 3 / 5 / 7 / 11 / 13 and default 0
    # (57 phone photos, careful user, 2026-12-07): wrong automatic poses 0.011 / 0.054, anchored ones within 0.3 %
    # of the width 0.05-0.65 (all but one above 0.066).
    min_outline_contrast: float | None = 0.06
    # Experimental, off: a phone photo that would need anchor clicks is first searched for by the model
    # (nodes/register/phonesearch.py: rotation from its straight lines, candidate positions around its GPS at hand
    # height from the outline), each candidate refined and scored on the fixed cameras' texture carried through the
    # model (phone_search_texture, below). BENCHMARKS 'phones found by the texture (notes, 2026-12-07)'.
    phone_search: bool = False
    phone_search_min_agreeing: int = 25
    # The older rule (phone_search_texture off): a found camera is kept only when one registered fixed camera's
    # frame's verified matches agree with it (phone_search_min_agreeing within a quarter percent of the width of
    # their epipolar lines), and after its refinement on those matches and its outline (phonesearch.refine_on_matches)
    # agree again and lie on the photo's edges by at least phone_search_min_contrast more than slid aside. On the
    # default site it let a camera 0.68-0.99 % of the width off through while finding one phone in 30.
    phone_search_min_contrast: float = 0.15
    # A found camera is confirmed by the fixed cameras' texture carried through the model instead of by matches
    # (phonesearch.phone_anchor_by_texture: refined by dense flow against it, kept when it correlates best by a
    # margin, stands where a person can and lines up nowhere else near); needs the registered frames' pixels (batch:
    # their files; streaming: each fixed camera's latest registered frame).
    phone_search_texture: bool = True
    # Only anchors observing at least this many triangulated track points are released: the others' poses rest on
    # their clicks alone.
    release_min_observations: int = 300
    # ... and only when at least this many photos carry clicks (one photo's clicks fix its own pose but hardly the
    # reconstruction's scale; 1: release a single anchor too).
    release_min_anchors: int = 1
    # With a single anchor the release's principal points and aspects need this many times the usual evidence.
    single_anchor_wald_factor: float = 5.0
    # Points per image in that final adjustment (its longest tracks; 0 = every triangulated point). The incremental
    # adjustments keep ba_points_per_image for speed; the final one uses all.
    release_points_per_image: int = 0
    loss_scale_px: float = 2.0
    ba_max_nfev: int = 40
    # Cap on the inner LSMR iterations of each bundle-adjustment step (inexact trust-region steps); None = SciPy's
    # default.
    ba_lsmr_maxiter: int | None = 30
    # Bundle-adjustment solver of the incremental adjustments (BundleOptions.solver); the final release always
    # uses "schur" (exact steps).
    ba_solver: str = "trf"
    local_ba_window: int = 5
    local_ba_max_nfev: int = 5
    ba_points_per_image: int = 400
    full_ba_every: int = 4
    focal_px: float | None = None
    # Standard deviation of a known focal prior as a fraction of it, applied in bundle adjustment (focal and depth
    # trade off for narrow fields of view, so a free focal drifts): a user-given focal_px is trusted, EXIF less.
    focal_prior_sigma_frac: float | None = 0.001
    exif_focal_sigma_frac: float | None = 0.02
    # Candidate search in matching on the descriptors' top principal components (exact similarities then decide
    # the ratio test); 0 = exact search.
    match_pca_dims: int = 64
    max_exhaustive_images: int = 40
    shortlist_size: int = 15
    # Clicks given up front (the anchor file's, not answers to requests) all anchor their photos at the start; False:
    # only the first (the paper's Algorithm 1), the others when their photo is reached or asked for.
    use_all_anchors: bool = True
    workers: int = 2
    # GPS safeguards (EXIF positions; phones ~3 m error, sometimes much worse). Distances between registered centres
    # are horizontal distances in the model frame, taken to be metric and z-up (the BIM's site-local metres).
    # A homography transfer (the premise: the same viewpoint) is refused when both photos carry GPS more than this
    # far apart (m; None = off). Two fixes 3 m sigma per axis of one viewpoint lie > 15 m apart with p ~ 2e-3.
    gps_max_homography_distance_m: float | None = 15.0
    # An automatic registration (PnP, homography) is refused when the median over the registered photos with GPS
    # of |distance between registered centres - distance between GPS positions| exceeds this (m; None = off); it
    # needs at least gps_min_references such photos. The image then stays unregistered (and asks for an anchor).
    gps_max_residual_m: float | None = 15.0
    gps_min_references: int = 2
    # Registered photos within this distance of each other by GPS count as one position in that median (the frames
    # of one fixed camera; see gps_median_residual_m).
    gps_same_position_m: float = 1.0
    # Orientation-aware second test (gps_heading_residual_m): used when the registered photos' GPS positions span at
    # least this (m); gps_sigma_m is the GPS error assumed for the fit's uncertainty.
    gps_min_fit_span_m: float = 30.0
    gps_sigma_m: float = 3.0
    # When clicks for an image are at hand before it is asked for them (the anchor file's, not answers to requests)
    # and an automatic registration puts them further than click_check_max_frac of the width (median) from where
    # they were clicked, the image is re-registered from its clicks (an anchor).
    check_auto_with_clicks: bool = True
    click_check_max_frac: float = 0.02
    # Accuracy target (model units, None = off): after a kept release, while some camera centre's standard deviation
    # (ImageState.centre_sigma_m) exceeds it, clicks are asked for the registered image with the largest one that
    # has none (the anchor file's, else request_anchor) and the final adjustment is redone with them; at most
    # accuracy_max_anchors such images.
    target_centre_sigma: float | None = None
    accuracy_max_anchors: int = 4
    # Anchor requests go to the image with the fewest matched tracks (the paper). At the start, before anything is
    # triangulated, every image ties at zero; the second anchor then fixes the model frame with the first, so the
    # image with the strongest link to a registered one is asked first: most verified matches x sin^2 of the
    # relative rotation (from the pair's fundamental matrix and the focal priors), over pairs with at least this
    # many verified matches. Later ties keep collection order. 0 = collection order throughout.
    anchor_request_min_shared_matches: int = 100
    # When fewer photos than this carry clicks once everything is registered, clicks are asked for one more (the
    # widest view from the anchors; frame_anchor_order): one anchor's dozen clicks fix the model frame less well
    # than two far apart. Unanswered, the registration stands. 0 or 1: never asked.
    min_anchors: int = 2
    # Clicks the anchor solve keeps after flagging mis-clicks must number at least this many (else the clicks are
    # refused with the reason and asked again).
    min_anchor_inliers: int = 6
    # One-anchor bootstrap (try_relative_pose): when no image has enough matched tracks, the unregistered image
    # with the most verified matches to a registered one is placed by their relative pose.
    bootstrap: bool = True
    bootstrap_min_matches: int = 100
    bootstrap_min_parallax_deg: float = 2.0
    # ... and between two frames of one fixed camera (a knock, a move to another mast), where most of the motion is
    # a turn: a knocked camera's frame (0.56 m, 8 deg) placed at a median parallax of 2.6 deg relative to its own
    # camera's frame came out 2.9 deg and 2.7 m off (the partition test's one-worker run, small site without BIM
    # depth), while a rotation homography or PnP on the camera's own model points register such frames.
    bootstrap_min_parallax_deg_own_camera: float = 5.0
    # ... and at most this: SIFT-like descriptors do not match across a larger change of view, so a larger median
    # parallax is a motion fitted to wrong matches (default seed 0: a phone placed at 130 deg from another across
    # the building, 16 m off, on the hoarding print's repeats).
    bootstrap_max_parallax_deg: float = 60.0
    # The matches' median residual after the best pure rotation (fraction of the width) must reach this: below it
    # the translation's sign in the image is within what the lens model's small errors make, and the relative
    # motion is not determined (a knocked mast camera: 0.27-0.32 % on the small sites, seeds 0, 7, 11).
    bootstrap_min_translation_frac: float = 0.005
    bootstrap_click_radius_frac: float = 0.05
    bootstrap_max_scale_spread: float = 0.05
    bootstrap_min_scale_agreement: float = 0.4
    # Triangulated points among the matches needed to take the baseline's length from them (fewer: the clicks, or
    # no registration); for a fixed camera's frame placed relative to its own camera's frame (nearly one
    # viewpoint: a knocked camera, whose handful of points on tracks chained across cameras by repeated texture
    # scaled its baseline 4x too long, 3 deg off), bootstrap_min_scale_points_own_camera. 12 for all (2026-12-03)
    # left templeSparseRing at 13/16 with one anchor.
    bootstrap_min_scale_points: int = 5
    bootstrap_min_scale_points_own_camera: int = 12
    # Standard deviation (px, relative to a user's click) of clicks carried into a bootstrapped photo by local
    # homographies of the matches around them: they hold the baseline's length, not the pose.
    carried_click_sigma_px: float = 5.0
