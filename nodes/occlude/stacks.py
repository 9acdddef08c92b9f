"""Pixel-aligned time-lapse stacks from viewpoint groups (paper Sec. 4.1.1).

Every photo is kept at a reduced working resolution. A photo's stack is its neighbours (photos
from nearly the same viewpoint) warped into its view by ``this_from_neighbour`` homographies.
Neighbours come from registration's viewpoint groups (either direction: a group of B listing A
with ``B_from_A`` gives ``A_from_B = inv(B_from_A)``) and, for a fixed camera, from the camera's
other frames (identity homography, refined by a phase-correlation shift to absorb small jitter;
a frame that still does not line up, because the camera was moved, is left out).

Adding a photo or a group is O(1); a stack is built on demand for one photo only, so a new frame
never forces recomputing other frames' stacks.

Pixel convention: (0, 0) is the centre of the top-left pixel, so scaling an image by ``s`` maps
``u -> s (u + 0.5) - 0.5``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.sampling import farthest_point_order

U8 = NDArray[np.uint8]
F64 = NDArray[np.float64]


def scale_matrix(scale: float) -> F64:
    """3x3 map from full-resolution pixels to pixels of an image resized by ``scale``."""
    off = 0.5 * scale - 0.5
    return np.array([[scale, 0.0, off], [0.0, scale, off], [0.0, 0.0, 1.0]])


def working_size(width_px: int, height_px: int, working_width_px: int) -> tuple[int, int, float]:
    """(width, height, scale) of the working image; never upscales."""
    if width_px <= 0 or height_px <= 0:
        raise ValueError(f"bad image size {width_px}x{height_px}")
    scale = min(1.0, working_width_px / float(width_px))
    return max(1, round(width_px * scale)), max(1, round(height_px * scale)), scale


def alignment_ncc(a_bgr: U8, b_bgr: U8, valid: NDArray[np.bool_]) -> float:
    """Normalised cross-correlation of the band-passed grey images over ``valid`` pixels (gain/offset
    invariant; about 1 for aligned views of the same scene, about 0 for misaligned ones)."""
    out = []
    for img in (a_bgr, b_bgr):
        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
        g = cv2.GaussianBlur(g, (0, 0), 1.0) - cv2.GaussianBlur(g, (0, 0), 4.0)
        out.append(g[valid])
    x, y = out
    x = x - x.mean()
    y = y - y.mean()
    den = float(np.sqrt((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / den) if den > 0 else 0.0


def gradient_ncc(a_bgr: U8, b_bgr: U8, valid: NDArray[np.bool_], blur_px: float = 1.5) -> float:
    """NCC over ``valid`` (h, w) of the gradient magnitudes of two aligned BGR images (h, w, 3): edges stay where
    they are when light changes, so this tells a moved camera from a sunny frame next to an overcast one."""
    mags = []
    for img in (a_bgr, b_bgr):
        g = cv2.GaussianBlur(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32), (0, 0), blur_px)
        mags.append(np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))[valid])
    a, b = mags[0] - mags[0].mean(), mags[1] - mags[1].mean()
    den = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return float(np.sum(a * b) / den) if den > 0 else 0.0


def spread_order(ids: list[str], times_ns: list[int], photo_time_ns: int) -> list[str]:
    """Reorder neighbours (any order) for temporal diversity: the nearest earlier and the nearest later
    one first, then a farthest-point sequence in capture time (each next pick maximises its time gap
    to the photo and to the already picked ones), so any prefix spreads over the whole time span."""
    if not ids:
        return []
    t = np.asarray(times_ns, dtype=np.float64) - float(photo_time_ns)
    picked: list[int] = []
    for side in (np.flatnonzero(t < 0), np.flatnonzero(t >= 0)):
        if len(side):
            picked.append(int(side[np.argmin(np.abs(t[side]))]))
    return [ids[i] for i in farthest_point_order(t[:, None], picked, also_from=[[0.0]])]


def alignment_tile_ncc(a_bgr: U8, b_bgr: U8, valid: NDArray[np.bool_], grid: int = 4, quantile: float = 25.0) -> float:
    """``quantile`` percentile of :func:`alignment_ncc` over a ``grid`` x ``grid`` tiling (tiles less
    than half covered by ``valid`` are skipped). A homography that leaves parallax lines up part of
    the view only, so a quarter of its tiles correlate near 0 while the global NCC can still pass."""
    h, w = valid.shape
    values = []
    for i in range(grid):
        for j in range(grid):
            rows, cols = slice(i * h // grid, (i + 1) * h // grid), slice(j * w // grid, (j + 1) * w // grid)
            v = valid[rows, cols]
            if v.size and v.mean() >= 0.5:
                values.append(
                    alignment_ncc(np.ascontiguousarray(a_bgr[rows, cols]), np.ascontiguousarray(b_bgr[rows, cols]), v)
                )
    return float(np.percentile(values, quantile)) if values else 0.0


@dataclass
class StackFrame:
    """One stored photo at working resolution. ``image_small``: uint8 BGR (h, w, 3)."""

    photo_id: str
    camera_id: str | None
    capture_time_ns: int
    image_small: U8
    scale: float
    full_size_px: tuple[int, int]  # (width, height) of the original photo
    occluder_small: NDArray[np.bool_] | None = None  # (h, w) its own dynamic mask, once known (two-pass)


@dataclass
class AlignedStack:
    """Neighbours warped into one photo's working view.

    ``images``: uint8 (N, h, w, 3) BGR; ``valid``: bool (N, h, w), True where the warped
    neighbour covers the pixel; ``photo_ids``: the N neighbours, nearest in time first.
    """

    photo_id: str
    images: U8
    valid: NDArray[np.bool_]
    photo_ids: tuple[str, ...] = ()
    times_ns: tuple[int, ...] = ()  # capture time of each neighbour
    photo_time_ns: int = 0
    occluded: NDArray[np.bool_] | None = None  # (N, h, w) neighbour's own dynamic mask warped here, if known

    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])


@dataclass
class TimelapseStore:
    """Photos at working resolution and the homographies between them.

    ``max_views``: stack size cap (neighbours nearest in capture time win);
    ``max_time_gap_ns``: neighbours further apart in time are ignored (None: no limit);
    ``min_overlap``: neighbours whose warp covers less of the photo are dropped;
    ``refine_fixed_shift``: estimate a sub-pixel shift between a fixed camera's frames.
    """

    working_width_px: int = 480
    max_views: int = 8
    max_time_gap_ns: int | None = None
    min_overlap: float = 0.3
    refine_fixed_shift: bool = True
    min_fixed_ncc: float = 0.5  # a fixed camera's frame is dropped when it aligns worse than this (camera moved)
    # ... measured on gradient magnitudes (edges stay put when sun, clouds and exposure change; colour NCC of a
    # sunny and an overcast frame of the same view falls to 0.4); None = colour NCC against min_fixed_ncc
    min_fixed_gradient_ncc: float | None = 0.3
    # "nearest": the max_views nearest in time; "spread": the nearest earlier and later neighbours first,
    # then neighbours spread evenly over the whole time span (an occluder that stays a week is gone weeks later)
    selection: str = "nearest"
    # check viewpoint-group neighbours that are not frames of the same fixed camera too: dropped when
    # their NCC is below min_fixed_ncc or a quarter of their 4x4 tiles align worse than min_tile_ncc (a
    # homography between photos taken from different spots leaves parallax that lights up the difference)
    check_group_alignment: bool = True
    min_tile_ncc: float = 0.25
    # "shift": a fixed camera's frames differ by a translation (phase correlation); "homography": by a
    # homography from SIFT matches on the working images (RANSAC; falls back to the shift when too few
    # inliers), which also absorbs daily zoom / roll jitter of the camera
    fixed_alignment: str = "homography"
    max_features: int = 1000  # SIFT features per working image for fixed_alignment="homography"
    frames: dict[str, StackFrame] = field(default_factory=dict)
    # (this, neighbour) -> this_from_neighbour in full-resolution pixels
    homographies: dict[tuple[str, str], F64] = field(default_factory=dict)
    by_camera: dict[str, list[str]] = field(default_factory=dict)
    _shift_cache: dict[tuple[str, str], F64] = field(default_factory=dict)
    # photo -> SIFT keypoints (N, 2) working pixels, descriptors (N, 128) uint8 (OpenCV's float SIFT descriptors are
    # whole numbers in 0..255: kept as bytes, a quarter of the memory, matched as float32)
    _features: dict[str, tuple[F64, NDArray[np.uint8] | None]] = field(default_factory=dict)

    def add_photo(self, photo_id: str, camera_id: str | None, capture_time_ns: int, image_bgr: U8) -> StackFrame:
        """Store a photo (uint8 BGR (H, W, 3), full resolution). Returns its frame."""
        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
            raise ValueError(f"photo {photo_id}: expected (H, W, 3) BGR, got shape {image_bgr.shape}")
        h_full, w_full = image_bgr.shape[:2]
        w, h, scale = working_size(w_full, h_full, self.working_width_px)
        small = np.asarray(
            cv2.resize(image_bgr, (w, h), interpolation=cv2.INTER_AREA) if scale < 1.0 else image_bgr.copy(), np.uint8
        )
        frame = StackFrame(photo_id, camera_id, int(capture_time_ns), small, scale, (w_full, h_full))
        if photo_id not in self.frames and camera_id is not None:
            self.by_camera.setdefault(camera_id, []).append(photo_id)
        self.frames[photo_id] = frame
        return frame

    def set_occluder_mask(self, photo_id: str, mask: NDArray[np.generic]) -> None:
        """Remember a stored photo's dynamic mask (any size, non-zero = occluder); stacks of other
        photos then leave those pixels out of their background where another view covers them."""
        frame = self.frames[photo_id]
        h, w = frame.image_small.shape[:2]
        m = np.asarray(mask)
        if m.ndim != 2:
            raise ValueError(f"photo {photo_id}: occluder mask must be (H, W), got shape {m.shape}")
        small = np.asarray(
            cv2.resize((m > 0).astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
            if m.shape != (h, w)
            else (m > 0).astype(np.uint8)
        )
        frame.occluder_small = np.asarray(small > 0, dtype=bool)

    def set_neighbours(self, photo_id: str, this_from_neighbour: dict[str, F64]) -> None:
        """Record a viewpoint group: 3x3 homographies mapping neighbour pixels to ``photo_id``'s."""
        for nid, H in this_from_neighbour.items():
            if nid == photo_id:
                continue
            H = np.asarray(H, dtype=np.float64).reshape(3, 3)
            if not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
                raise ValueError(f"viewpoint group of {photo_id}: degenerate homography for {nid}")
            self.homographies[(photo_id, nid)] = H / H[2, 2]

    def candidate_neighbours(self, photo_id: str) -> dict[str, F64]:
        """All neighbours of a stored photo with full-resolution ``this_from_neighbour`` (3, 3)."""
        out: dict[str, F64] = {}
        for (a, b), H in self.homographies.items():
            if a == photo_id and b in self.frames:
                out[b] = H
            elif b == photo_id and a in self.frames and a not in out:
                out[a] = np.asarray(np.linalg.inv(H), np.float64)
        frame = self.frames[photo_id]
        if frame.camera_id is not None:
            for nid in self.by_camera.get(frame.camera_id, ()):
                if nid != photo_id and nid not in out and self.frames[nid].full_size_px == frame.full_size_px:
                    out[nid] = self._fixed_camera_homography(photo_id, nid)
        return out

    def _fixed_camera_homography(self, photo_id: str, nid: str) -> F64:
        """Identity, or a translation from phase correlation of the working images."""
        if not self.refine_fixed_shift:
            return np.eye(3)
        key = (photo_id, nid)
        if key in self._shift_cache:
            return self._shift_cache[key]
        a = cv2.cvtColor(self.frames[photo_id].image_small, cv2.COLOR_BGR2GRAY).astype(np.float32)
        b = cv2.cvtColor(self.frames[nid].image_small, cv2.COLOR_BGR2GRAY).astype(np.float32)
        win = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
        (dx, dy), response = cv2.phaseCorrelate(b, a, win)
        H_small = np.eye(3)
        max_shift = 0.1 * a.shape[1]
        if response > 0.05 and abs(dx) < max_shift and abs(dy) < max_shift:
            H_small[0, 2], H_small[1, 2] = dx, dy
        if self.fixed_alignment == "homography":
            H_feat = self._feature_homography(photo_id, nid)
            if H_feat is not None:
                H_small = H_feat
        elif self.fixed_alignment != "shift":
            raise ValueError(f"unknown fixed_alignment {self.fixed_alignment!r} (shift or homography)")
        S = scale_matrix(self.frames[photo_id].scale)
        H = np.asarray(np.linalg.inv(S) @ H_small @ scale_matrix(self.frames[nid].scale), np.float64)
        self._shift_cache[key] = H
        self._shift_cache[(nid, photo_id)] = np.asarray(np.linalg.inv(H), np.float64)
        return H

    def _frame_features(self, photo_id: str) -> tuple[F64, NDArray[np.float32] | None]:
        """SIFT keypoints (N, 2) in working pixels and float32 descriptors (N, 128) of a stored frame (cached,
        the descriptors as uint8)."""
        if photo_id not in self._features:
            grey = cv2.cvtColor(self.frames[photo_id].image_small, cv2.COLOR_BGR2GRAY)
            kp, found = cv2.SIFT.create(nfeatures=self.max_features).detectAndCompute(grey, None)
            pts = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
            packed = None if found is None else np.clip(np.rint(found), 0, 255).astype(np.uint8)
            self._features[photo_id] = (pts, packed)
        pts, desc = self._features[photo_id]
        return pts, None if desc is None else np.asarray(desc, np.float32)

    def _feature_homography(self, photo_id: str, nid: str, min_inliers: int = 40) -> F64 | None:
        """this_from_neighbour (3, 3) in working pixels from SIFT matches + RANSAC (1 px), or None."""
        pa, da = self._frame_features(photo_id)
        pb, db = self._frame_features(nid)
        if da is None or db is None or len(pa) < min_inliers or len(pb) < min_inliers:
            return None
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(db, da, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        if len(good) < min_inliers:
            return None
        src = pb[[m.queryIdx for m in good]]
        dst = pa[[m.trainIdx for m in good]]
        H, inl = cv2.findHomography(src, dst, cv2.RANSAC, 1.0, maxIters=2000, confidence=0.999)
        if H is None or inl is None or int(inl.sum()) < min_inliers:
            return None
        # least-squares refit on the inliers
        keep = inl.ravel() > 0
        H2, _ = cv2.findHomography(src[keep], dst[keep], 0)
        H = H2 if H2 is not None else H
        return np.asarray(H / H[2, 2], np.float64)

    def aligned_stack(self, photo_id: str) -> AlignedStack:
        """Warp the nearest-in-time neighbours into ``photo_id``'s working view."""
        if photo_id not in self.frames:
            raise ValueError(f"unknown photo {photo_id}")
        frame = self.frames[photo_id]
        h, w = frame.image_small.shape[:2]
        cands = self.candidate_neighbours(photo_id)
        fixed = {n for n in cands if (photo_id, n) not in self.homographies and (n, photo_id) not in self.homographies}
        order = sorted(cands, key=lambda nid: (abs(self.frames[nid].capture_time_ns - frame.capture_time_ns), nid))
        if self.max_time_gap_ns is not None:
            order = [
                n for n in order if abs(self.frames[n].capture_time_ns - frame.capture_time_ns) <= self.max_time_gap_ns
            ]
        if self.selection == "spread":
            order = spread_order(order, [self.frames[n].capture_time_ns for n in order], frame.capture_time_ns)
        elif self.selection != "nearest":
            raise ValueError(f"unknown stack selection {self.selection!r} (nearest or spread)")
        S_this = scale_matrix(frame.scale)
        images: list[U8] = []
        valids: list[NDArray[np.bool_]] = []
        ids: list[str] = []
        occluded: dict[int, NDArray[np.bool_]] = {}
        for nid in order:
            if len(ids) >= self.max_views:
                break
            nf = self.frames[nid]
            H_small = S_this @ cands[nid] @ np.linalg.inv(scale_matrix(nf.scale))
            warped = np.asarray(
                cv2.warpPerspective(
                    nf.image_small, H_small, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                ),
                np.uint8,
            )
            ones = np.full(nf.image_small.shape[:2], 255, np.uint8)
            cover = cv2.warpPerspective(ones, H_small, (w, h), flags=cv2.INTER_NEAREST, borderValue=0)
            cover = cv2.erode(cover, np.ones((3, 3), np.uint8))
            valid = cover > 0
            if valid.mean() < self.min_overlap:
                continue
            if nid in fixed and (
                alignment_ncc(frame.image_small, warped, valid) < self.min_fixed_ncc
                if self.min_fixed_gradient_ncc is None
                else gradient_ncc(frame.image_small, warped, valid) < self.min_fixed_gradient_ncc
            ):
                continue  # the camera was moved between the two frames
            if (
                self.check_group_alignment
                and (frame.camera_id is None or nf.camera_id != frame.camera_id)
                and (
                    alignment_ncc(frame.image_small, warped, valid) < self.min_fixed_ncc
                    or alignment_tile_ncc(frame.image_small, warped, valid) < self.min_tile_ncc
                )
            ):
                continue  # photos taken from different spots: the homography leaves parallax
            images.append(warped)
            valids.append(valid)
            ids.append(nid)
            if nf.occluder_small is not None:
                occ = cv2.warpPerspective(
                    nf.occluder_small.astype(np.uint8), H_small, (w, h), flags=cv2.INTER_NEAREST, borderValue=0
                )
                occluded[len(ids) - 1] = occ > 0
        if not images:
            empty = AlignedStack(photo_id, np.zeros((0, h, w, 3), np.uint8), np.zeros((0, h, w), bool))
            empty.photo_time_ns = frame.capture_time_ns
            return empty
        times = tuple(self.frames[n].capture_time_ns for n in ids)
        occ_all = None
        if occluded:
            occ_all = np.zeros((len(ids), h, w), bool)
            for i, m in occluded.items():
                occ_all[i] = m
        return AlignedStack(
            photo_id, np.stack(images), np.stack(valids), tuple(ids), times, frame.capture_time_ns, occ_all
        )

    def warp_full_image(self, photo_id: str, neighbour_id: str, image: NDArray[np.generic]) -> NDArray[np.generic]:
        """Warp a full-resolution image of ``neighbour_id`` (e.g. a mask) into ``photo_id``'s working view
        with the same homography the stack uses (nearest-neighbour sampling, zero outside)."""
        frame = self.frames[photo_id]
        H = self.candidate_neighbours(photo_id)[neighbour_id]
        h, w = frame.image_small.shape[:2]
        H_small = scale_matrix(frame.scale) @ H
        return np.asarray(
            cv2.warpPerspective(np.asarray(image), H_small, (w, h), flags=cv2.INTER_NEAREST, borderValue=0)
        )

    def bound_unstored(self, keep: int) -> None:
        """Keep the viewpoint groups (homographies from a photo's own group) of at most ``keep`` photos that are
        not stored, the oldest dropped first (a group may come ahead of its photo, or after it was forgotten)."""
        owners = list(dict.fromkeys(a for a, _ in self.homographies if a not in self.frames))
        drop = set(owners[: max(0, len(owners) - keep)])
        if drop:
            self.homographies = {k: H for k, H in self.homographies.items() if k[0] not in drop}

    def forget(self, photo_id: str) -> None:
        """Drop a photo and every homography that mentions it."""
        frame = self.frames.pop(photo_id, None)
        if frame is not None and frame.camera_id is not None:
            self.by_camera[frame.camera_id] = [p for p in self.by_camera[frame.camera_id] if p != photo_id]
        for k in [k for k in self.homographies if photo_id in k]:
            del self.homographies[k]
        for k in [k for k in self._shift_cache if photo_id in k]:
            del self._shift_cache[k]
        self._features.pop(photo_id, None)
