"""Reconstruction state: images (features, camera, status), verified pairs, tracks and their points.

``track_obs[t]`` maps image index -> feature index; ``points`` (T, 3) world (NaN while untriangulated). Pixels:
OpenCV convention. Poses: ``world_from_camera`` (4, 4), OpenCV camera frame, model units.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from constructaide import camera as cam
from constructaide.anchorsolve import AnchorSolution
from nodes.register.config import MapperConfig
from nodes.register.features import (
    Features,
)
from schemas.messages import GeoPoint, Intrinsics

Clicks = tuple[np.ndarray, np.ndarray]  # pixels (N, 2) OpenCV px, world points (N, 3) model units


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
    # Standard deviation of the clicks relative to a user's (1: clicked or warped by a rotation homography; more
    # for clicks carried into the photo by local image matching).
    click_sigma_px: float = 1.0
    anchor: AnchorSolution | None = None
    num_matched_tracks: int = 0
    # Focal solved from this image's own clicks (None when the prior was kept); informational.
    solved_focal_px: float | None = None
    # The image's clicks (or warped clicks) contradicted the focal prior: no focal prior for it any more.
    focal_prior_rejected: bool = False
    # Image whose camera centre this one shares (a rotation homography to that anchor), or None.
    centre_source: int | None = None
    # Image whose lens (distortion) this one inherited (a homography transfer from the same physical camera): the
    # adjustments hold its k1, k2 near that image's unless its own data pin them. None: its own lens.
    lens_source: int | None = None
    # EXIF GPS position, None when absent.
    gps: GeoPoint | None = None
    # Fixed camera the photo comes from (None: a phone or an unknown camera) and its capture time (UTC ns).
    camera_id: str | None = None
    capture_time_ns: int = 0
    # Median GPS distance residual (m) of the automatic registration (see gps_check), NaN when not checked.
    gps_residual_m: float = float("nan")
    # Standard deviation of the camera centre (model units; sqrt of the trace of its 3x3 covariance) from the final
    # adjustment with the anchors released (release_anchors_if_significant): what the features and clicks fix of
    # where the camera stood. NaN when not estimated (release not run or not kept, or the pose held fixed).
    centre_sigma_m: float = float("nan")
    # An anchor whose lens the adjustments hold at its click solve's (their tracks pulled its clicks off: see
    # MapperConfig.max_anchor_click_drift_px).
    lens_held: bool = False

    @property
    def width_px(self) -> int:
        return self.features.width_px

    @property
    def height_px(self) -> int:
        return self.features.height_px

    @property
    def camera(self) -> Intrinsics:
        """Intrinsics of a registered image (ValueError when it has none)."""
        if self.intrinsics is None:
            raise ValueError(f"image {self.name} has no camera")
        return self.intrinsics

    @property
    def pose(self) -> np.ndarray:
        """``world_from_camera`` (4, 4) of a registered image (ValueError when it has none)."""
        if self.world_from_camera is None:
            raise ValueError(f"image {self.name} has no pose")
        return self.world_from_camera

    @property
    def accepted_clicks(self) -> Clicks | None:
        """An anchor's clicks its solve accepted (pixels (N, 2), model points (N, 3)); None when not an anchor."""
        if self.status != "anchor" or self.clicks is None:
            return None
        keep = self.click_inliers if self.click_inliers is not None else np.ones(len(self.clicks[0]), bool)
        return np.asarray(self.clicks[0])[keep], np.asarray(self.clicks[1])[keep]

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
    # Per-track arrays live in buffers that grow by doubling (tracks are added one at a time while streaming); the
    # properties below (points (T, 3), colors (T, 3) u8, point_from_model / point_confirmed / point_verified (T,))
    # are views of their first T rows.
    _buf: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    _n_tracks: int = 0
    _index: dict[str, int] = field(default_factory=dict, repr=False)
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
    # MapperConfig fields the kept release adjusted with (principal points, aspects, shared intrinsics), {} otherwise.
    release_settings: dict = field(default_factory=dict)
    # Images given clicks to meet MapperConfig.target_centre_sigma, in order.
    accuracy_anchors: list[str] = field(default_factory=list)
    # Whether point_verified has been computed (densification ran): until then it is all False and means unknown.
    densified: bool = False
    # Same for the aspect ratios (fy / fx, one per camera group) in the release, NaN if not refined there.
    aspect_wald: float = float("nan")

    def index(self, name: str) -> int:
        if len(self._index) != len(self.images):
            self._index = {im.name: i for i, im in enumerate(self.images)}
        return self._index[name]

    def __contains__(self, name: str) -> bool:
        try:
            self.index(name)
        except KeyError:
            return False
        return True

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

    _TRACK_ARRAYS = {
        "points": ((3,), np.float64, np.nan),
        "colors": ((3,), np.uint8, 0),
        "point_from_model": ((), bool, False),
        "point_confirmed": ((), bool, False),
        "point_verified": ((), bool, False),
    }

    def _array(self, name: str) -> np.ndarray:
        buf = self._buf.get(name)
        if buf is None:
            shape, dtype, fill = self._TRACK_ARRAYS[name]
            buf = self._buf[name] = np.full((max(self._n_tracks, 16), *shape), fill, dtype)
        return buf[: self._n_tracks]

    def _set_array(self, name: str, value: np.ndarray) -> None:
        shape, dtype, _ = self._TRACK_ARRAYS[name]
        value = np.asarray(value, dtype).reshape(-1, *shape)
        if len(value) != self._n_tracks:
            raise ValueError(f"{name}: {len(value)} rows for {self._n_tracks} tracks")
        self._array(name)  # allocate
        self._buf[name][: self._n_tracks] = value

    points = property(lambda self: self._array("points"), lambda self, v: self._set_array("points", v))
    colors = property(lambda self: self._array("colors"), lambda self, v: self._set_array("colors", v))
    point_from_model = property(
        lambda self: self._array("point_from_model"), lambda self, v: self._set_array("point_from_model", v)
    )
    """(T,) bool: the point was looked up on the BIM (depth of the model at an anchor's feature) and is held there."""
    point_confirmed = property(
        lambda self: self._array("point_confirmed"), lambda self, v: self._set_array("point_confirmed", v)
    )
    """(T,) bool: a model point that a triangulation from two views reproduced (nothing unmodelled in front)."""
    point_verified = property(
        lambda self: self._array("point_verified"), lambda self, v: self._set_array("point_verified", v)
    )
    """(T,) bool: confirmed by epipolar-guided matching (densification; the densified tracks are by construction).
    Occlusion reasoning uses verified points only (see ``densified``)."""

    def reset_tracks(self, n: int) -> None:
        """``n`` empty tracks (untriangulated, no flags); clears the per-track arrays."""
        self._buf, self._n_tracks = {}, n

    def _add_tracks(self, n: int) -> None:
        """Append ``n`` untriangulated tracks' rows to the per-track arrays (amortised growth)."""
        need = self._n_tracks + n
        for name, (shape, dtype, fill) in self._TRACK_ARRAYS.items():
            buf = self._buf.get(name)
            if buf is not None and len(buf) < need:
                grown = np.full((max(2 * len(buf), need), *shape), fill, dtype)
                grown[: self._n_tracks] = buf[: self._n_tracks]
                self._buf[name] = grown
            elif buf is not None:
                buf[self._n_tracks : need] = fill
        self._n_tracks = need

    def truncate_tracks(self, n: int) -> None:
        """Keep the first ``n`` tracks' rows (the caller restores ``track_obs`` to match)."""
        self._n_tracks = min(self._n_tracks, n)


