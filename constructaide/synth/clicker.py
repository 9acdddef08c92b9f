"""The simulated site user: the anchor clicks a person would give for a photo of the synthetic site.

A person anchoring a photo in the browser clicks points they can locate precisely in both the photo and the
BIM viewer: element corners and the crossings of element edges. So this user clicks only **model vertices and
crossings of two elements' edges** (see :class:`ModelCorners`) that are visible in the photo and look like a
corner there, spread over the image; the model point is the exact 3D vertex (the viewer snaps to it), the pixel
is the vertex's true projection + Gaussian noise (``noise_px`` per axis, default 1.5), and about one click in 20
is a gross mis-click (:func:`click_points`). It reads the site's ``truth/`` folder: it is simulation code (the
demo's ``--answer-anchor-requests``, the site's ``anchors.json``, benches and tests), never system code.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.anchorsolve import MIN_CLICKS as SOLVE_MIN_CLICKS
from constructaide.bimgeom import glb_to_meshes
from constructaide.sampling import farthest_point_order
from schemas.messages import Intrinsics

from .truth import element_index, load_cameras, load_depth, load_ids, true_camera

F64 = NDArray[np.float64]

N_CLICKS = 12
NOISE_PX = 1.5  # Gaussian click noise per axis, pixels
MISS_RATE = 0.05  # gross mis-clicks: about one click in 20
SLIP_PX = (10.0, 60.0)  # a slipped click lands this far from the corner
NEIGHBOUR_PX = (10.0, 80.0)  # a neighbouring corner this far away can be clicked instead
MIN_CLICKS = 6  # a photo with fewer clickable corners is not a good anchor photo
AMBIGUOUS_PX = 4.0  # two distinct model points closer than this in the image: neither is clicked


class TooFewCorners(ValueError):
    """Fewer corners are visible than the anchor solve needs."""


@dataclass(frozen=True)
class Clicks:
    """One photo's clicks. ``pixels_px`` (N, 2) as clicked (OpenCV pixels), ``points_in_world_m`` (N, 3) the
    model points picked, ``target_px`` (N, 2) the exact projection of those points (truth, for scoring),
    ``mis_clicked`` indices of the gross mis-clicks, ``miss_kinds`` their kinds ("neighbour" or "slip"),
    ``n_clickable`` how many corners were clickable in the photo (``few`` when below :data:`MIN_CLICKS`)."""

    pixels_px: F64
    points_in_world_m: F64
    target_px: F64
    mis_clicked: NDArray[np.int64]
    miss_kinds: tuple[str, ...]
    n_clickable: int

    @property
    def few(self) -> bool:
        return self.n_clickable < MIN_CLICKS

    def anchor_points(self) -> list[dict]:
        """``anchors.json`` points: [{"pixel": [u, v], "world": [x, y, z]}, ...]."""
        return [
            {"pixel": [round(float(u), 3), round(float(v), 3)], "world": [round(float(c), 5) for c in w]}
            for (u, v), w in zip(self.pixels_px, self.points_in_world_m, strict=True)
        ]


def spread_sample(px: F64, n: int, rng: np.random.Generator) -> NDArray[np.int64]:
    """Indices of ``n`` of the (M, 2) pixels spread over the image by greedy farthest-point sampling (the first
    one random)."""
    return farthest_point_order(px, [int(rng.integers(len(px)))], n)


def photo_rng(seed: int, photo_rel: str) -> np.random.Generator:
    """The user's generator for one photo: reproducible for (seed, photo), independent across photos."""
    return np.random.default_rng([seed, zlib.crc32(photo_rel.encode())])


