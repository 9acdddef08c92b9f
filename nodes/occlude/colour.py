"""Colour model of a site's dynamic occluders (beyond the paper; step 7 of :mod:`nodes.occlude.dynamic`): HSV
histograms of the photos' time-lapse masks against the rest of the photos, giving P(dynamic | colour)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]


@dataclass
class _ColourEntry:
    dynamic: F32  # histogram of the photo's time-lapse-mask pixels
    other: F32  # ... of its other pixels (outside the camera's moved-place map when counted)
    camera_id: str | None
    mask_bits: U8  # np.packbits of the time-lapse mask (for recounting)
    shape: tuple[int, int]
    # np.packbits of the camera's dilated moved-place map that ``other`` leaves out (None: nothing left out)
    moved_bits: U8 | None = None


@dataclass
class ColourModel:
    """Colour histograms (HSV bins) of the time-lapse dynamic masks of a site's photos and of the rest of
    those photos, for labelling what the time-lapse cannot see (beyond the paper).

    Each photo contributes the pixels of its working image inside its time-lapse mask (dynamic) and
    outside it (other); :meth:`posterior` is P(dynamic | colour) per pixel of a new image,
    ``dynamic / (dynamic + other + prior_count)`` of its bin. Colours that the site's building, ground,
    fence and sky also show get a low posterior because those surfaces are in every photo's "other"
    pixels; only colours seen (almost) exclusively on things that moved score high. That works when
    equipment and vehicles differ in colour from the static scene (true of the synthetic site's
    crane, trucks and cabins; on a real site a grey truck in front of a grey facade would not score).

    An occluder that stands still in most frames (a site cabin for weeks) is missed by most of its
    camera's time-lapse masks and would count as "other" there, teaching the model that its colour is
    background. So a fixed camera's "other" pixels leave out its moved-place map: the union of its
    frames' current time-lapse masks (a recomputed mask replaces the frame's earlier one, so a place
    that only a provisional mask flagged leaves the map again; a forgotten frame's mask stays),
    dilated by ``moved_dilation_px`` (None: no exclusion). Whenever that map changes, :meth:`add` brings
    every counted frame of the camera up to date by recounting only the pixels that entered or left the
    map (``image_of`` gives their working images; masks and maps are kept bit-packed, 1 bit per pixel), so
    the model depends on the frames' current masks, not on the order they came in (a frame whose image is
    gone keeps the map it was counted with).

    ``add`` replaces a photo's earlier contribution (its mask was recomputed); ``forget`` keeps the
    contribution but drops the per-photo record (bounded memory).
    """

    bins: tuple[int, int, int] = (36, 8, 8)  # hue (OpenCV 0-180), saturation, value
    moved_dilation_px: int | None = 2
    per_photo: dict[str, _ColourEntry] = field(default_factory=dict)
    # camera -> per pixel, how many of its frames' time-lapse masks (current ones, and those of forgotten frames)
    # cover it: the moved-place map is where this is > 0
    moved: dict[str, NDArray[np.uint16]] = field(default_factory=dict)
    _base: tuple[F32, F32] | None = None
    _base_frames: int = 0
    _sum: tuple[F32, F32] | None = None

    def _bin_index(self, photo_small: U8) -> NDArray[np.int32]:
        """Flat colour-bin index (h, w) of each pixel of a uint8 BGR image (OpenCV 8-bit HSV, uniform bins)."""
        hsv = cv2.cvtColor(photo_small, cv2.COLOR_BGR2HSV).astype(np.int32)
        nh, ns, nv = self.bins
        ih = np.minimum(hsv[..., 0] * nh // 180, nh - 1)
        return np.asarray((ih * ns + hsv[..., 1] * ns // 256) * nv + hsv[..., 2] * nv // 256, np.int32)

    def _hist(self, index: NDArray[np.int32], mask: NDArray[np.bool_]) -> F32:
        n = int(np.prod(self.bins))
        return np.bincount(index[mask], minlength=n).astype(np.float32).reshape(self.bins)

    def _moved_place(self, camera_id: str | None, shape: tuple[int, int]) -> NDArray[np.bool_] | None:
        """The camera's dilated moved-place map (h, w) (None when not kept or of another size)."""
        count = self.moved.get(camera_id) if camera_id is not None else None
        if count is None or count.shape != shape or self.moved_dilation_px is None:
            return None
        union = (count > 0).astype(np.uint8)
        k = 2 * max(0, int(self.moved_dilation_px)) + 1
        return np.asarray(cv2.dilate(union, np.ones((k, k), np.uint8)) > 0)

    def _count(
        self,
        photo_id: str,
        photo_small: U8,
        dyn: NDArray[np.bool_],
        camera_id: str | None,
        moved: NDArray[np.bool_] | None,
    ) -> None:
        index = self._bin_index(photo_small)
        other = ~dyn if moved is None else ~dyn & ~moved
        h, w = dyn.shape
        self.per_photo[photo_id] = _ColourEntry(
            self._hist(index, dyn),
            self._hist(index, other),
            camera_id,
            np.packbits(dyn),
            (h, w),
            None if moved is None else np.packbits(moved),
        )
        self._sum = None

    def _update_other(self, entry: _ColourEntry, img: U8, moved: NDArray[np.bool_]) -> None:
        """Bring ``entry.other`` from the map it was counted with to ``moved`` (h, w): only the pixels that
        entered (now left out) or left (background again) the map are recounted."""
        n = entry.shape[0] * entry.shape[1]
        old = np.zeros(n, bool) if entry.moved_bits is None else np.unpackbits(entry.moved_bits, count=n).astype(bool)
        new = moved.ravel()
        changed = np.flatnonzero(old != new)
        if len(changed) == 0:
            return
        dyn = np.unpackbits(entry.mask_bits, count=n).astype(bool)
        changed = changed[~dyn[changed]]  # a frame's own dynamic pixels are never in its background
        if len(changed):
            pixels = img.reshape(-1, img.shape[-1])[changed].reshape(-1, 1, img.shape[-1])
            bins = self._bin_index(np.ascontiguousarray(pixels)).ravel()
            sign = np.where(new[changed], -1.0, 1.0)
            size = int(np.prod(self.bins))
            delta = np.bincount(bins, weights=sign, minlength=size).astype(np.float32).reshape(self.bins)
            entry.other = np.maximum(entry.other + delta, 0.0).astype(np.float32)
        entry.moved_bits = np.packbits(new)
        self._sum = None

    def add(
        self,
        photo_id: str,
        photo_small: U8,
        mask_small: NDArray[np.generic],
        camera_id: str | None = None,
        image_of: Callable[[str], U8 | None] | None = None,
    ) -> None:
        """Learn from a photo's working image (uint8 BGR (h, w, 3)) and its time-lapse mask (h, w), non-zero =
        dynamic. ``camera_id``: the fixed camera that took it (its moved-place map grows); ``image_of``:
        working image of a stored photo (None when gone), for recounting the camera's earlier frames."""
        if mask_small.shape != photo_small.shape[:2]:
            raise ValueError(f"photo {photo_id}: mask {mask_small.shape} does not match image {photo_small.shape[:2]}")
        dyn = np.asarray(mask_small) > 0
        if camera_id is not None and self.moved_dilation_px is not None:
            count = self.moved.get(camera_id)
            if count is None or count.shape != dyn.shape:
                count = np.zeros(dyn.shape, np.uint16)
            previous = self.learnt_mask(photo_id)
            if previous is not None and previous.shape == dyn.shape and self.per_photo[photo_id].camera_id == camera_id:
                count -= previous  # the frame's earlier mask is replaced (every counted pixel is >= 1)
            count += dyn
            self.moved[camera_id] = count
        moved = self._moved_place(camera_id, dyn.shape)
        self._count(photo_id, photo_small, dyn, camera_id, moved)
        if moved is None or image_of is None:
            return
        for pid, entry in list(self.per_photo.items()):
            if pid == photo_id or entry.camera_id != camera_id or entry.shape != dyn.shape:
                continue
            img = image_of(pid)
            if img is not None and img.shape[:2] == entry.shape:
                self._update_other(entry, img, moved)

    def forget(self, photo_id: str) -> None:
        """Drop the per-photo record; its pixels stay in the model."""
        entry = self.per_photo.pop(photo_id, None)
        if entry is None:
            return
        if self._base is None:
            self._base = (entry.dynamic.copy(), entry.other.copy())
        else:
            self._base = (self._base[0] + entry.dynamic, self._base[1] + entry.other)
        self._base_frames += 1
        self._sum = None

    def learnt_mask(self, photo_id: str) -> NDArray[np.bool_] | None:
        """The time-lapse mask (h, w) last learnt from a photo (None when never added or forgotten)."""
        entry = self.per_photo.get(photo_id)
        if entry is None:
            return None
        h, w = entry.shape
        return np.unpackbits(entry.mask_bits, count=h * w).reshape(h, w).astype(bool)

    @property
    def num_frames(self) -> int:
        return len(self.per_photo) + self._base_frames

    def totals(self) -> tuple[F32, F32]:
        """(dynamic, other) histograms summed over all contributions."""
        if self._sum is None:
            shape = tuple(self.bins)
            dyn = np.zeros(shape, np.float32) if self._base is None else self._base[0].copy()
            other = np.zeros(shape, np.float32) if self._base is None else self._base[1].copy()
            for e in self.per_photo.values():
                dyn += e.dynamic
                other += e.other
            self._sum = (dyn, other)
        return self._sum

    def recall(self, level: float, prior_count: float) -> float:
        """Fraction of the learnt time-lapse-mask pixels whose colour has P(dynamic | colour) >= ``level``
        (0 before any): how much of what was seen to move the model recognises by colour."""
        dyn, other = self.totals()
        total = float(dyn.sum())
        if total <= 0:
            return 0.0
        table = dyn / (dyn + other + max(prior_count, 1e-6))
        return float(dyn[table >= level].sum()) / total

    def posterior(self, photo_small: U8, prior_count: float) -> F32:
        """P(dynamic | colour) (h, w) in [0, 1] for a uint8 BGR working image."""
        dyn, other = self.totals()
        table = (dyn / (dyn + other + max(prior_count, 1e-6))).astype(np.float32).ravel()
        return table[self._bin_index(photo_small)]