def focal_prior(im: ImageState, cfg: MapperConfig) -> float:
    if cfg.focal_px is not None:
        return float(cfg.focal_px)
    if im.focal_prior_px is not None:
        return float(im.focal_prior_px)
    return float(cam.focal_from_fov(im.width_px, 50.0))


def focal_sigma_frac(im: ImageState, cfg: MapperConfig) -> float:
    """Relative standard deviation of the focal prior of an image (inf when the prior is only a FOV guess, or
    when the image's own clicks contradicted it)."""
    if im.focal_prior_rejected:
        return np.inf
    if cfg.focal_px is not None:
        return cfg.focal_prior_sigma_frac if cfg.focal_prior_sigma_frac is not None else np.inf
    if im.focal_prior_px is not None:
        return cfg.exif_focal_sigma_frac if cfg.exif_focal_sigma_frac is not None else np.inf
    return np.inf


def anchor_focal_kwargs(im: ImageState, cfg: MapperConfig) -> dict:
    """Focal arguments of :func:`solve_anchor` for image ``im``: its external prior (user / EXIF) with that
    prior's relative sigma, or no prior at all (a 50 degree FOV is a starting guess, not evidence)."""
    sigma = focal_sigma_frac(im, cfg)
    if not np.isfinite(sigma):
        return {"focal_px": None}
    return {"focal_px": focal_prior(im, cfg), "focal_prior_sigma": float(sigma)}


