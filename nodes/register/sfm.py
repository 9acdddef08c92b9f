"""Model-assisted structure from motion (paper Sec. 6, Algorithm 1), pure core.

The state is a :class:`Reconstruction`: images (features, camera, status), pairwise verified matches, tracks
(``track_obs[t]`` maps image index -> feature index) and their triangulated points in the model frame. Images can
be added one at a time (:func:`add_image`, :func:`match_image`, :func:`link_image_tracks`,
:func:`register_image_pnp`, :func:`triangulate_tracks`, :func:`bundle`), which is what the streaming node
does; :func:`reconstruct` runs the whole batch algorithm:

1. the first anchor image is solved from its clicks (:mod:`constructaide.anchorsolve`);
2. features are matched over the collection (exhaustive, or a bag-of-words shortlist for large sets) and
   pruned by a fundamental matrix (RANSAC); matches are chained into tracks;
3. images whose matches to an anchor are >= 80 % inliers of one homography receive the warped clicks and are
   solved by PnP;
4. constrained bundle adjustment (:mod:`nodes.register.bundle`) after each addition: anchor poses fixed,
   points seen by an anchor parameterised by depth along its ray, rays closer than 2 degrees not triangulated;
5. next image: among unregistered images with >= 60 matches to triangulated tracks, the one with the fewest,
   solved by PnP-RANSAC (inliers within 1 % of the width) refined with the paper's epipolar term;
6. when none qualifies, the image with the fewest matched tracks needs anchor clicks (``request_anchor``);
7. finally, the anchors that observe enough triangulated points are released (held by their clicks) and one
   principal point and one pixel aspect ratio per camera are refined, each kept only when significant
   (:func:`release_anchors_if_significant`); that adjustment also gives each camera centre's standard
   deviation, and with an accuracy target the least certain images are clicked too
   (:func:`add_clicks_for_accuracy`).

Pixels: OpenCV convention. Poses: ``world_from_camera`` (4, 4), OpenCV camera frame, model units.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from constructaide import camera as cam
from constructaide.anchorsolve import AnchorSolution, DegenerateAnchors, solve_anchor
from constructaide.geo import EARTH_RADIUS_M, gps_distance_residuals_m, horizontal_distance_m
from nodes.register.bundle import BundleOptions, BundleProblem, bundle_adjust, single_thread_blas
from nodes.register.features import (
    Features,
    filter_matches_fundamental,
    homography_inlier_ratio,
    match_features,
    pca_basis,
    project_pca,
    ransac_iterations,
)
from schemas.messages import GeoPoint, Intrinsics

Clicks = tuple[np.ndarray, np.ndarray]  # pixels (N, 2) OpenCV px, world points (N, 3) model units


@dataclass
class SfmConfig:
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
    # True: a photo registered through a rotation homography keeps its anchor's camera centre (only rotation
    # and intrinsics are solved, and adjusted while that anchor's pose is held fixed). Off by default: a fixed
    # camera bumped by half a metre 40 m from the building still passes the rotation test (synthetic site, east
    # camera) and then inherits a wrong centre; on that site the mean centre error was 0.48 m with it vs 0.39 m
    # without (0.24 vs 0.29 m after a similarity): no clear gain.
    homography_shares_centre: bool = False
    min_track_matches: int = 60
    fallback_min_track_matches: int = 25
    pnp_inlier_frac: float = 0.01
    min_pnp_inliers: int = 20
    # A PnP pose must explain this fraction of the verified matches to registered images (epipolar check).
    min_pose_pair_agreement: float = 0.7
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
    # default: on fountain-P11 (one calibrated camera) over six click-noise draws (earlier seeding and second anchor)
    # the mean centre error was 7.98 mm shared vs 7.81 mm per image (draws ranged 5.8-9.6 mm either way), temple
    # 0.31 vs 0.29 deg: no gain.
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
    # Only anchors observing at least this many triangulated track points are released: the others' poses rest on
    # their clicks alone (synthetic site: 0-250 per anchor, fixed cameras 40 m from the building; temple 600-800,
    # fountain 1900-2400).
    release_min_observations: int = 300
    # Points per image in that final adjustment (its longest tracks; 0 = every triangulated point). The incremental
    # adjustments keep ba_points_per_image for speed; the final one uses all (fountain-P11: centre error over six
    # click-noise draws, earlier seeding and second anchor, 8.8 -> 7.8 mm mean).
    release_points_per_image: int = 0
    loss_scale_px: float = 2.0
    ba_max_nfev: int = 40
    # Cap on the inner LSMR iterations of each bundle-adjustment step (inexact trust-region steps): ~2x faster
    # batch BA at equal accuracy on temple/fountain/synthetic (bench/registration.py); None = SciPy's default.
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
    # the ratio test): ~30 % less matching time, 99.6 % of the exact verified matches (templeSparseRing);
    # 0 = exact search.
    match_pca_dims: int = 64
    max_exhaustive_images: int = 40
    shortlist_size: int = 15
    use_all_anchors: bool = False
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
    # they were clicked, the image is re-registered from its clicks (an anchor). Synthetic default site: correct
    # automatic poses put clicks <= 0.6 % of the width off, the wrong ones (mirrored, repeated print) >= 14 %.
    check_auto_with_clicks: bool = True
    click_check_max_frac: float = 0.02
    # Accuracy target (model units, None = off): after a kept release, while some camera centre's standard deviation
    # (ImageState.centre_sigma_m) exceeds it, clicks are asked for the registered image with the largest one that
    # has none (the anchor file's, else request_anchor) and the final adjustment is redone with them; at most
    # accuracy_max_anchors such images. More clicks fix the model frame better (fountain-P11: 2 anchors of 12
    # clicks leave 6-14 mm).
    target_centre_sigma: float | None = None
    accuracy_max_anchors: int = 4
    # Anchor requests go to the image with the fewest matched tracks (the paper). At the start, before anything is
    # triangulated, every image ties at zero; the second anchor then fixes the model frame with the first, so the
    # image with the strongest link to a registered one is asked first: most verified matches x sin^2 of the
    # relative rotation (from the pair's fundamental matrix and the focal priors), over pairs with at least this
    # many verified matches. fountain-P11 over 18 click-noise draws (features at 1600 px), second anchor 47 deg
    # from the first (this rule) vs 9 deg (collection order): centre 6.8 vs 8.3 mm, checkpoint reprojection
    # 0.019 vs 0.058 % of the width, angle 0.059 vs 0.062 deg (bench/registration.py --sets fountain --runs 18
    # --variants 'default,collection order'). Later ties keep collection order (templeSparseRing, 18 draws:
    # breaking them the same way cost 0.2 mm). 0 = collection order throughout.
    anchor_request_min_shared_matches: int = 100


@dataclass
class PairGeometry:
    """Verified matches between images i < j: ``matches`` (M, 2) feature indices (in i, in j), ``F`` with
    ``x_j^T F x_i = 0`` in pixels, and the homography inlier ratio (computed lazily, NaN until then)."""

    matches: np.ndarray
    F: np.ndarray
    num_raw_matches: int
    homography_i_to_j: np.ndarray | None = None
    homography_ratio: float = float("nan")


@dataclass
class ImageState:
    """One image. ``status``: unregistered, anchor, auto or failed; ``clicks`` are model-point constraints
    (user clicks for anchors, warped clicks for homography registrations)."""

    name: str
    features: Features
    colors_rgb_u8: np.ndarray | None = None
    focal_prior_px: float | None = None
    intrinsics: Intrinsics | None = None
    world_from_camera: np.ndarray | None = None
    status: str = "unregistered"
    method: str = ""
    num_inliers: int = 0
    rms_px: float = float("nan")
    message: str = ""
    clicks: Clicks | None = None
    click_inliers: np.ndarray | None = None
    anchor: AnchorSolution | None = None
    num_matched_tracks: int = 0
    # Focal solved from this image's own clicks (None when the prior was kept); informational.
    solved_focal_px: float | None = None
    # The image's clicks (or warped clicks) contradicted the focal prior: no focal prior for it any more.
    focal_prior_rejected: bool = False
    # Image whose camera centre this one shares (a rotation homography to that anchor), or None.
    centre_source: int | None = None
    # EXIF GPS position, None when absent.
    gps: GeoPoint | None = None
    # Median GPS distance residual (m) of the automatic registration (see gps_check), NaN when not checked.
    gps_residual_m: float = float("nan")
    # Standard deviation of the camera centre (model units; sqrt of the trace of its 3x3 covariance) from the final
    # adjustment with the anchors released (release_anchors_if_significant): what the features and clicks fix of
    # where the camera stood. NaN when not estimated (release not run or not kept, or the pose held fixed).
    centre_sigma_m: float = float("nan")

    @property
    def width_px(self) -> int:
        return self.features.width_px

    @property
    def height_px(self) -> int:
        return self.features.height_px

    @property
    def registered(self) -> bool:
        return self.status in ("anchor", "auto")


@dataclass
class Reconstruction:
    """Images, verified pairs, tracks and points (T, 3) world (NaN while untriangulated)."""

    images: list[ImageState] = field(default_factory=list)
    pairs: dict[tuple[int, int], PairGeometry] = field(default_factory=dict)
    track_obs: list[dict[int, int]] = field(default_factory=list)
    feature_track: list[np.ndarray] = field(default_factory=list)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    needs_anchor: list[tuple[str, str, int]] = field(default_factory=list)
    timings_secs: dict[str, float] = field(default_factory=dict)
    # Statistic of the final anchor-release test (see release_anchors_if_significant), NaN when not run, and
    # whether the released anchors were kept.
    anchor_release_score: float = float("nan")
    anchors_released: bool = False
    # Likelihood-ratio statistic of shared focal / distortion per camera group in the release (NaN if not tried)
    # and whether they were kept shared.
    shared_intrinsics_lr: float = float("nan")
    shared_intrinsics: bool = False
    # Wald statistic of the shared principal points in the release (kept when > 9 per parameter), NaN if not run.
    principal_point_wald: float = float("nan")
    # SfmConfig fields the kept release adjusted with (principal points, aspects, shared intrinsics), {} otherwise.
    release_settings: dict = field(default_factory=dict)
    # Images given clicks to meet SfmConfig.target_centre_sigma, in order.
    accuracy_anchors: list[str] = field(default_factory=list)
    # (T,) bool per track once densified (nodes.register.batch.densify_reconstruction): confirmed by epipolar-guided
    # matching (the densified tracks are by construction); None before. Occlusion reasoning uses confirmed ones only.
    point_verified: np.ndarray | None = None
    # Same for the aspect ratios (fy / fx, one per camera group) in the release, NaN if not refined there.
    aspect_wald: float = float("nan")

    def index(self, name: str) -> int:
        for i, im in enumerate(self.images):
            if im.name == name:
                return i
        raise KeyError(name)

    def registered_indices(self) -> list[int]:
        return [i for i, im in enumerate(self.images) if im.registered]

    def pair(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(matches (M, 2) as (feature in a, feature in b), F with x_b^T F x_a = 0) or None."""
        if a < b:
            g = self.pairs.get((a, b))
            return None if g is None else (g.matches, g.F)
        g = self.pairs.get((b, a))
        return None if g is None else (g.matches[:, ::-1], g.F.T)

    def sparse_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Triangulated points (P, 3), colours (P, 3) u8, and observations over registered images:
        point index (M,), image index (M,), pixel (M, 2)."""
        ok = np.nonzero(np.all(np.isfinite(self.points), axis=1))[0]
        remap = -np.ones(len(self.points), int)
        remap[ok] = np.arange(len(ok))
        op, oi, ox = [], [], []
        for t in ok:
            for i, f in self.track_obs[t].items():
                if self.images[i].registered:
                    op.append(remap[t])
                    oi.append(i)
                    ox.append(self.images[i].features.keypoints_px[f])
        px = np.array(ox, np.float64).reshape(-1, 2)
        return self.points[ok], self.colors[ok], np.array(op, int), np.array(oi, int), px

    def _add_tracks(self, n: int) -> None:
        self.points = np.vstack([self.points, np.full((n, 3), np.nan)])
        self.colors = np.vstack([self.colors, np.zeros((n, 3), np.uint8)])


def focal_prior(im: ImageState, cfg: SfmConfig) -> float:
    if cfg.focal_px is not None:
        return float(cfg.focal_px)
    if im.focal_prior_px is not None:
        return float(im.focal_prior_px)
    return float(cam.focal_from_fov(im.width_px, 50.0))


def _focal_sigma_frac(im: ImageState, cfg: SfmConfig) -> float:
    """Relative standard deviation of the focal prior of an image (inf when the prior is only a FOV guess, or
    when the image's own clicks contradicted it)."""
    if im.focal_prior_rejected:
        return np.inf
    if cfg.focal_px is not None:
        return cfg.focal_prior_sigma_frac if cfg.focal_prior_sigma_frac is not None else np.inf
    if im.focal_prior_px is not None:
        return cfg.exif_focal_sigma_frac if cfg.exif_focal_sigma_frac is not None else np.inf
    return np.inf


def _anchor_focal_kwargs(im: ImageState, cfg: SfmConfig) -> dict:
    """Focal arguments of :func:`solve_anchor` for image ``im``: its external prior (user / EXIF) with that
    prior's relative sigma, or no prior at all (a 50 degree FOV is a starting guess, not evidence)."""
    sigma = _focal_sigma_frac(im, cfg)
    if not np.isfinite(sigma):
        return {"focal_px": None}
    return {"focal_px": focal_prior(im, cfg), "focal_prior_sigma": float(sigma)}


# ---------------------------------------------------------------------------
# Images, pairs, tracks
# ---------------------------------------------------------------------------


def add_image(
    recon: Reconstruction,
    name: str,
    features: Features,
    colors_rgb_u8: np.ndarray | None = None,
    focal_prior_px: float | None = None,
    gps: GeoPoint | None = None,
) -> int:
    """Append an unregistered image; returns its index. ``colors_rgb_u8`` (N, 3): colour at each keypoint;
    ``gps``: its EXIF position (None when absent)."""
    if any(im.name == name for im in recon.images):
        raise ValueError(f"image {name!r} is already in the reconstruction")
    recon.images.append(ImageState(name, features, colors_rgb_u8, focal_prior_px, gps=gps))
    recon.feature_track.append(-np.ones(len(features), dtype=np.int64))
    return len(recon.images) - 1


def _largest_scales(f: Features, n: int) -> Features:
    keep = np.argsort(-f.scales)[:n]
    pca = None if f.descriptors_pca is None else f.descriptors_pca[keep]
    return Features(f.keypoints_px[keep], f.descriptors[keep], f.scales[keep], f.width_px, f.height_px, pca)


def verify_pair(a: Features, b: Features, cfg: SfmConfig) -> PairGeometry | None:
    """Ratio-test matches pruned by a RANSAC fundamental matrix; None with fewer than ``min_pair_inliers``.

    Preemptive matching (as in VisualSFM): the ``preemptive_features`` largest-scale features are matched first
    and the pair is skipped when fewer than ``preemptive_min_matches`` of them match.
    """
    n_pre = cfg.preemptive_features
    if n_pre and len(a) > 2 * n_pre and len(b) > 2 * n_pre:
        pre = match_features(_largest_scales(a, n_pre), _largest_scales(b, n_pre), cfg.ratio)
        if len(pre) < cfg.preemptive_min_matches:
            return None
    m = match_features(a, b, cfg.ratio)
    if len(m) < cfg.min_pair_inliers:
        return None
    thr = max(1.0, cfg.fundamental_threshold_frac * max(a.width_px, b.width_px))
    # No more iterations than needed to find a model with the fewest inliers a pair may have (most pairs of
    # a collection do not overlap and have a few dozen chance matches: they cost ~100 iterations, not 10000).
    iters = min(10000, ransac_iterations(len(m), cfg.min_pair_inliers))
    F, inl = filter_matches_fundamental(a.keypoints_px, b.keypoints_px, m, thr, max_iters=iters)
    if F is None or inl.sum() < cfg.min_pair_inliers:
        return None
    return PairGeometry(m[inl], F, len(m))


def select_pairs(features: list[Features], cfg: SfmConfig, seed: int = 0) -> list[tuple[int, int]]:
    """All pairs for small sets; for more than ``max_exhaustive_images`` a bag-of-words shortlist (each image with
    its ``shortlist_size`` most similar images by tf-idf cosine over a k-means vocabulary of RootSIFT)."""
    n = len(features)
    if n <= cfg.max_exhaustive_images:
        return [(i, j) for i in range(n) for j in range(i + 1, n)]
    rng = np.random.default_rng(seed)
    sample = []
    for f in features:
        if len(f):
            sample.append(f.descriptors[rng.choice(len(f), min(len(f), 300), replace=False)])
    data = np.vstack(sample).astype(np.float32)
    k = int(min(1024, max(16, len(data) // 4)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
    cv2.setRNGSeed(seed)
    _, _, centers = cv2.kmeans(data, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    hist = np.zeros((n, k))
    for i, f in enumerate(features):
        if len(f):
            words = np.array([m.trainIdx for m in matcher.match(f.descriptors, centers)])
            hist[i] = np.bincount(words, minlength=k)
    idf = np.log(n / np.maximum((hist > 0).sum(0), 1))
    h = hist * idf
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    sim = h @ h.T
    np.fill_diagonal(sim, -np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(-sim[i])[: cfg.shortlist_size]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def match_image(
    recon: Reconstruction, idx: int, others: list[int], cfg: SfmConfig, progress: Callable[[], None] | None = None
) -> int:
    """Verify pairs between image ``idx`` and ``others``; stores them; returns how many pairs were kept."""
    kept = 0
    for o in others:
        if o == idx:
            continue
        i, j = min(idx, o), max(idx, o)
        if (i, j) in recon.pairs:
            kept += 1
            continue
        g = verify_pair(recon.images[i].features, recon.images[j].features, cfg)
        if g is not None:
            recon.pairs[(i, j)] = g
            kept += 1
        if progress is not None:
            progress()
    return kept


def build_tracks(recon: Reconstruction) -> None:
    """(Re)build all tracks from the verified pairs by union-find; tracks with two features in one image are
    dropped. Clears triangulated points."""
    offsets = np.cumsum([0] + [len(im.features) for im in recon.images])
    parent = np.arange(offsets[-1])

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for (i, j), g in recon.pairs.items():
        for fa, fb in g.matches:
            ra, rb = find(offsets[i] + fa), find(offsets[j] + fb)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    comps: dict[int, dict[int, int]] = {}
    bad: set[int] = set()
    node_image = np.repeat(np.arange(len(recon.images)), np.diff(offsets))
    used = set()
    for (i, j), g in recon.pairs.items():
        used.update((offsets[i] + g.matches[:, 0]).tolist())
        used.update((offsets[j] + g.matches[:, 1]).tolist())
    for node in used:
        r = find(node)
        img = int(node_image[node])
        d = comps.setdefault(r, {})
        if img in d:
            bad.add(r)
        d[img] = int(node - offsets[img])
    recon.track_obs = [d for r, d in comps.items() if r not in bad and len(d) >= 2]
    recon.feature_track = [-np.ones(len(im.features), dtype=np.int64) for im in recon.images]
    for t, d in enumerate(recon.track_obs):
        for i, f in d.items():
            recon.feature_track[i][f] = t
    n = len(recon.track_obs)
    recon.points = np.full((n, 3), np.nan)
    recon.colors = np.zeros((n, 3), np.uint8)


def link_image_tracks(recon: Reconstruction, idx: int) -> int:
    """Attach the features of image ``idx`` to tracks through its verified pairs (incremental, no merging of
    existing tracks); new two-view tracks are created for unmatched pairs. Returns the number of links made."""
    links = 0
    ft = recon.feature_track[idx]
    for (i, j), g in list(recon.pairs.items()):
        if idx not in (i, j):
            continue
        other = j if i == idx else i
        m = g.matches if i == idx else g.matches[:, ::-1]
        for f_new, f_other in m:
            if ft[f_new] >= 0:
                continue
            t = int(recon.feature_track[other][f_other])
            if t < 0:
                t = len(recon.track_obs)
                recon.track_obs.append({int(other): int(f_other)})
                recon._add_tracks(1)
                recon.feature_track[other][f_other] = t
            elif idx in recon.track_obs[t]:
                continue
            recon.track_obs[t][idx] = int(f_new)
            ft[f_new] = t
            links += 1
    return links


def matched_track_count(recon: Reconstruction, idx: int) -> int:
    """Features of image ``idx`` that belong to triangulated tracks."""
    t = recon.feature_track[idx]
    t = t[t >= 0]
    if len(t) == 0:
        return 0
    return int(np.sum(np.all(np.isfinite(recon.points[t]), axis=1)))


# ---------------------------------------------------------------------------
# Registration steps
# ---------------------------------------------------------------------------


def register_anchor(recon: Reconstruction, idx: int, clicks: Clicks, cfg: SfmConfig) -> AnchorSolution:
    """Solve image ``idx`` from user clicks; marks it an anchor. Raises DegenerateAnchors."""
    im = recon.images[idx]
    px, world = np.asarray(clicks[0], float), np.asarray(clicks[1], float)
    sol = solve_anchor(
        px, world, im.width_px, im.height_px, solve_distortion=cfg.anchor_distortion, **_anchor_focal_kwargs(im, cfg)
    )
    im.intrinsics, im.world_from_camera = sol.intrinsics, sol.world_from_camera
    im.status, im.method, im.anchor = "anchor", "anchor", sol
    im.solved_focal_px = sol.intrinsics.f_px if sol.focal_solved else None
    im.focal_prior_rejected = sol.focal_prior_rejected
    im.clicks, im.click_inliers = (px, world), ~sol.outlier_mask
    im.num_inliers = int(np.sum(~sol.outlier_mask))
    im.rms_px = sol.rms_px
    n_out = int(sol.outlier_mask.sum())
    im.message = f"{len(px)} clicks, rms {sol.rms_px:.2f} px" + (f", {n_out} flagged as mis-clicks" if n_out else "")
    return sol


def _gps_positions(references: list[tuple[np.ndarray, GeoPoint]], same_position_m: float) -> list[list[int]]:
    """Indices of ``references`` grouped by GPS position (greedy: within ``same_position_m`` of a group's first)."""
    groups: list[list[int]] = []
    for k, (_, g) in enumerate(references):
        for members in groups:
            if horizontal_distance_m(references[members[0]][1], g) <= same_position_m:
                members.append(k)
                break
        else:
            groups.append([k])
    return groups


def _enu_m(g: GeoPoint, origin: GeoPoint) -> np.ndarray:
    """East / north metres (2,) of ``g`` from ``origin`` (local equirectangular, like horizontal_distance_m)."""
    lat = np.radians(0.5 * (g.lat_deg + origin.lat_deg))
    return EARTH_RADIUS_M * np.array(
        [np.radians(g.lon_deg - origin.lon_deg) * np.cos(lat), np.radians(g.lat_deg - origin.lat_deg)]
    )


def gps_median_residual_m(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    same_position_m: float = 1.0,
) -> float:
    """Median GPS distance residual (m) of a camera at ``centre_in_world_m`` (3,) with ``gps`` against
    ``references`` (camera centre (3,) world m, GPS): |horizontal distance between the centres - distance between
    the GPS positions| (:func:`constructaide.geo.gps_distance_residuals_m`, needs no georeference of the model).

    References whose GPS positions lie within ``same_position_m`` of each other (the frames of one fixed camera)
    count once, with the median of their residuals; the result is the median over those positions (20 frames of
    one camera would otherwise outvote every other direction). NaN without references."""
    if not references:
        return float("nan")
    centres = np.array([np.asarray(c, np.float64)[:3] for c, _ in references])
    res = gps_distance_residuals_m(np.asarray(centre_in_world_m, np.float64), gps, centres, [g for _, g in references])
    return float(np.median([np.median(res[m]) for m in _gps_positions(references, same_position_m)]))


def gps_heading_residual_m(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    same_position_m: float = 1.0,
    inlier_m: float = 15.0,
    min_span_m: float = 30.0,
    sigma_m: float = 3.0,
) -> tuple[float, float]:
    """Orientation-aware GPS check of a camera at ``centre_in_world_m`` (3,) with ``gps``: (horizontal distance (m)
    between its GPS position and its centre carried into east/north metres by the rigid motion (rotation about z,
    translation) fitted to ``references``, that fit's own uncertainty at the candidate (3 sigma, m)).

    Distances alone (:func:`gps_median_residual_m`) cannot tell a model from its mirror image: a camera mirrored
    across the line through two references keeps its distances to both (synthetic site: a west camera placed by PnP
    on repeated hoarding print 64 m off, at the east camera's place, keeps its distances to the north and south
    cameras). The z-up model frame is right-handed like east/north/up, so a rigid motion without reflection relates
    them; it is fitted (least median of squares over pairs of positions, then least squares on the positions within
    ``inlier_m``) to the reference positions (grouped as in gps_median_residual_m, model centre = median of the
    group's). Its uncertainty at the candidate is 3 ``sigma_m`` (GPS error) times (1 / sqrt(n) + distance from the
    positions' centroid / their spread (root sum of squares)). (NaN, NaN) when the inlier positions span less than
    ``min_span_m`` (the heading is then too uncertain)."""
    nan = (float("nan"), float("nan"))
    groups = _gps_positions(references, same_position_m)
    if len(groups) < 2:
        return nan
    origin = references[0][1]
    enu = np.array([_enu_m(references[m[0]][1], origin) for m in groups])
    xy = np.array([np.median([np.asarray(references[k][0], np.float64)[:2] for k in m], axis=0) for m in groups])
    n = len(groups)
    ii, jj = np.triu_indices(n, 1)
    sep = np.linalg.norm(enu[jj] - enu[ii], axis=1)
    keep = sep >= 0.5 * min_span_m
    ii, jj = ii[keep], jj[keep]
    if len(ii) == 0:
        return nan
    if len(ii) > 2000:
        pick = np.random.default_rng(0).choice(len(ii), 2000, replace=False)
        ii, jj = ii[pick], jj[pick]
    de, dm = enu[jj] - enu[ii], xy[jj] - xy[ii]
    theta = np.arctan2(de[:, 1], de[:, 0]) - np.arctan2(dm[:, 1], dm[:, 0])
    c, s = np.cos(theta), np.sin(theta)
    mid_m, mid_e = 0.5 * (xy[ii] + xy[jj]), 0.5 * (enu[ii] + enu[jj])
    t = mid_e - np.c_[c * mid_m[:, 0] - s * mid_m[:, 1], s * mid_m[:, 0] + c * mid_m[:, 1]]
    px = c[:, None] * xy[None, :, 0] - s[:, None] * xy[None, :, 1] + t[:, :1]
    py = s[:, None] * xy[None, :, 0] + c[:, None] * xy[None, :, 1] + t[:, 1:]
    err = np.hypot(px - enu[None, :, 0], py - enu[None, :, 1])
    best = int(np.argmin(np.median(err, axis=1)))
    inl = err[best] <= inlier_m
    if inl.sum() < 2:
        return nan
    span = np.max(np.linalg.norm(enu[inl][:, None] - enu[inl][None], axis=2))
    if span < min_span_m:
        return nan
    # Least squares rotation + translation (2D Kabsch) on the inlier positions.
    a, b = xy[inl], enu[inl]
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    R = u @ np.diag([1.0, np.linalg.det(u @ vt)]) @ vt
    tt = mb - R @ ma
    pred = R @ np.asarray(centre_in_world_m, np.float64)[:2] + tt
    resid = float(np.linalg.norm(pred - _enu_m(gps, origin)))
    spread = float(np.sqrt(np.sum((a - ma) ** 2)))
    dist = float(np.linalg.norm(np.asarray(centre_in_world_m, np.float64)[:2] - ma))
    allowance = 3.0 * sigma_m * (1.0 / np.sqrt(len(a)) + dist / max(spread, 1e-9))
    return resid, float(allowance)


def gps_refusal(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    max_residual_m: float,
    same_position_m: float = 1.0,
    min_fit_span_m: float = 30.0,
    sigma_m: float = 3.0,
) -> tuple[str, float]:
    """GPS test of a candidate automatic registration (camera centre (3,) world m, its GPS) against registered
    ``references`` (centre, GPS): (why it is refused, "" when it is not; its residual, m). Two tests, each refusing
    above ``max_residual_m``: the median distance residual over the references' positions
    (:func:`gps_median_residual_m`), and, when those positions span enough to fix the heading, the distance after
    the fitted rigid motion less that fit's uncertainty (:func:`gps_heading_residual_m`; it also sees mirror
    images). The residual is the larger of the two."""
    med = gps_median_residual_m(centre_in_world_m, gps, references, same_position_m)
    head, allow = gps_heading_residual_m(
        centre_in_world_m, gps, references, same_position_m, max_residual_m, min_fit_span_m, sigma_m
    )
    excess = head - allow if np.isfinite(head) else float("nan")
    residual = float(np.nanmax([med, excess])) if np.isfinite([med, excess]).any() else float("nan")
    if med > max_residual_m:
        why = (
            f"its distances to {len(references)} registered photos differ from their GPS distances by {med:.1f} m "
            f"(median over GPS positions > {max_residual_m:g} m)"
        )
        return why, residual
    if excess > max_residual_m:
        why = (
            f"its centre lies {head:.1f} m from its GPS position in the frame fitted to {len(references)} registered "
            f"photos' GPS (> {max_residual_m:g} m + {allow:.1f} m fit uncertainty)"
        )
        return why, residual
    return "", residual


def gps_check(recon: Reconstruction, idx: int, world_from_camera: np.ndarray, cfg: SfmConfig) -> str:
    """Why a candidate automatic pose of image ``idx`` contradicts GPS (:func:`gps_refusal` against the registered
    images with GPS; "" when it does not, or cannot be told: no GPS, fewer than ``cfg.gps_min_references``
    registered photos with GPS, or the check is off). Records the residual in ``gps_residual_m``."""
    im = recon.images[idx]
    if cfg.gps_max_residual_m is None or im.gps is None:
        return ""
    refs = [
        (o.world_from_camera[:3, 3], o.gps)
        for j, o in enumerate(recon.images)
        if j != idx and o.registered and o.gps is not None and o.world_from_camera is not None
    ]
    if len(refs) < max(1, cfg.gps_min_references):
        return ""
    why, im.gps_residual_m = gps_refusal(
        world_from_camera[:3, 3],
        im.gps,
        refs,
        cfg.gps_max_residual_m,
        cfg.gps_same_position_m,
        cfg.gps_min_fit_span_m,
        cfg.gps_sigma_m,
    )
    return why


def gps_apart_m(a: ImageState, b: ImageState) -> float:
    """Horizontal distance (m) between the GPS positions of two images, NaN when either has none."""
    if a.gps is None or b.gps is None:
        return float("nan")
    return horizontal_distance_m(a.gps, b.gps)


def rotation_homography_deviation(
    H_b_from_a: np.ndarray, intr_a: Intrinsics, width_b: int, height_b: int
) -> tuple[float, float]:
    """How far a pixel homography (a -> b) is from a rotation about a shared camera centre plus a zoom.

    With centred principal points, ``H' = diag(f_b, f_b, 1) R diag(1/f_a, 1/f_a, 1)``; so the rows of
    ``A = H' diag(f_a, f_a, 1)`` are ``f_b R_0, f_b R_1, R_2`` up to scale. Returns (deviation, f_b): deviation is
    the largest of |row-norm ratio - 1| of the first two rows and the rows' pairwise |cosines|.
    """
    Ta = np.array([[1, 0, -intr_a.cx_px], [0, 1, -intr_a.cy_px], [0, 0, 1.0]])
    Tb = np.array([[1, 0, -(width_b - 1) / 2], [0, 1, -(height_b - 1) / 2], [0, 0, 1.0]])
    A = Tb @ H_b_from_a @ np.linalg.inv(Ta) @ np.diag([intr_a.f_px, intr_a.f_px, 1.0])
    n = np.linalg.norm(A, axis=1)
    if np.any(n < 1e-12):
        return float("inf"), float("nan")
    U = A / n[:, None]
    cos = [abs(U[0] @ U[1]), abs(U[0] @ U[2]), abs(U[1] @ U[2])]
    dev = max(abs(n[0] / n[1] - 1.0), *cos)
    return float(dev), float((n[0] + n[1]) / 2 / n[2])


def try_homography_transfer(recon: Reconstruction, anchor_idx: int, idx: int, cfg: SfmConfig) -> bool:
    """Register ``idx`` by warping the clicks of ``anchor_idx`` through a homography fitting >= 80 % of their
    matches, then PnP on the warped clicks inside the image (>= 4). Returns True when registered."""
    a, im = recon.images[anchor_idx], recon.images[idx]
    p = recon.pair(anchor_idx, idx)
    if p is None or a.clicks is None or len(p[0]) < cfg.homography_min_matches:
        return False
    # The transfer's premise is the same viewpoint; GPS fixes far apart say otherwise (a repeated print, e.g. site
    # hoarding, gives one homography for most matches of two photos taken 50 m apart, and no image test can tell).
    apart = gps_apart_m(a, im)
    if cfg.gps_max_homography_distance_m is not None and apart > cfg.gps_max_homography_distance_m:
        im.message = f"homography from {a.name} refused: GPS positions {apart:.0f} m apart"
        return False
    m, _ = p
    thr = max(1.0, cfg.homography_threshold_frac * im.width_px)
    H, ratio = homography_inlier_ratio(a.features.keypoints_px, im.features.keypoints_px, m, thr)
    if H is None or ratio < cfg.homography_min_inlier_ratio:
        return False
    # A plane (a facade) also gives one homography for most matches from far-apart viewpoints; transferring
    # clicks off that plane would then be wrong. Only rotation(+zoom)-like homographies qualify.
    dev, _ = rotation_homography_deviation(H, a.intrinsics, im.width_px, im.height_px)
    if dev > cfg.homography_max_rotation_deviation:
        return False
    keep = a.click_inliers if a.click_inliers is not None else np.ones(len(a.clicks[0]), bool)
    px_a, world = a.clicks[0][keep], a.clicks[1][keep]
    warped = cv2.perspectiveTransform(px_a.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    inside = (
        np.all(np.isfinite(warped), axis=1)
        & (warped[:, 0] >= -0.5)
        & (warped[:, 1] >= -0.5)
        & (warped[:, 0] <= im.width_px - 0.5)
        & (warped[:, 1] <= im.height_px - 0.5)
    )
    if inside.sum() < 4:
        return False
    try:
        sol = solve_anchor(
            warped[inside],
            world[inside],
            im.width_px,
            im.height_px,
            solve_distortion=cfg.anchor_distortion,
            **_anchor_focal_kwargs(im, cfg),
        )
    except DegenerateAnchors:
        return False
    intr, world_from_camera, rms = sol.intrinsics, sol.world_from_camera, sol.rms_px
    centre = a.world_from_camera[:3, 3] if cfg.homography_shares_centre else world_from_camera[:3, 3]
    why = gps_check(recon, idx, cam.rigid(np.eye(3), centre), cfg)
    if why:
        im.message = f"homography from {a.name} refused: {why}"
        return False
    im.focal_prior_rejected = sol.focal_prior_rejected
    if cfg.homography_shares_centre:
        # The homography says: the same viewpoint as the anchor, rotated (and zoomed). Solving a full pose from
        # the warped clicks would let the centre wander along the clicks' weak direction (clicks bunched in
        # the middle of the frame); keep the anchor's centre and solve only rotation and focal.
        ok = ~sol.outlier_mask
        intr, world_from_camera, rms = _solve_rotation_about_centre(
            warped[inside][ok], world[inside][ok], sol, a.world_from_camera[:3, 3], im, cfg
        )
        im.centre_source = anchor_idx
    im.intrinsics, im.world_from_camera = intr, world_from_camera
    im.status, im.method = "auto", "homography"
    im.solved_focal_px = intr.f_px if sol.focal_solved else None
    im.clicks, im.click_inliers = (warped[inside], world[inside]), ~sol.outlier_mask
    im.num_inliers, im.rms_px = int(inside.sum()), rms
    im.message = f"homography from {a.name} ({ratio:.0%} inliers), {int(inside.sum())} warped clicks"
    return True


def _solve_rotation_about_centre(
    px: np.ndarray, world: np.ndarray, sol: AnchorSolution, centre_in_world: np.ndarray, im: ImageState, cfg: SfmConfig
) -> tuple[Intrinsics, np.ndarray, float]:
    """Rotation (and focal) of a camera at a known centre (3,) world from clicks pixels (N, 2) <-> world (N, 3),
    starting from an anchor solution; the focal is solved under the image's focal prior (free without one).
    Returns (intrinsics, world_from_camera (4, 4), rms px)."""
    intr0 = sol.intrinsics
    R0 = sol.world_from_camera[:3, :3].T  # camera_from_world rotation
    d = world - centre_in_world
    c = np.array([intr0.cx_px, intr0.cy_px])
    sigma = _focal_sigma_frac(im, cfg)
    f_ref = focal_prior(im, cfg)

    def res(x: np.ndarray) -> np.ndarray:
        R = cam.rodrigues_to_matrix(x[:3]) @ R0
        p = d @ R.T
        z = np.where(np.abs(p[:, 2]) < 1e-9, 1e-9, p[:, 2])
        xy = cam.distort_normalized(p[:, :2] / z[:, None], intr0.k1, intr0.k2)
        r = (np.exp(x[3]) * xy + c - px).ravel()
        if np.isfinite(sigma):
            r = np.concatenate([r, [(x[3] - np.log(f_ref)) / sigma]])
        return r

    x = least_squares(res, np.array([0.0, 0.0, 0.0, np.log(intr0.f_px)]), method="lm", x_scale="jac", max_nfev=200).x
    R = cam.rodrigues_to_matrix(x[:3]) @ R0
    f = float(np.exp(x[3]))
    intr = cam.centered_intrinsics(im.width_px, im.height_px, f, intr0.k1, intr0.k2)
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3] = R.T
    world_from_camera[:3, 3] = centre_in_world
    r = res(x)[: 2 * len(px)].reshape(-1, 2)
    return intr, world_from_camera, float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def _epipolar_constraints(recon: Reconstruction, idx: int) -> tuple[np.ndarray, np.ndarray]:
    """Model points (K, 3) of anchor clicks and their epipolar lines (K, 3) in image ``idx`` (normalised so
    a·u + b·v + c is a distance in pixels)."""
    pts, lines = [], []
    for a_idx, a in enumerate(recon.images):
        if a.status != "anchor" or a.clicks is None or a_idx == idx:
            continue
        p = recon.pair(a_idx, idx)
        if p is None:
            continue
        _, F = p  # x_idx^T F x_a = 0
        keep = a.click_inliers if a.click_inliers is not None else np.ones(len(a.clicks[0]), bool)
        x_a = np.c_[a.clicks[0][keep], np.ones(int(keep.sum()))]
        ln = x_a @ F.T
        ln /= np.maximum(np.linalg.norm(ln[:, :2], axis=1, keepdims=True), 1e-12)
        pts.append(a.clicks[1][keep])
        lines.append(ln)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.vstack(pts), np.vstack(lines)


def _project(intr: Intrinsics, rvec: np.ndarray, t: np.ndarray, f: float, pts: np.ndarray) -> np.ndarray:
    R = cam.rodrigues_to_matrix(rvec)
    p = pts @ R.T + t
    xy = p[:, :2] / np.maximum(p[:, 2:3], 1e-9)
    r2 = np.sum(xy * xy, axis=1, keepdims=True)
    xy = xy * (1 + intr.k1 * r2 + intr.k2 * r2 * r2)
    return xy * np.array([f, f * intr.fy_over_fx]) + np.array([intr.cx_px, intr.cy_px])


def solve_pose_epipolar(
    intr: Intrinsics,
    rvec0: np.ndarray,
    t0: np.ndarray,
    points_in_world: np.ndarray,
    pixels_px: np.ndarray,
    click_points_in_world: np.ndarray,
    click_lines: np.ndarray,
    epipolar_weight: float,
    solve_focal: bool,
    loss_scale_px: float,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The paper's constrained PnP: min over (R, t[, f]) of robust reprojection error of (N, 3) points to their
    pixels plus the distance of projected click model points (K, 3) to their epipolar lines (K, 3)."""

    def res(x: np.ndarray) -> np.ndarray:
        f = float(np.exp(x[6])) if solve_focal else intr.f_px
        r = (_project(intr, x[:3], x[3:6], f, points_in_world) - pixels_px).ravel()
        if len(click_lines):
            q = _project(intr, x[:3], x[3:6], f, click_points_in_world)
            d = np.sum(q * click_lines[:, :2], axis=1)
            r = np.concatenate([r, epipolar_weight * (d + click_lines[:, 2])])
        return r

    x0 = np.concatenate([rvec0, t0] + ([[np.log(intr.f_px)]] if solve_focal else []))
    sol = least_squares(res, x0, method="trf", loss="soft_l1", f_scale=loss_scale_px, x_scale="jac", max_nfev=100)
    f = float(np.exp(sol.x[6])) if solve_focal else intr.f_px
    return sol.x[:3], sol.x[3:6], f


def _pose_pair_agreement(
    recon: Reconstruction, idx: int, intr: Intrinsics, world_from_camera: np.ndarray, thr_px: float
) -> float:
    """Fraction of the verified matches between image ``idx`` and registered images whose epipolar distance (px,
    in image ``idx``) under the candidate pose is below ``thr_px`` (1.0 without such pairs). A pose fitted to
    matches on repeated texture (the same lettering on two sides of a site) disagrees with the other matches."""
    n_ok, n_all = 0, 0
    for j in recon.registered_indices():
        if j == idx:
            continue
        p = recon.pair(j, idx)
        if p is None:
            continue
        m, _ = p
        o = recon.images[j]
        xj = cam.pixels_to_normalized(o.intrinsics, o.features.keypoints_px[m[:, 0]])
        xi = cam.pixels_to_normalized(intr, recon.images[idx].features.keypoints_px[m[:, 1]])
        T = cam.invert_rigid(world_from_camera) @ o.world_from_camera  # camera idx from camera j
        tx = np.array([[0, -T[2, 3], T[1, 3]], [T[2, 3], 0, -T[0, 3]], [-T[1, 3], T[0, 3], 0]])
        E = tx @ T[:3, :3]
        ln = np.c_[xj, np.ones(len(xj))] @ E.T
        d = np.abs(np.sum(ln[:, :2] * xi, axis=1) + ln[:, 2]) / np.maximum(np.linalg.norm(ln[:, :2], axis=1), 1e-12)
        n_ok += int(np.sum(d * intr.f_px < thr_px))
        n_all += len(m)
    return n_ok / n_all if n_all else 1.0


def relative_rotation_deg(recon: Reconstruction, a: int, b: int, cfg: SfmConfig) -> float:
    """Rotation angle (deg) between the cameras of images ``a`` and ``b`` from their verified matches: the pair's
    fundamental matrix made essential with each image's pinhole matrix (registered: its intrinsics without
    distortion; else its focal prior and a centred principal point), decomposed with the cheirality test. NaN
    without a pair."""
    p = recon.pair(a, b)
    if p is None or len(p[0]) < 8:
        return float("nan")
    m, F = p
    K, xy = [], []
    for i, col in ((a, 0), (b, 1)):
        im = recon.images[i]
        intr = im.intrinsics
        if intr is None:
            intr = cam.centered_intrinsics(im.width_px, im.height_px, focal_prior(im, cfg))
        Ki = cam.K_matrix(intr)
        px = im.features.keypoints_px[m[:, col]].astype(np.float64)
        K.append(Ki)
        xy.append((px - Ki[:2, 2]) / np.diag(Ki)[:2])
    E = K[1].T @ F @ K[0]
    _, R, _, _ = cv2.recoverPose(E, xy[0], xy[1], np.eye(3))
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def anchor_request_order(recon: Reconstruction, unreg: list[int], counts: dict[int, int], cfg: SfmConfig) -> list[int]:
    """Unregistered images in the order anchor clicks are asked for: fewest matched tracks first (the paper). While
    nothing is triangulated yet (every image ties at zero: the second anchor, which fixes the model frame with the
    first), the image most strongly linked to a registered image goes first: over registered images sharing
    >= ``cfg.anchor_request_min_shared_matches`` verified matches, the largest matches x sin^2 of the relative
    rotation (a point's depth precision from two rays grows with the sine of their angle); images without such a
    link last. Other ties in collection order."""
    bootstrap = not np.isfinite(recon.points).all(axis=1).any()
    if cfg.anchor_request_min_shared_matches <= 0 or not bootstrap:
        return sorted(unreg, key=lambda i: counts[i])
    registered = recon.registered_indices()
    strength: dict[int, float] = {}
    for u in unreg:
        scores = [-1.0]
        for r in registered:
            p = recon.pair(r, u)
            if p is not None and len(p[0]) >= cfg.anchor_request_min_shared_matches:
                angle = relative_rotation_deg(recon, r, u, cfg)
                if np.isfinite(angle):
                    scores.append(len(p[0]) * np.sin(np.radians(min(angle, 90.0))) ** 2)
        strength[u] = max(scores)
    return sorted(unreg, key=lambda i: (counts[i], -strength[i]))


def register_image_pnp(recon: Reconstruction, idx: int, cfg: SfmConfig) -> bool:
    """Register image ``idx`` from its matches to triangulated tracks: PnP-RANSAC (inliers within
    ``pnp_inlier_frac`` of the width) then the epipolar-constrained refinement. Returns True on success."""
    im = recon.images[idx]
    ft = recon.feature_track[idx]
    feats = np.nonzero(ft >= 0)[0]
    tr = ft[feats]
    ok = np.all(np.isfinite(recon.points[tr]), axis=1)
    feats, tr = feats[ok], tr[ok]
    im.num_matched_tracks = len(feats)
    if len(feats) < max(cfg.min_pnp_inliers, 6):
        im.message = f"only {len(feats)} matches to triangulated tracks"
        return False
    obj = recon.points[tr].astype(np.float64)
    img = im.features.keypoints_px[feats].astype(np.float64)
    f0 = focal_prior(im, cfg)
    intr = cam.centered_intrinsics(im.width_px, im.height_px, f0)
    K = cam.K_matrix(intr)
    thr = cfg.pnp_inlier_frac * im.width_px
    best = None
    # Try the prior focal and, if that registers poorly, a few alternatives (a wrong prior breaks RANSAC).
    for f_try in (f0, f0 * 0.7, f0 * 1.4, f0 * 2.0, f0 * 0.5):
        Kt = K.copy()
        Kt[0, 0] = Kt[1, 1] = f_try
        ok_r, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, Kt, None, iterationsCount=2000, reprojectionError=thr, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP
        )
        n_inl = 0 if (not ok_r or inl is None) else len(inl)
        if best is None or n_inl > best[0]:
            best = (n_inl, f_try, rvec, tvec, inl)
        if n_inl >= 0.5 * len(obj):
            break
    n_inl, f_try, rvec, tvec, inl = best
    if n_inl < cfg.min_pnp_inliers:
        im.message = f"PnP found {n_inl} inliers among {len(obj)} track matches (< {cfg.min_pnp_inliers})"
        return False
    inl = inl.ravel()
    intr = cam.centered_intrinsics(im.width_px, im.height_px, f_try)
    cpts, clines = _epipolar_constraints(recon, idx)
    rv, tv, f = solve_pose_epipolar(
        intr,
        rvec.ravel(),
        tvec.ravel(),
        obj[inl],
        img[inl],
        cpts,
        clines,
        cfg.epipolar_weight,
        solve_focal=n_inl >= 50 and not np.isfinite(_focal_sigma_frac(im, cfg)),
        loss_scale_px=cfg.loss_scale_px,
    )
    intr = cam.centered_intrinsics(im.width_px, im.height_px, f)
    proj = _project(intr, rv, tv, f, obj)
    err = np.linalg.norm(proj - img, axis=1)
    R = cam.rodrigues_to_matrix(rv)
    z = obj @ R.T[:, 2] + tv[2]
    inliers = (err < thr) & (z > 0)
    if inliers.sum() < cfg.min_pnp_inliers:
        im.message = f"refined pose keeps {int(inliers.sum())} inliers (< {cfg.min_pnp_inliers})"
        return False
    agree = _pose_pair_agreement(recon, idx, intr, cam.invert_rigid(cam.rigid(R, tv)), 2 * thr)
    if agree < cfg.min_pose_pair_agreement:
        im.message = (
            f"PnP pose explains only {agree:.0%} of the verified matches to registered images "
            f"(< {cfg.min_pose_pair_agreement:.0%}; repeated texture?)"
        )
        return False
    world_from_camera = cam.invert_rigid(cam.rigid(R, tv))
    why = gps_check(recon, idx, world_from_camera, cfg)
    if why:
        im.message = f"PnP pose ({int(inliers.sum())}/{len(obj)} inliers) refused: {why}"
        return False
    im.intrinsics = intr
    im.world_from_camera = world_from_camera
    im.status, im.method = "auto", "pnp"
    im.num_inliers = int(inliers.sum())
    im.rms_px = float(np.sqrt(np.mean(err[inliers] ** 2)))
    im.message = f"PnP {int(inliers.sum())}/{len(obj)} inliers, {len(clines)} epipolar click constraints"
    # Drop this image's outlier observations from their tracks.
    for fi, t in zip(feats[~inliers], tr[~inliers], strict=True):
        recon.track_obs[t].pop(idx, None)
        recon.feature_track[idx][fi] = -1
    return True


# ---------------------------------------------------------------------------
# Triangulation and bundle adjustment
# ---------------------------------------------------------------------------


def _obs_thr(im: ImageState, cfg: SfmConfig) -> float:
    return max(cfg.min_obs_error_px, cfg.max_obs_error_frac * im.width_px)


def _rays(recon: Reconstruction, img_idx: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (M, 3) and unit world ray directions (M, 3) of pixels (M, 2) in images ``img_idx``."""
    centers = np.zeros((len(img_idx), 3))
    dirs = np.zeros((len(img_idx), 3))
    for i in np.unique(img_idx):
        sel = img_idx == i
        im = recon.images[i]
        xy = cam.pixels_to_normalized(im.intrinsics, px[sel])
        d = np.c_[xy, np.ones(len(xy))] @ im.world_from_camera[:3, :3].T
        dirs[sel] = d / np.linalg.norm(d, axis=1, keepdims=True)
        centers[sel] = im.world_from_camera[:3, 3]
    return centers, dirs


def _flat_obs(recon: Reconstruction, tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations of ``tracks`` as flat arrays (track, image, feature) (M,), in each track's dict order."""
    tracks = np.asarray(tracks, dtype=np.int64).ravel()
    imgs: list[int] = []
    feats: list[int] = []
    lens = np.empty(len(tracks), dtype=np.int64)
    obs = recon.track_obs
    for k, t in enumerate(tracks.tolist()):
        d = obs[t]
        imgs.extend(d)
        feats.extend(d.values())
        lens[k] = len(d)
    return np.repeat(tracks, lens), np.array(imgs, dtype=np.int64), np.array(feats, dtype=np.int64)


def _obs_pixels(recon: Reconstruction, img: np.ndarray, feat: np.ndarray) -> np.ndarray:
    """Keypoints (M, 2) float64 px of observations (image, feature)."""
    px = np.zeros((len(img), 2))
    for i in np.unique(img):
        sel = img == i
        px[sel] = recon.images[i].features.keypoints_px[feat[sel]]
    return px


def _obs_thr_per_image(recon: Reconstruction, cfg: SfmConfig) -> np.ndarray:
    return np.array([_obs_thr(im, cfg) for im in recon.images])


def triangulate_tracks(
    recon: Reconstruction, cfg: SfmConfig, retriangulate: bool = False, only: list[int] | None = None
) -> int:
    """Triangulate untriangulated tracks seen by >= 2 registered images (midpoint of rays, all at once), keeping
    those whose rays span >= ``min_triangulation_angle_deg`` and that reproject within threshold in front of
    every camera. ``retriangulate`` redoes triangulated ones too; ``only`` restricts to these tracks. Returns the
    number of points (re)made."""
    reg = np.array([im.registered for im in recon.images], dtype=bool)
    candidates = np.arange(len(recon.track_obs)) if only is None else np.asarray(only, dtype=np.int64)
    if len(candidates) == 0 or not reg.any():
        return 0
    if not retriangulate:
        candidates = candidates[~np.all(np.isfinite(recon.points[candidates]), axis=1)]
    tids_a, iids_a, fids_a = _flat_obs(recon, candidates)
    keep = reg[iids_a] if len(iids_a) else np.zeros(0, bool)
    tids_a, iids_a, fids_a = tids_a[keep], iids_a[keep], fids_a[keep]
    if len(tids_a) == 0:
        return 0
    uniq, inv, cnt = np.unique(tids_a, return_inverse=True, return_counts=True)
    two = cnt[inv] >= 2
    tids_a, iids_a, fids_a = tids_a[two], iids_a[two], fids_a[two]
    if len(tids_a) == 0:
        return 0
    px = _obs_pixels(recon, iids_a, fids_a)
    C, D = _rays(recon, iids_a, px)
    uniq, inv = np.unique(tids_a, return_inverse=True)
    n = len(uniq)
    M = np.eye(3)[None] - D[:, :, None] * D[:, None, :]
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(A, inv, M)
    np.add.at(b, inv, np.einsum("nij,nj->ni", M, C))
    det = np.linalg.det(A)
    good = np.abs(det) > 1e-12
    X = np.full((n, 3), np.nan)
    X[good] = np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0]
    # Ray span: max angle between any ray and the track's first ray, as a bound.
    first = np.zeros(n, int)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    cosang = np.sum(D * D[first][inv], axis=1)
    min_cos = np.ones(n)
    np.minimum.at(min_cos, inv, cosang)
    wide = min_cos < np.cos(np.radians(cfg.min_triangulation_angle_deg))
    # Reprojection and cheirality per observation.
    bad = np.zeros(n, bool)
    thr = _obs_thr_per_image(recon, cfg)
    for i in np.unique(iids_a):
        sel = np.nonzero(iids_a == i)[0]
        im = recon.images[i]
        proj, z = cam.project_points(im.intrinsics, cam.invert_rigid(im.world_from_camera), X[inv[sel]])
        e = np.linalg.norm(proj - px[sel], axis=1)
        fail = ~(np.isfinite(e) & (e < thr[i]) & (z > 0))
        np.logical_or.at(bad, inv[sel], fail)
    accept = good & wide & ~bad
    if retriangulate:
        recon.points[uniq[~accept]] = np.nan
    acc_t = uniq[accept]
    new = len(acc_t) if retriangulate else int(np.sum(~np.all(np.isfinite(recon.points[acc_t]), axis=1)))
    recon.points[acc_t] = X[accept]
    # Colour from each track's first observation (in dict order).
    first_obs = np.array([next(iter(recon.track_obs[t].items())) for t in acc_t.tolist()], np.int64).reshape(-1, 2)
    for i in np.unique(first_obs[:, 0]):
        cols = recon.images[i].colors_rgb_u8
        if cols is not None:
            sel = first_obs[:, 0] == i
            recon.colors[acc_t[sel]] = cols[first_obs[sel, 1]]
    return new


def drop_runaway_points(recon: Reconstruction, tracks: np.ndarray, factor: float = 1e3) -> int:
    """Untriangulate (NaN) those of ``tracks`` whose point is not finite or lies more than ``factor`` times the
    median point-to-camera distance of ``tracks`` from every registered camera that observes it. A point carried on
    an anchor's ray whose other views hardly constrain its depth can run off towards infinity, where it still
    reprojects (its rays are then nearly parallel) and a trust-region step no longer moves it; seen on the default
    synthetic site (a depth of 1e141). Its track stays and can be triangulated again. Returns the number dropped."""
    tracks = np.asarray(tracks, np.int64)
    if len(tracks) == 0:
        return 0
    reg = np.array([im.registered for im in recon.images], dtype=bool)
    t_ids, i_ids, _ = _flat_obs(recon, tracks)
    on = reg[i_ids] if len(i_ids) else np.zeros(0, bool)
    t_ids, i_ids = t_ids[on], i_ids[on]
    centres = np.array([im.world_from_camera[:3, 3] if im.registered else np.zeros(3) for im in recon.images])
    with np.errstate(over="ignore", invalid="ignore"):
        dist_m = np.linalg.norm(recon.points[t_ids] - centres[i_ids], axis=1)
    dist_m = np.where(np.isfinite(dist_m), dist_m, np.inf)
    nearest_m = np.full(len(recon.points), np.inf)
    np.minimum.at(nearest_m, t_ids, dist_m)
    nearest_m = nearest_m[tracks]
    finite = np.isfinite(nearest_m)
    if not np.any(finite):
        return 0
    scale_m = float(np.median(nearest_m[finite]))
    observed = np.isin(tracks, t_ids)
    bad = tracks[observed & ~(nearest_m <= factor * scale_m)]
    recon.points[bad] = np.nan
    return len(bad)


def bundle(
    recon: Reconstruction,
    cfg: SfmConfig,
    window: list[int] | None = None,
    fixed_anchors: set[int] | None = None,
    covariance: bool = False,
) -> dict[str, float]:
    """Constrained bundle adjustment over all registered images, or a local one where only images in ``window``
    (and the points they see) move. Then drops observations beyond threshold and points left with < 2 views.
    ``covariance`` (with ``cfg.ba_solver == "schur"``): set each moved camera's ``centre_sigma_m``.
    Returns stats (initial/final rms px, observations removed, points, observations, initial/final total squared
    error of features and clicks px^2 and the number of those residuals)."""
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
    o_t, o_i, o_f = _flat_obs(recon, tri)
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
    obs_x_a = _obs_pixels(recon, obs_img_a, obs_feat_a)
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
    intr = [recon.images[i].intrinsics for i in reg]
    click_c, click_w, click_x = [], [], []
    for i in reg:
        im = recon.images[i]
        if im.clicks is not None:
            keep = im.click_inliers if im.click_inliers is not None else np.ones(len(im.clicks[0]), bool)
            click_c += [cam_of[i]] * int(keep.sum())
            click_w.append(im.clicks[1][keep])
            click_x.append(im.clicks[0][keep])
    point_ref = ref_cam
    # In a local window, points fixed when they are not seen by a movable image (already filtered), anchors'
    # rays are used only for movable anchors.
    pose_fixed = np.array([(i in anchors) or (i not in movable) for i in reg])
    centre_fixed = np.array([recon.images[i].centre_source in anchors for i in reg])
    intr_fixed = np.array([i not in movable for i in reg])
    prob = BundleProblem(
        camera_from_world=np.stack([cam.invert_rigid(recon.images[i].world_from_camera) for i in reg]),
        f_px=np.array([x.f_px for x in intr]),
        cx_px=np.array([x.cx_px for x in intr]),
        cy_px=np.array([x.cy_px for x in intr]),
        k1=np.array([x.k1 for x in intr]),
        k2=np.array([x.k2 for x in intr]),
        fy_over_fx=np.array([x.fy_over_fx for x in intr]),
        pose_fixed=pose_fixed,
        intrinsics_fixed=intr_fixed,
        points_in_world=recon.points[pt_list] if pt_list else np.zeros((0, 3)),
        point_fixed=np.zeros(len(pt_list), bool),
        point_ref_cam=np.where(point_ref >= 0, point_ref, -1) if len(point_ref) else np.zeros(0, int),
        point_ref_px=ref_px,
        obs_cam=obs_c,
        obs_point=obs_p_a,
        obs_px=obs_x_a,
        click_cam=np.array(click_c, int),
        click_world=np.vstack(click_w) if click_w else np.zeros((0, 3)),
        click_px=np.vstack(click_x) if click_x else np.zeros((0, 2)),
        centre_fixed=centre_fixed,
        pp_group=principal_point_groups(recon, reg) if cfg.share_principal_point else None,
        intr_group=principal_point_groups(recon, reg) if cfg.share_intrinsics else None,
    )
    # Focal priors: the external ones (user / EXIF) only. A focal solved from an image's clicks is not a prior:
    # the clicks are residuals of this adjustment already (counting them twice pinned a focal that absorbed
    # model error, e.g. an off-centre principal point, at the user's tight sigma).
    reg_ims = [recon.images[i] for i in reg]
    f_prior = np.array([focal_prior(im, cfg) for im in reg_ims])
    sigma = np.array([_focal_sigma_frac(recon.images[i], cfg) for i in reg]) * f_prior
    opts = BundleOptions(
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
            fy_over_fx=float(res.fy_over_fx[c]) if res.fy_over_fx is not None else im.intrinsics.fy_over_fx,
        )
        if i not in anchors:
            im.world_from_camera = cam.invert_rigid(res.camera_from_world[c])
    if pt_list:
        recon.points[pt_list] = res.points_in_world
    # Outlier observations.
    thr_img = _obs_thr_per_image(recon, cfg)
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
        recon.points[pt_arr[remaining < 2]] = np.nan
        drop_runaway_points(recon, pt_arr)
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


def release_anchors_if_significant(recon: Reconstruction, cfg: SfmConfig) -> float:
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
    held = _held_anchors(recon, cfg)
    tracked = [i for i in reg if recon.images[i].status == "anchor" and i not in held]
    if not tracked or len(reg) < 2:
        return float("nan")
    n_grp = len(set(principal_point_groups(recon, reg).tolist())) if cfg.share_principal_point else len(reg)
    snap = _snapshot(recon)
    # Exact steps (Schur complement): the shared principal point and the anchors' rotations form a soft mode that
    # capped, inexact LSMR steps barely move (fountain-P11: 2 px of a 22 px offset found with the cap, 20 without).
    use_pp, use_asp = True, bool(cfg.release_aspect)

    def adjust(share: bool = False) -> dict[str, float]:
        release = {
            "refine_principal_point": use_pp,
            "refine_aspect": use_asp,
            "ba_solver": "schur",
            "ba_points_per_image": cfg.release_points_per_image,
            "share_intrinsics": share,
        }
        recon.release_settings = release
        return bundle(recon, SfmConfig(**{**cfg.__dict__, **release}), fixed_anchors=held, covariance=True)

    stats = adjust()
    wald = stats.get("principal_point_wald", float("nan"))
    wald_a = stats.get("aspect_wald", float("nan"))
    # Parameters whose offsets are not significant are dropped and the release redone without them (a centred lens
    # would only trade its principal point for a common rotation of the cameras within the clicks' noise).
    for _ in range(2):
        drop_pp = use_pp and not (stats.get("principal_point_wald", np.nan) > 9.0 * 2 * n_grp)
        drop_asp = use_asp and not (stats.get("aspect_wald", np.nan) > 9.0 * n_grp)
        if not (drop_pp or drop_asp):
            break
        _restore(recon, snap)
        snap = _snapshot(recon)
        use_pp, use_asp = use_pp and not drop_pp, use_asp and not drop_asp
        stats = adjust()
    recon.principal_point_wald = float(wald)
    recon.aspect_wald = float(wald_a)
    n_added = 6 * len(tracked) + n_grp * (2 * int(use_pp) + int(use_asp))
    s0, s1, m = stats.get("initial_sse_px2", 0.0), stats.get("final_sse_px2", 0.0), stats.get("residuals", 0.0)
    if not stats or m <= 0 or s1 <= 0:
        _restore(recon, snap)
        return float("nan")
    score = (s0 - s1) / (n_added * s1 / m)
    if not score > ANCHOR_RELEASE_THRESHOLD:
        _restore(recon, snap)
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
        free = _snapshot(recon)
        _restore(recon, snap)
        snap = _snapshot(recon)
        shared = adjust(share=True)
        dof = n_tied * (3 if cfg.refine_distortion else 1)
        lr = (shared.get("final_sse_px2", np.inf) - s1) / (s1 / max(m - dof, 1.0))
        recon.shared_intrinsics_lr = float(lr)
        recon.shared_intrinsics = bool(lr <= 9.0 * dof)
        if not recon.shared_intrinsics:
            _restore(recon, free)
            recon.release_settings = {**recon.release_settings, "share_intrinsics": False}
    return float(score)


def _held_anchors(recon: Reconstruction, cfg: SfmConfig) -> set[int]:
    """Registered anchors observing fewer than ``cfg.release_min_observations`` triangulated points: the final
    adjustment keeps their poses fixed (their tracks cannot check their clicks)."""
    return {
        i
        for i in recon.registered_indices()
        if recon.images[i].status == "anchor" and matched_track_count(recon, i) < cfg.release_min_observations
    }


def add_clicks_for_accuracy(
    recon: Reconstruction, cfg: SfmConfig, clicks_for: Callable[[int, str], Clicks | None]
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
    release_cfg = SfmConfig(**{**cfg.__dict__, **recon.release_settings})
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
        bundle(recon, release_cfg, fixed_anchors=_held_anchors(recon, cfg), covariance=True)
    return added, None


def click_disagreement_px(im: ImageState, clicks: Clicks) -> float:
    """Median distance (px) between clicked pixels and their model points projected under image ``im``'s current
    pose and intrinsics (points behind the camera count as infinitely far)."""
    return cam.median_click_error_px(im.intrinsics, im.world_from_camera, clicks[0], clicks[1])


def _snapshot(recon: Reconstruction) -> tuple:
    ims = []
    for im in recon.images:
        T = None if im.world_from_camera is None else im.world_from_camera.copy()
        ims.append((im.intrinsics, T, im.rms_px, im.num_inliers, im.centre_sigma_m))
    return (
        ims,
        recon.points.copy(),
        [dict(d) for d in recon.track_obs],
        [ft.copy() for ft in recon.feature_track],
    )


def _restore(recon: Reconstruction, snap: tuple) -> None:
    ims, points, track_obs, feature_track = snap
    for im, (intr, T, rms, n_inl, sig) in zip(recon.images, ims, strict=True):
        im.intrinsics, im.world_from_camera, im.rms_px, im.num_inliers, im.centre_sigma_m = intr, T, rms, n_inl, sig
    recon.points, recon.track_obs, recon.feature_track = points, track_obs, feature_track


def principal_point_groups(recon: Reconstruction, indices: list[int]) -> np.ndarray:
    """Group id per image of ``indices``: images with the same size and focal prior (EXIF) share one."""
    keys: dict[tuple, int] = {}
    out = []
    for i in indices:
        im = recon.images[i]
        f = None if im.focal_prior_px is None else round(float(im.focal_prior_px), 1)
        out.append(keys.setdefault((im.width_px, im.height_px, f), len(keys)))
    return np.array(out, int)


def _image_tracks(recon: Reconstruction, images: list[int]) -> list[int]:
    """Tracks (sorted ids) with an observation in any of ``images``."""
    ft = [recon.feature_track[i] for i in images]
    ids = np.concatenate([t[t >= 0] for t in ft]) if ft else np.zeros(0, np.int64)
    return np.unique(ids).tolist()


def local_window(recon: Reconstruction, idx: int, size: int) -> list[int]:
    """Image ``idx`` and the registered images sharing the most triangulated tracks with it (``size`` in all)."""
    shared: dict[int, int] = {}
    for t in recon.feature_track[idx]:
        if t < 0 or not np.isfinite(recon.points[t, 0]):
            continue
        for i in recon.track_obs[t]:
            if i != idx and recon.images[i].registered:
                shared[i] = shared.get(i, 0) + 1
    best = sorted(shared, key=lambda i: -shared[i])[: max(0, size - 1)]
    return [idx, *best]


# ---------------------------------------------------------------------------
# The batch algorithm
# ---------------------------------------------------------------------------


def reconstruct(
    recon: Reconstruction,
    anchors: dict[str, Clicks],
    cfg: SfmConfig,
    request_anchor: Callable[[str, str, int], Clicks | None] | None = None,
    progress: Callable[[str, int], None] | None = None,
    match_progress: Callable[[], None] | None = None,
) -> Reconstruction:
    """Run Algorithm 1 on a reconstruction whose images were added with :func:`add_image`.

    ``anchors``: clicks by image name; the first one (or all with ``cfg.use_all_anchors``) starts the
    reconstruction, the others are used when an image needs an anchor. ``request_anchor(name, reason,
    num_tracks)`` may supply clicks for other images (None: the image stays unregistered for now); every request
    is also recorded in ``recon.needs_anchor``. ``progress(stage, registered_count)`` is called after each step.
    """
    t_start = time.perf_counter()
    names = [im.name for im in recon.images]
    unknown = [n for n in anchors if n not in names]
    if unknown:
        raise ValueError(f"anchor clicks for images not in the collection: {', '.join(unknown[:5])}")
    if not anchors:
        raise ValueError("at least one anchor image with clicks is needed")
    pending = dict(anchors)

    # Matching.
    t0 = time.perf_counter()
    if not recon.pairs:
        feats = [im.features for im in recon.images]
        pairs = select_pairs(feats, cfg)
        if cfg.match_pca_dims and cfg.match_pca_dims < 128:
            basis = pca_basis([f.descriptors for f in feats], cfg.match_pca_dims)
            feats = [project_pca(f, basis) for f in feats]

        def job(ij: tuple[int, int]) -> tuple[tuple[int, int], PairGeometry | None]:
            return ij, verify_pair(feats[ij[0]], feats[ij[1]], cfg)

        # Pairs run in parallel threads, each product on one BLAS thread (no oversubscription).
        with single_thread_blas(), ThreadPoolExecutor(max(1, cfg.workers)) as pool:
            for ij, g in pool.map(job, pairs):
                if g is not None:
                    recon.pairs[ij] = g
                if match_progress is not None:
                    match_progress()
    build_tracks(recon)
    recon.timings_secs["matching"] = time.perf_counter() - t0

    def note(stage: str) -> None:
        if progress is not None:
            progress(stage, len(recon.registered_indices()))

    def clicks_for(i: int, reason: str, num_tracks: int) -> Clicks | None:
        """Clicks for image ``i``: given up front (the anchor file's), else asked for (None: none to be had)."""
        name = recon.images[i].name
        clicks = pending.pop(name, None)
        if clicks is None and request_anchor is not None:
            clicks = request_anchor(name, reason, num_tracks)
        return clicks

    def recheck_with_clicks(u: int) -> bool:
        """Image ``u`` was just registered automatically: when clicks for it are at hand (given up front, not
        answers to requests) and the pose puts them further than ``click_check_max_frac`` of the width (median)
        from where they were clicked, re-register it from them (an anchor). Returns True when it was."""
        im = recon.images[u]
        if not cfg.check_auto_with_clicks or im.name not in pending:
            return False
        err = click_disagreement_px(im, pending[im.name])
        if not err > cfg.click_check_max_frac * im.width_px:
            return False
        was = f"{im.method} pose ({im.message}) put its clicks {err:.0f} px off (median)"
        clicks = pending.pop(im.name)
        im.centre_source = None
        try:
            register_anchor(recon, u, clicks, cfg)
        except DegenerateAnchors as e:
            im.status, im.method, im.world_from_camera = "failed", "", None
            im.message = f"{was}; its anchor clicks were rejected: {e}"
            return True
        im.message += f"; re-registered from its clicks: the automatic {was}"
        note(f"anchor {im.name} (automatic pose disagreed with its clicks)")
        return True

    # Initial anchors.
    first = list(pending)[: (len(pending) if cfg.use_all_anchors else 1)]
    for name in first:
        clicks = pending.pop(name)
        idx = recon.index(name)
        try:
            register_anchor(recon, idx, clicks, cfg)
        except DegenerateAnchors as e:
            recon.images[idx].status, recon.images[idx].message = "failed", f"anchor clicks rejected: {e}"
        note(f"anchor {name}")
    t_reg = time.perf_counter()
    checked_h: set[tuple[int, int]] = set()
    failed_pnp: set[int] = set()
    dirty = True  # something was added since the last full bundle adjustment
    since_full = 0
    while True:
        # Homography transfer from every clicked image to unregistered images.
        added = True
        while added:
            added = False
            for a in [i for i, im in enumerate(recon.images) if im.status == "anchor"]:
                for u in [i for i, im in enumerate(recon.images) if im.status == "unregistered"]:
                    if (a, u) in checked_h:
                        continue
                    checked_h.add((a, u))
                    if try_homography_transfer(recon, a, u, cfg):
                        added = dirty = True
                        if not recheck_with_clicks(u):
                            note(f"homography {recon.images[u].name}")
        if dirty:
            triangulate_tracks(recon, cfg)
            bundle(recon, cfg)
            triangulate_tracks(recon, cfg)
            dirty, since_full = False, 0
        unreg = [i for i, im in enumerate(recon.images) if im.status == "unregistered"]
        if not unreg:
            break
        counts = {i: matched_track_count(recon, i) for i in unreg}
        for i, c in counts.items():
            recon.images[i].num_matched_tracks = c
        candidates = [i for i in unreg if i not in failed_pnp]
        qualified = [i for i in candidates if counts[i] >= cfg.min_track_matches]
        if qualified:
            # The paper's rule: the qualifying image with the fewest matched tracks (wide baseline).
            u = min(qualified, key=lambda i: counts[i])
        else:
            # Before asking for clicks, try the best-connected image above a lower bar (PnP still has to succeed).
            weak = [i for i in candidates if counts[i] >= cfg.fallback_min_track_matches]
            u = max(weak, key=lambda i: counts[i]) if weak else -1
        if u >= 0:
            if register_image_pnp(recon, u, cfg):
                failed_pnp.clear()
                if recheck_with_clicks(u):
                    dirty = True
                    continue
                # Only tracks through the new image can have become triangulable.
                triangulate_tracks(recon, cfg, only=_image_tracks(recon, [u]))
                since_full += 1
                if since_full >= cfg.full_ba_every:
                    bundle(recon, cfg)
                    since_full = 0
                    triangulate_tracks(recon, cfg)
                else:
                    local_cfg = SfmConfig(**{**cfg.__dict__, "ba_max_nfev": cfg.local_ba_max_nfev})
                    window = local_window(recon, u, cfg.local_ba_window)
                    bundle(recon, local_cfg, window=window)
                    triangulate_tracks(recon, cfg, only=_image_tracks(recon, window))
                note(f"pnp {recon.images[u].name}")
            else:
                failed_pnp.add(u)
            continue
        # No image has enough tracks: ask for an anchor, fewest matched tracks first.
        got = False
        for u in anchor_request_order(recon, unreg, counts, cfg):
            name = recon.images[u].name
            reason = f"only {counts[u]} matches to triangulated tracks (< {cfg.min_track_matches})"
            if u in failed_pnp and recon.images[u].message:
                reason = recon.images[u].message.removeprefix("needs anchor clicks: ")
            recon.needs_anchor = [r for r in recon.needs_anchor if r[0] != name] + [(name, reason, counts[u])]
            clicks = clicks_for(u, reason, counts[u])
            if clicks is None:
                recon.images[u].message = f"needs anchor clicks: {reason}"
                continue
            try:
                register_anchor(recon, u, clicks, cfg)
            except DegenerateAnchors as e:
                recon.images[u].status, recon.images[u].message = "failed", f"anchor clicks rejected: {e}"
                continue
            failed_pnp.clear()
            got = dirty = True
            note(f"anchor {name}")
            break
        if not got:
            break
    if since_full:
        bundle(recon, cfg)
    if cfg.fix_anchor_poses and cfg.release_anchors:
        recon.anchor_release_score = release_anchors_if_significant(recon, cfg)
        recon.anchors_released = bool(recon.anchor_release_score > ANCHOR_RELEASE_THRESHOLD)
        recon.accuracy_anchors, unmet = add_clicks_for_accuracy(
            recon, cfg, lambda i, reason: clicks_for(i, reason, matched_track_count(recon, i))
        )
        for name in recon.accuracy_anchors:
            note(f"anchor {name} (accuracy)")
        if unmet is not None:
            name = recon.images[unmet[0]].name
            n = matched_track_count(recon, unmet[0])
            recon.needs_anchor = [r for r in recon.needs_anchor if r[0] != name] + [(name, unmet[1], n)]
    for i, im in enumerate(recon.images):
        if im.status == "unregistered" and i in failed_pnp and not im.message.startswith("needs"):
            im.message = "PnP failed: " + im.message
    recon.timings_secs["registration"] = time.perf_counter() - t_reg
    recon.timings_secs["total"] = time.perf_counter() - t_start
    return recon