def click_points(
    target_px: F64,
    points_in_world_m: F64,
    rng: np.random.Generator,
    image_size: tuple[int, int],
    n_clicks: int = N_CLICKS,
    noise_px: float = NOISE_PX,
    miss_rate: float = MISS_RATE,
) -> Clicks:
    """A person clicking ``n_clicks`` of the clickable points (fewer when fewer are given), spread over the image.

    ``target_px`` (M, 2) are where the clickable points show in the photo, ``points_in_world_m`` (M, 3) the
    model points, ``image_size`` (width, height). Each click is the target + N(0, ``noise_px``) per axis. With
    probability ``miss_rate`` a click is a gross mis-click, the model point staying the intended one: half of
    them (when one exists) a **neighbouring corner** 10-80 px away clicked instead (the nearest such clickable
    point, + noise), the others a **slip** 10-60 px from the corner in a random direction. Raises
    :class:`TooFewCorners` with fewer than the anchor solve's 4 points.
    """
    target_px = np.asarray(target_px, np.float64).reshape(-1, 2)
    points_in_world_m = np.asarray(points_in_world_m, np.float64).reshape(-1, 3)
    if len(target_px) < SOLVE_MIN_CLICKS:
        raise TooFewCorners(f"only {len(target_px)} clickable corners (< {SOLVE_MIN_CLICKS})")
    pick = spread_sample(target_px, n_clicks, rng)
    target = target_px[pick]
    clicked = target + rng.normal(0.0, noise_px, target.shape)
    miss = np.nonzero(rng.random(len(pick)) < miss_rate)[0]
    kinds = []
    for k in miss:
        d = np.linalg.norm(target_px - target[k], axis=1)
        near = np.nonzero((d >= NEIGHBOUR_PX[0]) & (d <= NEIGHBOUR_PX[1]))[0]
        if len(near) and rng.random() < 0.5:
            clicked[k] = target_px[near[np.argmin(d[near])]] + rng.normal(0.0, noise_px, 2)
            kinds.append("neighbour")
        else:
            a = rng.uniform(0.0, 2.0 * np.pi)
            clicked[k] = target[k] + rng.uniform(*SLIP_PX) * np.array([np.cos(a), np.sin(a)])
            kinds.append("slip")
    W, H = image_size
    clicked = np.clip(clicked, 0.0, [W - 1.0, H - 1.0])
    return Clicks(clicked, points_in_world_m[pick], target, miss.astype(np.int64), tuple(kinds), len(target_px))