def add_image(
    recon: Reconstruction,
    name: str,
    features: Features,
    colors_rgb_u8: np.ndarray | None = None,
    focal_prior_px: float | None = None,
    gps: GeoPoint | None = None,
    camera_id: str | None = None,
    capture_time_ns: int = 0,
) -> int:
    """Append an unregistered image; returns its index. ``colors_rgb_u8`` (N, 3): colour at each keypoint;
    ``gps``: its EXIF position (None when absent)."""
    if name in recon:
        raise ValueError(f"image {name!r} is already in the reconstruction")
    recon.images.append(
        ImageState(
            name, features, colors_rgb_u8, focal_prior_px, gps=gps, camera_id=camera_id, capture_time_ns=capture_time_ns
        )
    )
    recon.feature_track.append(-np.ones(len(features), dtype=np.int64))
    return len(recon.images) - 1


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
    recon.reset_tracks(n)


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


def obs_threshold_px(im: ImageState, cfg: MapperConfig) -> float:
    return max(cfg.min_obs_error_px, cfg.max_obs_error_frac * im.width_px)


def obs_threshold_per_image(recon: Reconstruction, cfg: MapperConfig) -> np.ndarray:
    return np.array([obs_threshold_px(im, cfg) for im in recon.images])


def flat_obs(recon: Reconstruction, tracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def obs_pixels(recon: Reconstruction, img: np.ndarray, feat: np.ndarray) -> np.ndarray:
    """Keypoints (M, 2) float64 px of observations (image, feature)."""
    px = np.zeros((len(img), 2))
    for i in np.unique(img):
        sel = img == i
        px[sel] = recon.images[i].features.keypoints_px[feat[sel]]
    return px


def snapshot(recon: Reconstruction) -> tuple:
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


def restore(recon: Reconstruction, snap: tuple) -> None:
    ims, points, track_obs, feature_track = snap
    for im, (intr, T, rms, n_inl, sig) in zip(recon.images, ims, strict=True):
        im.intrinsics, im.world_from_camera, im.rms_px, im.num_inliers, im.centre_sigma_m = intr, T, rms, n_inl, sig
    if len(points) < len(recon.points):
        recon.truncate_tracks(len(points))
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


def image_tracks(recon: Reconstruction, images: list[int]) -> list[int]:
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


def remove_images(recon: Reconstruction, drop: set[int] | list[int]) -> np.ndarray:
    """Take images ``drop`` out of the reconstruction (a bounded map: old key frames retired) and compact it.

    Their pairs and observations go; a triangulated point left with fewer than two observations is untriangulated
    (a model point keeps its BIM position); tracks left without observations are removed. ``centre_source`` /
    ``lens_source`` naming a removed image become None. Returns ``old_to_new`` (N_old,) int: each old image's new
    index, -1 for a removed one (track ids are renumbered too; callers keep no track ids across this call)."""
    drop = {int(i) for i in drop}
    n_old = len(recon.images)
    old_to_new = -np.ones(n_old, np.int64)
    keep = [i for i in range(n_old) if i not in drop]
    old_to_new[keep] = np.arange(len(keep))
    if not drop:
        return old_to_new
    recon.pairs = {
        (int(old_to_new[i]), int(old_to_new[j])): g
        for (i, j), g in recon.pairs.items()
        if i not in drop and j not in drop
    }
    arrays = {name: recon._array(name).copy() for name in recon._TRACK_ARRAYS}
    obs = [{int(old_to_new[i]): f for i, f in d.items() if i not in drop} for d in recon.track_obs]
    alive = np.array([len(d) > 0 for d in obs], bool)
    thin = np.array([len(d) < 2 for d in obs], bool) & ~arrays["point_from_model"]
    arrays["points"][thin] = np.nan
    arrays["point_confirmed"][thin] = False
    arrays["point_verified"][thin] = False
    track_new = -np.ones(len(obs) + 1, np.int64)  # index -1 (no track) maps to -1
    track_new[np.nonzero(alive)[0]] = np.arange(int(alive.sum()))
    recon.track_obs = [d for d, a in zip(obs, alive, strict=True) if a]
    recon.feature_track = [track_new[recon.feature_track[i]] for i in keep]
    recon.images = [recon.images[i] for i in keep]
    recon._index = {}
    recon.reset_tracks(len(recon.track_obs))
    for name, a in arrays.items():
        setattr(recon, name, a[alive])
    for im in recon.images:
        for attr in ("centre_source", "lens_source"):
            src = getattr(im, attr)
            if src is not None:
                setattr(im, attr, None if src in drop else int(old_to_new[src]))
    names = {im.name for im in recon.images}
    recon.needs_anchor = [r for r in recon.needs_anchor if r[0] in names]
    return old_to_new
