"""Viewpoint groups (paper Sec. 4.1.1): for each photo, the photos taken from nearly the same viewpoint.

Two photos share a viewpoint when one homography explains at least ``min_inlier_ratio`` (80 %) of their
feature matches and there are at least ``min_matches`` matches. Each edge keeps the homography
``this_from_neighbour`` (3x3, pixels of the neighbour -> pixels of this photo, OpenCV pixel convention) and is
stored in both directions (the reverse edge carries the inverse homography). The graph is incremental: adding
a photo's edges updates its own group and appends it to each neighbour's group.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from constructaide import camera as cam
from schemas.messages import Intrinsics, ViewpointGroup, ViewpointNeighbour


@dataclass(frozen=True)
class ViewpointEdge:
    """``this_from_neighbour`` (3, 3) homography, fraction of matches it explains, number of matches."""

    this_from_neighbour: np.ndarray
    inlier_ratio: float
    num_matches: int


def accept_pair(
    homography: np.ndarray | None, inlier_ratio: float, num_matches: int, min_inlier_ratio: float, min_matches: int
) -> bool:
    """True when a homography fit qualifies two photos as the same viewpoint (paper: >= 80 % inliers)."""
    if homography is None or num_matches < min_matches or inlier_ratio < min_inlier_ratio:
        return False
    H = np.asarray(homography, dtype=np.float64)
    return bool(H.shape == (3, 3) and np.all(np.isfinite(H)) and abs(np.linalg.det(H)) > 1e-12)


def rotation_homography(
    intr_this: Intrinsics, world_from_this: np.ndarray, intr_other: Intrinsics, world_from_other: np.ndarray
) -> np.ndarray:
    """Homography (3, 3) other-pixels -> this-pixels for two cameras sharing a centre (rotation and zoom only).

    ``H = K_this R_this_from_world R_other_from_world^T K_other^-1``; distortion is ignored.
    """
    R_this = np.asarray(world_from_this)[:3, :3].T
    R_other = np.asarray(world_from_other)[:3, :3].T
    H = cam.K_matrix(intr_this) @ R_this @ R_other.T @ np.linalg.inv(cam.K_matrix(intr_other))
    return H / H[2, 2]


class ViewpointGraph:
    """Incremental same-viewpoint graph with at most ``max_neighbours`` per photo (oldest edges dropped)."""

    def __init__(self, min_inlier_ratio: float = 0.8, min_matches: int = 30, max_neighbours: int = 50) -> None:
        if not 0.0 < min_inlier_ratio <= 1.0:
            raise ValueError(f"min_inlier_ratio must be in (0, 1], got {min_inlier_ratio}")
        if max_neighbours < 1:
            raise ValueError(f"max_neighbours must be >= 1, got {max_neighbours}")
        self.min_inlier_ratio = min_inlier_ratio
        self.min_matches = min_matches
        self.max_neighbours = max_neighbours
        self._edges: dict[str, OrderedDict[str, ViewpointEdge]] = {}

    def __contains__(self, photo_id: str) -> bool:
        return photo_id in self._edges

    def add_photo(self, photo_id: str) -> None:
        """Make ``photo_id`` known (an empty group until edges are added)."""
        self._edges.setdefault(photo_id, OrderedDict())

    def add_pair(
        self,
        photo_id: str,
        neighbour_id: str,
        this_from_neighbour: np.ndarray | None,
        inlier_ratio: float,
        num_matches: int,
        *,
        check: bool = True,
    ) -> bool:
        """Record that two photos share a viewpoint; returns False (nothing stored) when the fit does not qualify.

        With ``check=False`` the thresholds are skipped (for homographies derived from registered poses).
        """
        if photo_id == neighbour_id:
            return False
        if this_from_neighbour is None:
            return False
        if check and not accept_pair(
            this_from_neighbour, inlier_ratio, num_matches, self.min_inlier_ratio, self.min_matches
        ):
            return False
        H = np.asarray(this_from_neighbour, dtype=np.float64)
        if abs(np.linalg.det(H)) < 1e-12 or not np.all(np.isfinite(H)):
            return False
        H = H / H[2, 2]
        H_inv = np.linalg.inv(H)
        H_inv /= H_inv[2, 2]
        self._set(photo_id, neighbour_id, ViewpointEdge(H, float(inlier_ratio), int(num_matches)))
        self._set(neighbour_id, photo_id, ViewpointEdge(H_inv, float(inlier_ratio), int(num_matches)))
        return True

    def _set(self, a: str, b: str, edge: ViewpointEdge) -> None:
        group = self._edges.setdefault(a, OrderedDict())
        group.pop(b, None)
        group[b] = edge
        while len(group) > self.max_neighbours:
            group.popitem(last=False)

    def forget(self, photo_id: str) -> None:
        """Drop a photo and its edges (both directions)."""
        for other in self._edges.pop(photo_id, {}):
            group = self._edges.get(other)
            if group is not None:
                group.pop(photo_id, None)

    def __len__(self) -> int:
        return len(self._edges)

    def neighbours(self, photo_id: str) -> dict[str, ViewpointEdge]:
        """Edges of one photo, oldest first (empty for unknown photos)."""
        return dict(self._edges.get(photo_id, {}))

    def group_message(self, site: str, photo_id: str) -> ViewpointGroup:
        """The :class:`ViewpointGroup` bus message of one photo."""
        return ViewpointGroup(
            site=site,
            photo_id=photo_id,
            neighbours=tuple(
                ViewpointNeighbour(
                    photo_id=other,
                    this_from_neighbour=tuple(float(v) for v in e.this_from_neighbour.reshape(9)),
                    inlier_ratio=e.inlier_ratio,
                    num_matches=e.num_matches,
                )
                for other, e in self._edges.get(photo_id, {}).items()
            ),
        )