def _feature_edges(vertices: F64, faces: NDArray) -> F64:
    """(E, 2, 3) edges of a triangle mesh where the surface creases (> 1 deg) or ends: polygon edges, without
    the diagonals of a triangulated face."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    key = np.round(vertices, 6)
    adjacent: dict[tuple, list[int]] = {}
    for t, f in enumerate(faces):
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            ka, kb = tuple(key[a]), tuple(key[b])
            adjacent.setdefault((ka, kb) if ka < kb else (kb, ka), []).append(t)
    out = [e for e, ts in adjacent.items() if len(ts) != 2 or float(n[ts[0]] @ n[ts[1]]) < np.cos(np.radians(1.0))]
    return np.asarray(out, np.float64).reshape(-1, 2, 3)


def _edge_crossings(edges_a: F64, edges_b: F64, tol_m: float = 1e-4, end_m: float = 1e-3) -> F64:
    """(K, 3) points where an edge of a (Ea, 2, 3) set crosses an edge of b strictly inside both (an X, not a
    shared vertex nor a T whose end is a vertex already)."""
    p, u = edges_a[:, None, 0], (edges_a[:, 1] - edges_a[:, 0])[:, None]
    q, v = edges_b[None, :, 0], (edges_b[:, 1] - edges_b[:, 0])[None]
    w = p - q
    a, b, c = np.sum(u * u, -1), np.sum(u * v, -1), np.sum(v * v, -1)
    d, e = np.sum(u * w, -1), np.sum(v * w, -1)
    den = a * c - b * b
    skew = den > 1e-12 * a * c  # not parallel
    den = np.where(skew, den, 1.0)
    s, t = (b * e - c * d) / den, (a * e - b * d) / den
    la, lb = np.sqrt(a), np.sqrt(c)
    ok = skew & (s * la > end_m) & ((1 - s) * la > end_m) & (t * lb > end_m) & ((1 - t) * lb > end_m)
    pa = p + s[..., None] * u
    pb = q + t[..., None] * v
    ok &= np.linalg.norm(pa - pb, axis=-1) < tol_m
    return pa[ok].reshape(-1, 3)


@dataclass(frozen=True)
class ModelCorners:
    """The points a person can pick precisely in the BIM viewer: every element vertex and every crossing of two
    elements' feature edges. ``points_m`` (M, 3) in the site frame, ``owners`` (M, k) int ID-image indices of
    the elements each point belongs to (padded with -1)."""

    points_m: F64
    owners: NDArray[np.int64]

    @classmethod
    def from_meshes(cls, meshes: Mapping[int, tuple[F64, NDArray]]) -> ModelCorners:
        """From ``{ID-image index: (vertices (N, 3) m, triangles (T, 3))}``."""
        owners: dict[tuple, set[int]] = {}
        for idx, (v, _) in meshes.items():
            for p in np.unique(np.round(np.asarray(v, np.float64), 6), axis=0):
                owners.setdefault(tuple(p), set()).add(int(idx))
        edges = {idx: _feature_edges(np.asarray(v, np.float64), np.asarray(f)) for idx, (v, f) in meshes.items()}
        bounds = {idx: (e.reshape(-1, 3).min(0) - 1e-3, e.reshape(-1, 3).max(0) + 1e-3) for idx, e in edges.items()}
        keys = sorted(k for k in edges if len(edges[k]))
        for i, ka in enumerate(keys):
            lo_a, hi_a = bounds[ka]
            for kb in keys[i + 1 :]:
                lo_b, hi_b = bounds[kb]
                if np.any(lo_a > hi_b) or np.any(lo_b > hi_a):
                    continue
                for p in _edge_crossings(edges[ka], edges[kb]):
                    owners.setdefault(tuple(np.round(p, 6)), set()).update((ka, kb))
        order = sorted(owners)  # the same points in the same order however the meshes were listed
        pts = np.array(order, np.float64).reshape(-1, 3)
        width = max((len(s) for s in owners.values()), default=1)
        own = np.full((len(pts), width), -1, np.int64)
        for r, p in enumerate(order):
            own[r, : len(owners[p])] = sorted(owners[p])
        return cls(pts, own)

    def visible(
        self,
        intr: Intrinsics,
        world_from_camera: F64,
        ids: NDArray,
        depth_m: NDArray,
        min_height_m: float = 0.05,
    ) -> tuple[F64, F64]:
        """Points clickable in a photo: (N, 2) exact pixels and (N, 3) model points. Clickable = inside the
        image (away from the border), above the ground, visible (in a 3x3 window the ID image shows one of its
        elements and the depth matches within 2 % + 5 cm), looks like a corner (:func:`_looks_like_corner`)
        and no other distinct model point within 4 px (a person could not tell which one is meant)."""
        H, W = ids.shape
        px, z = cam.project_points(intr, cam.invert_rigid(world_from_camera), self.points_m)
        m = 8  # the corner test looks 6 px around
        ok = np.all(np.isfinite(px), axis=1) & (z > 0) & (self.points_m[:, 2] >= min_height_m)
        ok &= (px[:, 0] >= m) & (px[:, 0] < W - 1 - m) & (px[:, 1] >= m) & (px[:, 1] < H - 1 - m)
        sel = np.nonzero(ok)[0]
        uv = np.round(px[sel]).astype(np.int64)
        win = np.arange(-1, 2)
        vv = uv[:, 1, None, None] + win[None, :, None]
        uu = uv[:, 0, None, None] + win[None, None, :]
        win_ids = ids[vv, uu].reshape(len(sel), -1).astype(np.int64)
        win_d = depth_m[vv, uu].reshape(len(sel), -1).astype(np.float64)
        shows = np.any(win_ids[:, :, None] == self.owners[sel][:, None, :], axis=(1, 2))
        depth_ok = np.min(np.abs(win_d - z[sel, None]), axis=1) <= 0.02 * z[sel] + 0.05
        sel = sel[shows & depth_ok]
        corner = _looks_like_corner(intr, ids, depth_m, px[sel])
        sel = sel[corner]
        pix, pts = px[sel], self.points_m[sel]
        if len(sel) > 1:
            dpx = np.linalg.norm(pix[:, None] - pix[None], axis=-1)
            dw = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
            clash = (dpx < AMBIGUOUS_PX) & (dw > 0.01)
            keep = ~np.any(clash, axis=1)
            pix, pts = pix[keep], pts[keep]
        return pix, pts


def _surfaces(intr: Intrinsics, ids: NDArray, depth_m: NDArray, centre_uv: NDArray[np.int64], r: int):
    """Patches (M, 2r+1, 2r+1) around integer pixels (M, 2): element index, depth (m, 0 = sky) and unit surface
    normal (camera frame, from the back-projected depth by the one-sided difference that stays on the surface)."""
    P = 2 * r + 1
    off = np.arange(-r - 1, r + 2)  # one pixel more on each side for the differences
    vv, uu = np.broadcast_arrays(
        centre_uv[:, 1, None, None] + off[None, :, None], centre_uv[:, 0, None, None] + off[None, None, :]
    )
    z_all = depth_m[vv, uu].astype(np.float64)
    pix = np.stack([uu, vv], axis=-1).reshape(-1, 2).astype(np.float64)
    xy = cam.pixels_to_normalized(intr, pix).reshape(len(centre_uv), P + 2, P + 2, 2)
    pts = np.concatenate([xy * z_all[..., None], z_all[..., None]], axis=-1)
    inner = (slice(None), slice(1, -1), slice(1, -1))

    def tangent(fwd: F64, bwd: F64) -> F64:
        return np.where((np.abs(fwd[..., 2]) <= np.abs(bwd[..., 2]))[..., None], fwd, bwd)

    t_u = tangent(pts[:, 1:-1, 2:] - pts[inner], pts[inner] - pts[:, 1:-1, :-2])
    t_v = tangent(pts[:, 2:, 1:-1] - pts[inner], pts[inner] - pts[:, :-2, 1:-1])
    n = np.cross(t_u, t_v)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return ids[vv, uu].astype(np.int64)[inner], z_all[inner], n


CIRCLE_RADII_PX = (2.0, 3.5, 5.0)
CIRCLE_SAMPLES = 32
RAY_TOLERANCE_DEG = 22.0  # a surface boundary leaving the point crosses every circle at this same angle
CORNER_MAX_SPAN_DEG = 140.0  # two rays closer to opposite than 180 - 140 deg are one straight edge
RAY_MERGE_DEG = 40.0  # rays closer than this are one edge (thin strips, parallel edges a pixel apart)


def _circle_transitions(lab: NDArray, z: F64, n: F64) -> F64:
    """Angles (rad) where the visible surface changes along a closed circle of samples (S,) taken at angles
    2 pi k / S: the element changes, sky begins or ends, the depth jumps (> 3 %) or the surface creases
    (> 20 deg). Runs shorter than 2 samples (jagged ID edges) are merged into their neighbour."""
    S = len(lab)
    nxt = np.roll(np.arange(S), -1)
    both = (z > 0) & (z[nxt] > 0)
    change = (lab != lab[nxt]) | ((z > 0) != (z[nxt] > 0))
    change |= both & (np.abs(z - z[nxt]) > 0.03 * np.minimum(z, z[nxt]))
    change |= both & (np.sum(n * n[nxt], axis=-1) < np.cos(np.radians(20.0)))
    cuts = list(np.nonzero(change)[0])
    while len(cuts) > 2:
        runs = np.diff(np.r_[cuts, cuts[0] + S])  # run k goes from cut k to cut k+1
        k = int(np.argmin(runs))
        if runs[k] >= 2:
            break
        del cuts[(k + 1) % len(cuts)]
    if len(cuts) < 2:
        return np.zeros(0)
    return 2.0 * np.pi * (np.asarray(cuts, np.float64) + 0.5) / S


def _angle_gap(a: F64, b: F64) -> F64:
    """Smallest absolute difference (rad) between each angle of a (A,) and the angles b (B,) (inf if B = 0)."""
    if len(b) == 0:
        return np.full(len(a), np.inf)
    d = np.abs((a[:, None] - b[None] + np.pi) % (2.0 * np.pi) - np.pi)
    return d.min(axis=1)


def _merge_rays(rays: F64) -> F64:
    """Circular means of the groups of angles (rad) that chain within :data:`RAY_MERGE_DEG` of each other."""
    if len(rays) < 2:
        return rays
    a = np.sort(rays % (2.0 * np.pi))
    gaps = np.diff(np.r_[a, a[0] + 2.0 * np.pi])
    if np.all(gaps < np.radians(RAY_MERGE_DEG)):
        return np.array([float(np.arctan2(np.sin(a).sum(), np.cos(a).sum()))])
    start = int(np.argmax(gaps)) + 1  # begin after the widest gap, so no group wraps around
    a = np.roll(a, -start)
    groups, cur = [], [a[0]]
    for x in a[1:]:
        if (x - cur[-1]) % (2.0 * np.pi) < np.radians(RAY_MERGE_DEG):
            cur.append(x)
        else:
            groups.append(cur)
            cur = [x]
    groups.append(cur)
    return np.array([float(np.arctan2(np.sin(g).sum(), np.cos(g).sum())) for g in groups])


def _looks_like_corner(intr: Intrinsics, ids: NDArray, depth_m: NDArray, px: F64) -> NDArray[np.bool_]:
    """(M,) whether each exact pixel (M, 2) is a corner a person can point at: surface boundaries (another
    element, sky, a depth jump, a crease) leave the point as rays - crossing circles of 2, 3.5 and 5 px around it
    at the same angle (within 22 deg), rays within 40 deg of each other counting as one - and there are three
    or more rays (a T, Y or X junction) or two that are not one straight line (an L, 40-140 deg apart). A point
    along a straight edge, inside a face, or beside a junction (parallel edges, a corner a few pixels away) is
    not a corner."""
    if len(px) == 0:
        return np.zeros(0, dtype=bool)
    r = int(np.ceil(max(CIRCLE_RADII_PX))) + 1
    c = np.round(px).astype(np.int64)
    lab, z, n = _surfaces(intr, ids, depth_m, c, r)
    ang = 2.0 * np.pi * np.arange(CIRCLE_SAMPLES) / CIRCLE_SAMPLES
    frac = px - c
    m = np.arange(len(px))[:, None]
    samples = []
    for rc in CIRCLE_RADII_PX:
        du = np.rint(frac[:, 0, None] + rc * np.cos(ang)[None]).astype(np.int64) + r
        dv = np.rint(frac[:, 1, None] + rc * np.sin(ang)[None]).astype(np.int64) + r
        samples.append((lab[m, dv, du], z[m, dv, du], n[m, dv, du]))
    tol = np.radians(RAY_TOLERANCE_DEG)
    ok = np.zeros(len(px), dtype=bool)
    for i in range(len(px)):
        inner, mid, outer = (_circle_transitions(lb[i], zz[i], nn[i]) for lb, zz, nn in samples)
        rays = _merge_rays(mid[(_angle_gap(mid, inner) < tol) & (_angle_gap(mid, outer) < tol)])
        if len(rays) >= 3:
            ok[i] = True
        elif len(rays) == 2:
            opposite = abs(abs((rays[1] - rays[0] + np.pi) % (2.0 * np.pi) - np.pi) - np.pi)
            ok[i] = np.degrees(opposite) > 180.0 - CORNER_MAX_SPAN_DEG
    return ok


def _index_meshes(site_dir: Path) -> dict[int, tuple[F64, NDArray]]:
    """The site's model (``model/building.glb``) keyed by ID-image index."""
    meshes = glb_to_meshes((Path(site_dir) / "model" / "building.glb").read_bytes())
    return {idx: meshes[guid] for idx, guid in element_index(site_dir).items() if guid in meshes}


class SiteClicker:
    """The simulated user for one site folder (model corners computed once, cameras loaded once)."""

    def __init__(self, site_dir: Path, cameras: dict[str, dict] | None = None) -> None:
        self.site_dir = Path(site_dir)
        self.cameras = cameras if cameras is not None else load_cameras(site_dir)
        self.corners = ModelCorners.from_meshes(_index_meshes(site_dir))

    def clickable(self, photo_rel: str) -> tuple[F64, F64]:
        """(N, 2) exact pixels and (N, 3) model points of the corners clickable in a photo."""
        intr, world_from_camera = true_camera(self.site_dir, photo_rel, self.cameras)
        ids, depth = load_ids(self.site_dir, photo_rel), load_depth(self.site_dir, photo_rel)
        return self.corners.visible(intr, world_from_camera, ids, depth)

    def clicks(
        self,
        photo_rel: str,
        n_clicks: int = N_CLICKS,
        noise_px: float = NOISE_PX,
        seed: int = 0,
        miss_rate: float = MISS_RATE,
    ) -> Clicks:
        """The user's clicks for a photo (``photo_rel`` relative to ``photos/``); see :func:`click_points`.
        Raises :class:`TooFewCorners` when fewer than 4 corners are clickable."""
        rec = self.cameras[photo_rel]
        px, world = self.clickable(photo_rel)
        try:
            return click_points(
                px, world, photo_rng(seed, photo_rel), (rec["width"], rec["height"]), n_clicks, noise_px, miss_rate
            )
        except TooFewCorners as exc:
            raise TooFewCorners(f"{photo_rel}: {exc}") from None


def realistic_clicks(
    site_dir: Path,
    photo_rel: str,
    n_clicks: int = N_CLICKS,
    noise_px: float = NOISE_PX,
    seed: int = 0,
    miss_rate: float = MISS_RATE,
    cameras: dict[str, dict] | None = None,
) -> Clicks:
    """One photo's clicks by the simulated user (builds a :class:`SiteClicker`; use one for many photos)."""
    return SiteClicker(site_dir, cameras).clicks(photo_rel, n_clicks, noise_px, seed, miss_rate)


def simulated_clicks(
    site_dir: Path,
    photo_rel: str,
    n_clicks: int = N_CLICKS,
    noise_px: float = NOISE_PX,
    seed: int = 0,
    cameras: dict[str, dict] | None = None,
) -> tuple[F64, F64]:
    """The old interface: (pixels (N, 2), model points (N, 3)) of :func:`realistic_clicks` (mis-clicks
    included). Raises ValueError (:class:`TooFewCorners`) with fewer than 4 clickable corners."""
    c = realistic_clicks(site_dir, photo_rel, n_clicks, noise_px, seed, cameras=cameras)
    return c.pixels_px, c.points_in_world_m
