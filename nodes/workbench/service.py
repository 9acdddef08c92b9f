"""The workbench's operations behind the JSON API: photos and their status, picks, live anchor solves, selections,
annotations transferred to every registered photo, peeks through time and photoreal previews.

:class:`Workbench` is fed bus messages (:meth:`Workbench.apply`) by the node shell or from a recording, and hands
what the user made (AnchorClicks, Annotation) to ``publish`` (None: review only, nothing leaves). Bad requests
raise :class:`ApiError` with an HTTP status and a reason. GL renders run on one worker thread (EGL contexts are
thread-bound); everything else is guarded by one lock.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide import imagecodec
from constructaide.anchorsolve import MIN_CLICKS, AnchorSolution, DegenerateAnchors, solve_anchor
from nodes.workbench import progress as progress_view
from nodes.workbench import regions
from nodes.workbench.geometry import GROW_BY, ModelGeometry
from nodes.workbench.idrender import IdImage, IdRenderer, intrinsics_scaled_by
from nodes.workbench.state import EventHub, SiteState, merged_model
from schemas import keys
from schemas.messages import (
    AnchorClicks,
    AnchorPoint,
    Annotation,
    BimElement,
    BimModel,
    Intrinsics,
    Message,
    Photo,
    Registration,
)

STATUS_RGBA: dict[str, tuple[int, int, int, int]] = {
    "ahead": (40, 200, 60, 150),
    "on_time": (255, 255, 255, 110),
    "behind": (230, 40, 40, 160),
    "built": (40, 200, 60, 150),
    "not_built": (230, 40, 40, 160),
    "needs_review": (20, 40, 150, 190),
    "occluded": (120, 120, 120, 150),
    "": (255, 200, 0, 150),
}
RENDER_WIDTH_PX = 960  # ID renders for regions and transfer
THUMB_WIDTH_PX = 240
FUTURE_RGBA = (255, 170, 0, 200)
STANDING_RGBA = (200, 200, 200, 150)

MAX_COORD_PX = 32768.0  # polygon / brush vertices beyond this are refused (off-image parts are clipped)
INT64 = 1 << 63
MAX_WORLD_M = 1e6  # site-local metres: world points and camera positions beyond this are refused
MAX_FOCAL_PX = 1e6

Publish = Callable[[str, Message], None]


class ApiError(Exception):
    """A request the workbench cannot serve: HTTP ``status`` and a reason for the person."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


def points_px(x: Any, what: str) -> list[tuple[float, float]]:
    """[(u, v)] of a JSON list of pixel pairs: finite, within +-:data:`MAX_COORD_PX`; ApiError 400 otherwise."""
    try:
        pts = [(float(u), float(v)) for u, v in x]
    except (TypeError, ValueError) as e:
        raise ApiError(400, f"{what} must be a list of [u, v] pixel pairs: {e}") from None
    if not all(np.isfinite(c) and abs(c) <= MAX_COORD_PX for p in pts for c in p):
        raise ApiError(400, f"{what} has non-finite or absurd pixel coordinates (beyond {MAX_COORD_PX:.0f} px)")
    return pts


def rigid_pose(T: NDArray[np.float64], max_t_m: float = MAX_WORLD_M) -> bool:
    """Whether a 4x4 is finite and rigid: orthonormal rotation (det +1), |t| <= ``max_t_m``, last row 0 0 0 1."""
    if T.shape != (4, 4) or not np.isfinite(T).all() or np.abs(T[:3, 3]).max() > max_t_m:
        return False
    R = T[:3, :3]
    if np.abs(R).max() > 1.001:  # before any product: no overflow on absurd entries
        return False
    ok_rot = np.allclose(R.T @ R, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0
    return bool(ok_rot and np.allclose(T[3], (0.0, 0.0, 0.0, 1.0)))


def at_ns_of(x: Any) -> int:
    """An integer time in ns (int64); ApiError 400 otherwise."""
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x) or not -INT64 <= x < INT64:
        raise ApiError(400, f"at_ns must be an integer time in ns, not {str(x)[:40]}")
    return int(x)


def photo_id_of(x: Any) -> str | None:
    if x is not None and not isinstance(x, str):
        raise ApiError(400, f"photo_id must be a string, not {type(x).__name__}")
    return x


def decode_rgb(data: bytes) -> NDArray[np.uint8]:
    """(H, W, 3) RGB of a stored JPEG/PNG; ApiError 422 when undecodable."""
    try:
        return imagecodec.decode_rgb(data)
    except ValueError as e:
        raise ApiError(422, "stored image is not a decodable JPEG/PNG") from e


def fit_intrinsics(intr: Intrinsics, width_px: int, height_px: int) -> Intrinsics:
    """Intrinsics for the photo's stored size when a registration was solved at another size."""
    if width_px <= 0 or (intr.width_px, intr.height_px) == (width_px, height_px):
        return intr
    return cam.scaled_intrinsics(intr, width_px, height_px)


class _Points(msgspec.Struct, forbid_unknown_fields=True):
    pixel: tuple[float, float]
    world: tuple[float, float, float]


class AnchorBody(msgspec.Struct, forbid_unknown_fields=True):
    points: list[_Points]
    focal_px: float | None = None
    author: str = ""


def _leave_one_out(
    px: NDArray[np.float64], world: NDArray[np.float64], w: int, h: int, focal: float | None
) -> tuple[AnchorSolution, NDArray[np.float64], NDArray[np.bool_]] | None:
    """The best solve without one click (lowest RMS of the others), every click's residual under it, and that
    click flagged; None when no subset solves or the left-out click fits as well as the others."""
    best = None
    for i in range(len(px)):
        keep = np.arange(len(px)) != i
        try:
            sol = solve_anchor(px[keep], world[keep], w, h, focal_px=focal, solve_distortion=False)
        except DegenerateAnchors:
            continue
        if best is None or sol.rms_px < best[0].rms_px:
            best = (sol, i)
    if best is None:
        return None
    sol, i = best
    proj, _ = cam.project_points(sol.intrinsics, cam.invert_rigid(sol.world_from_camera), world)
    residuals = np.linalg.norm(proj - px, axis=1)
    residuals[~np.isfinite(residuals)] = 1e6  # behind the camera
    if not residuals[i] > max(sol.outlier_threshold_px, 5.0 * sol.rms_px, 3.0):
        return None
    flags = np.zeros(len(px), bool)
    flags[i] = True
    return sol, residuals, flags


class Workbench:
    """See module docstring."""

    def __init__(self, site: str, publish: Publish | None = None, render_width_px: int = RENDER_WIDTH_PX) -> None:
        self.site = site
        self.publish = publish
        self.render_width_px = render_width_px
        self.state = SiteState()
        self.events = EventHub()
        self._lock = threading.RLock()
        self._gl = ThreadPoolExecutor(1, thread_name_prefix="workbench-gl")
        self._renderer: IdRenderer | None = None
        self._geometry: ModelGeometry | None = None
        self._model: BimModel | None = None
        self._renders: OrderedDict[tuple, IdImage] = OrderedDict()
        self._thumbs: dict[str, bytes] = {}
        self._lifted: dict[tuple[str, int], NDArray[np.float64]] = {}

    @property
    def live(self) -> bool:
        return self.publish is not None

    # -- inputs -----------------------------------------------------------------------------------------------

    def apply(self, msg: Message) -> None:
        """Take one bus message (from the node shell or a recording)."""
        with self._lock:
            events = self.state.apply(msg)
            if events and events[0]["kind"] == "model":
                self._geometry, self._model = None, None
                self._renders.clear()
                self._lifted.clear()
            if isinstance(msg, Registration):
                self._renders = OrderedDict((k, v) for k, v in self._renders.items() if k[0] != msg.photo_id)
        self.events.publish(events)

    # -- model ------------------------------------------------------------------------------------------------

    def model(self) -> BimModel:
        with self._lock:
            if self.state.model is None:
                raise ApiError(409, "no BIM model received yet")
            if self._model is None:
                self._model = merged_model(self.state.model, self.state.updates)
            return self._model

    def geometry(self) -> ModelGeometry:
        with self._lock:
            if self._geometry is None:
                self._geometry = ModelGeometry(self.model())
            return self._geometry

    def model_info(self) -> dict[str, Any]:
        g = self.geometry()
        times = [p.capture_time_ns for p in self.state.photos.values()]
        tasks = self.model().tasks
        t_all = times + [t.planned_start_ns for t in tasks] + [t.planned_finish_ns for t in tasks]
        return {
            "revision": g.revision,
            "elements": [
                {**g.element_info(e.global_id), "index": i, "has_geometry": bool(i in set(g.tri_elements.tolist()))}
                for i, e in enumerate(g.elements)
            ],
            "bbox_min_m": g.bbox_min_m.tolist(),
            "bbox_max_m": g.bbox_max_m.tolist(),
            "time_range_ns": [min(t_all), max(t_all)] if t_all else [0, 0],
            "grow_by": list(GROW_BY),
        }

    def visible_indices(self, at_ns: int) -> list[int]:
        return np.nonzero(self.geometry().standing(at_ns))[0].tolist()

    # -- photos -----------------------------------------------------------------------------------------------

    def photo(self, photo_id: str) -> Photo:
        p = self.state.photos.get(photo_id)
        if p is None:
            raise ApiError(404, f"unknown photo {photo_id!r}")
        return p

    def photo_detail(self, photo_id: str) -> dict[str, Any]:
        with self._lock:
            p = self.photo(photo_id)
            out = self.state.photo_entry(p)
            reg = self.state.registrations.get(photo_id)
            out["registration"] = msgspec.to_builtins(reg) if reg is not None else None
            vg = self.state.viewpoints.get(photo_id)
            out["viewpoint_neighbours"] = (
                [
                    {"photo_id": n.photo_id, "capture_time": self.state.photos[n.photo_id].capture_time_ns}
                    for n in vg.neighbours
                    if n.photo_id in self.state.photos
                ]
                if vg is not None
                else []
            )
            return out

    def camera(self, photo_id: str) -> cam.PinholeCamera:
        p = self.photo(photo_id)
        reg = self.state.registrations.get(photo_id)
        camera = None if reg is None else cam.registered_camera(reg)
        if camera is None:
            raise ApiError(409, f"photo {photo_id} is not registered (status {self.state.status(photo_id)})")
        return cam.PinholeCamera(fit_intrinsics(camera.intrinsics, p.width_px, p.height_px), camera.world_from_camera)

    def thumbnail(self, photo_id: str) -> bytes:
        p = self.photo(photo_id)
        if photo_id not in self._thumbs:
            try:
                img = imagecodec.decode_bgr(p.data, reduced=2)
            except ValueError as e:
                raise ApiError(422, f"photo {photo_id} is not a decodable image") from e
            h = round(img.shape[0] * THUMB_WIDTH_PX / img.shape[1])
            small = np.asarray(cv2.resize(img, (THUMB_WIDTH_PX, h), interpolation=cv2.INTER_AREA), np.uint8)
            self._thumbs[photo_id] = imagecodec.encode_jpeg(small, quality=95)
        return self._thumbs[photo_id]

    def overlay_png(self, photo_id: str, mode: str) -> bytes:
        self.photo(photo_id)
        ov = self.state.overlays.get((photo_id, mode))
        if ov is None:
            have = sorted(m for (pid, m) in self.state.overlays if pid == photo_id)
            raise ApiError(404, f"no {mode!r} overlay for photo {photo_id} (have: {', '.join(have) or 'none'})")
        return ov.image_png

    def mask_png(self, photo_id: str, kind: str) -> bytes:
        self.photo(photo_id)
        m = self.state.masks.get((photo_id, kind))
        if m is None or m.status != "ok" or not m.mask_png:
            raise ApiError(404, f"no usable {kind!r} occlusion mask for photo {photo_id}")
        return m.mask_png

    def anchor_queue(self) -> list[dict[str, Any]]:
        with self._lock:
            out = []
            for pid, need in self.state.needs_anchor.items():
                p = self.state.photos.get(pid)
                out.append(
                    {
                        "photo_id": pid,
                        "reason": need.reason,
                        "num_matched_tracks": need.num_matched_tracks,
                        "filename": p.filename if p else "",
                        "camera_id": p.camera_id if p else None,
                        "capture_time": p.capture_time_ns if p else None,
                    }
                )
            return sorted(out, key=lambda e: (e["capture_time"] or 0, e["photo_id"]))

    # -- renders ----------------------------------------------------------------------------------------------

    def _render(self, photo_id: str, at_ns: int | None = None) -> tuple[IdImage, cam.PinholeCamera]:
        """ID / depth render of a registered photo at ``at_ns`` (default: its capture time), cached; and the
        camera at the render's scale."""
        g = self.geometry()
        camera = self.camera(photo_id)
        at = self.photo(photo_id).capture_time_ns if at_ns is None else at_ns
        visible = g.standing(at)
        key = (photo_id, g.revision, np.packbits(visible).tobytes())
        with self._lock:
            hit = self._renders.get(key)
        if hit is None:
            if self._renderer is None or self._renderer.geometry is not g:
                old, self._renderer = self._renderer, None
                if old is not None:
                    self._gl.submit(old.close).result()
                self._renderer = self._gl.submit(IdRenderer, g).result()
            renderer = self._renderer
            hit = self._gl.submit(renderer.render, camera, visible, self.render_width_px).result()
            with self._lock:
                self._renders[key] = hit
                while len(self._renders) > 48:
                    self._renders.popitem(last=False)
        scaled = cam.PinholeCamera(intrinsics_scaled_by(camera.intrinsics, hit.scale), camera.world_from_camera)
        return hit, scaled if hit.scale < 1.0 else camera

    def _outline(self, img: IdImage, mask: NDArray[np.bool_]) -> list[list[list[float]]]:
        polys = regions.mask_polygons(mask)
        return [img.to_photo_px(np.asarray(p)).round(1).tolist() for p in polys]

    def _occluded(self, photo_id: str, shape: tuple[int, int]) -> NDArray[np.bool_] | None:
        m = self.state.masks.get((photo_id, "combined")) or self.state.masks.get((photo_id, "static"))
        if m is None or m.status != "ok" or not m.mask_png:
            return None
        try:
            return imagecodec.mask_of_message(m, shape)
        except ValueError:
            return None

    # -- picks ------------------------------------------------------------------------------------------------

    def pick_photo(self, photo_id: str, u: float, v: float, snap_px: float = 0.0) -> dict[str, Any]:
        p = self.photo(photo_id)
        camera = self.camera(photo_id)
        w, h = camera.intrinsics.width_px, camera.intrinsics.height_px
        if not (-0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
            raise ApiError(400, f"pixel ({u}, {v}) is outside the {w}x{h} photo")
        g = self.geometry()
        return g.pick(camera, u, v, g.standing(p.capture_time_ns), snap_px=snap_px).as_json()

    def pick_view(self, body: dict[str, Any]) -> dict[str, Any]:
        """Pick in a model view: ``world_from_camera`` (16), ``intrinsics`` {width_px, height_px, f_px, cx_px,
        cy_px}, ``u``, ``v``, optional ``at_ns`` (elements standing then; default all) and ``snap_px``."""
        try:
            intr = msgspec.convert(body["intrinsics"], Intrinsics)
            wfc = cam.pose_from_tuple(tuple(float(x) for x in body["world_from_camera"]))
            u, v = float(body["u"]), float(body["v"])
            snap = float(body.get("snap_px", 8.0))
            at = body.get("at_ns")
        except (KeyError, TypeError, ValueError, msgspec.ValidationError) as e:
            raise ApiError(400, f"pick needs world_from_camera (16 numbers), intrinsics, u and v: {e}") from None
        if not rigid_pose(wfc):
            raise ApiError(
                400, "world_from_camera must be a rigid transform (rotation, |t| <= 1e6 m, last row 0 0 0 1)"
            )
        numbers = [u, v, snap, intr.f_px, intr.fy_over_fx, intr.cx_px, intr.cy_px, intr.k1, intr.k2]
        if (
            not np.isfinite(numbers).all()
            or not (0 < intr.f_px <= MAX_FOCAL_PX and 0.01 <= intr.fy_over_fx <= 100 and 0 <= snap <= MAX_COORD_PX)
            or max(abs(intr.cx_px), abs(intr.cy_px)) > MAX_COORD_PX
            or max(abs(intr.k1), abs(intr.k2)) > 100
        ):
            raise ApiError(
                400,
                "u, v, snap_px and the intrinsics must be finite and plausible: 0 < f_px <= 1e6, fy_over_fx in "
                "[0.01, 100], |cx|, |cy| <= 32768 px, |k1|, |k2| <= 100",
            )
        if not (0 < intr.width_px <= MAX_COORD_PX and 0 < intr.height_px <= MAX_COORD_PX):
            raise ApiError(400, f"view size {intr.width_px}x{intr.height_px} is not positive or beyond 32768 px")
        if not (-0.5 <= u < intr.width_px - 0.5 and -0.5 <= v < intr.height_px - 0.5):
            raise ApiError(400, f"pixel ({u}, {v}) is outside the {intr.width_px}x{intr.height_px} view")
        g = self.geometry()
        visible = g.standing(at_ns_of(at)) if at is not None else None
        return g.pick(cam.PinholeCamera(intr, wfc), u, v, visible, snap_px=snap).as_json()

    # -- anchors ----------------------------------------------------------------------------------------------

    def solve(self, photo_id: str, body: bytes) -> dict[str, Any]:
        """Pose from clicks; ``points`` [{pixel: [u, v], world: [x, y, z]}] (>= 4)."""
        p = self.photo(photo_id)
        try:
            req = msgspec.json.decode(body, type=AnchorBody)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise ApiError(
                400, f'body must be {{"points": [{{"pixel": [u, v], "world": [x, y, z]}}, ...]}}: {e}'
            ) from None
        w, h = p.width_px, p.height_px
        if w <= 0 or h <= 0:
            h, w = decode_rgb(p.data).shape[:2]
        px = np.array([q.pixel for q in req.points], np.float64).reshape(-1, 2)
        bad = [i for i, (u, v) in enumerate(px) if not (-0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5)]
        if bad:
            raise ApiError(400, f"clicks {bad} are outside the {w}x{h} photo")
        world = np.array([q.world for q in req.points], np.float64).reshape(-1, 3)
        far = [i for i, x in enumerate(world) if not (np.isfinite(x).all() and np.abs(x).max() <= MAX_WORLD_M)]
        if far:
            raise ApiError(400, f"clicks {far} have non-finite or absurd world points (beyond {MAX_WORLD_M:.0e} m)")
        if req.focal_px is not None and not (np.isfinite(req.focal_px) and 0 < req.focal_px <= MAX_FOCAL_PX):
            raise ApiError(400, f"focal_px {req.focal_px} is not a positive focal length in pixels (<= 1e6)")
        focal = req.focal_px or p.focal_px
        note = ""
        try:
            sol = solve_anchor(px, world, w, h, focal_px=focal, solve_distortion=False)
            residuals, misclick = sol.residuals_px, sol.outlier_mask
        except DegenerateAnchors as e:
            # One mis-click among few clicks can leave no camera at all (e.g. drag a free focal into a mirrored one):
            # solve without each click in turn and flag the one whose removal explains the rest.
            found = _leave_one_out(px, world, w, h, focal) if len(px) > MIN_CLICKS else None
            if found is None:
                raise ApiError(422, str(e)) from None
            sol, residuals, misclick = found
            note = f"solved without click {int(np.argmax(misclick)) + 1}: with it, {e}"
        if sol.ambiguous:
            warn = (
                f"these clicks also fit a camera {sol.ambiguous_turn_deg:.0f} deg turned from this one: add clicks "
                "spread over the photo, on points at different depths"
            )
            note = f"{note}; {warn}" if note else warn
        return {
            "photo_id": photo_id,
            "residuals_px": [round(float(r), 3) for r in residuals],
            "world_from_camera": cam.pose_to_tuple(sol.world_from_camera),
            "intrinsics": msgspec.to_builtins(sol.intrinsics),
            "rms_px": sol.rms_px,
            "misclick": [bool(b) for b in misclick],
            "loo_errors_px": [None if not np.isfinite(e) else round(float(e), 3) for e in sol.loo_errors_px],
            "outlier_threshold_px": float(sol.outlier_threshold_px),
            "focal_solved": sol.focal_solved,
            "note": note,
            "_req": req,
        }

    def submit_anchors(self, photo_id: str, body: bytes) -> dict[str, Any]:
        """Solve, then (live) publish the clicks as AnchorClicks for the register node."""
        out = self.solve(photo_id, body)
        req: AnchorBody = out.pop("_req")
        p = self.photo(photo_id)
        msg = AnchorClicks(
            site=self.site,
            photo_id=photo_id,
            image_name=p.filename,
            points=tuple(AnchorPoint(pixel_px=q.pixel, point_in_world_m=q.world) for q in req.points),
            focal_px=req.focal_px or p.focal_px,
            author=req.author or "workbench",
        )
        if self.publish is not None:
            self.publish(keys.key(keys.ANCHORS, site=self.site, photo=photo_id), msg)
        out["published"] = self.publish is not None
        return out

    # -- selection --------------------------------------------------------------------------------------------

    def select(self, photo_id: str, body: dict[str, Any]) -> dict[str, Any]:
        """Selection on a registered photo. ``mode``: ``click`` (u, v), ``grow`` (element_ids, by), ``region``
        (polygon or brush + radius_px, photo pixels), ``occlusion`` (u, v, kind: the mask region there)."""
        mode = body.get("mode")
        g = self.geometry()
        region_polys: list[list[list[float]]] = []
        try:
            if mode == "click":
                pick = self.pick_photo(photo_id, float(body["u"]), float(body["v"]))
                ids = [pick["global_id"]] if pick["global_id"] else []
            elif mode == "grow":
                ids = g.grow([str(x) for x in body["element_ids"]], str(body["by"]))
            elif mode == "region":
                img, _ = self._render(photo_id)
                poly = points_px(body.get("polygon") or [], "polygon")
                brush = points_px(body.get("brush") or [], "brush")
                radius = float(body.get("radius_px", 12.0))
                if not 0 < radius <= MAX_COORD_PX:
                    raise ApiError(400, f"radius_px must be a positive number of pixels, not {radius}")
                scale = img.scale
                mask = regions.region_mask(
                    img.ids.shape,
                    polygon=img.from_photo_px(np.asarray(poly, np.float64)).tolist() if poly else None,
                    brush=img.from_photo_px(np.asarray(brush, np.float64)).tolist() if brush else None,
                    radius_px=radius * scale,
                )
                if not mask.any():
                    raise ApiError(400, "region is empty: give a polygon of >= 3 points or a brush stroke")
                ids = [g.elements[i].global_id for i in regions.elements_in_region(img.ids, mask)]
                region_polys = self._outline(img, mask)
            elif mode == "occlusion":
                kind = str(body.get("kind", "combined"))
                p = self.photo(photo_id)
                png = self.mask_png(photo_id, kind)
                try:
                    m = imagecodec.decode_mask(png)
                except ValueError as e:
                    raise ApiError(422, f"the {kind} mask of photo {photo_id} is not a decodable PNG") from e
                part = regions.component_at(m, float(body["u"]), float(body["v"]))
                if not part.any():
                    raise ApiError(404, f"no {kind} occlusion region under that pixel")
                sy, sx = (
                    p.height_px / m.shape[0] if p.height_px else 1.0,
                    p.width_px / m.shape[1] if p.width_px else 1.0,
                )
                region_polys = [
                    [[(x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5] for x, y in poly]
                    for poly in regions.mask_polygons(part)
                ]
                ids = []
            else:
                raise ApiError(400, "mode must be click, grow, region or occlusion")
        except (KeyError, TypeError, ValueError) as e:
            raise ApiError(400, f"bad selection request ({mode}): {e}") from None
        at = self.photo(photo_id).capture_time_ns
        return {
            "element_ids": ids,
            "elements": [g.element_info(x, at) for x in ids],
            "polygons": self.outline(photo_id, ids) if ids else [],
            "region_polygons": region_polys,
        }

    def outline(self, photo_id: str, element_ids: list[str]) -> list[list[list[float]]]:
        """Outlines (photo pixels) of the elements' visible parts in a registered photo."""
        g = self.geometry()
        img, _ = self._render(photo_id)
        idx = [g.index_of[x] for x in element_ids if x in g.index_of]
        mask = regions.element_mask(img.ids, idx)
        occ = self._occluded(photo_id, img.ids.shape)
        if occ is not None:
            mask &= ~occ
        return self._outline(img, mask)

    # -- annotations ------------------------------------------------------------------------------------------

    def create_annotation(self, body: dict[str, Any], annotation_id: str | None = None) -> dict[str, Any]:
        """New annotation (or, with ``annotation_id``, a new revision of it): ``element_ids`` and / or ``polygon_px``
        on ``photo_id``, ``status``, ``rgba``, ``text``, ``author``."""
        now = time.time_ns()
        prev = None
        if annotation_id is not None:
            revs = self.state.annotations.get(annotation_id)
            if not revs or revs[-1].deleted:
                raise ApiError(404, f"unknown annotation {annotation_id!r}")
            prev = revs[-1]
            body = {**msgspec.to_builtins(prev), **body}
        if not isinstance(body, dict):
            raise ApiError(400, "body must be a JSON object")
        photo_id = photo_id_of(body.get("photo_id"))
        p = self.photo(photo_id) if photo_id else None
        ids = body.get("element_ids") or ()
        if not isinstance(ids, (list, tuple)) or not all(isinstance(x, str) for x in ids):
            raise ApiError(400, "element_ids must be a list of strings")
        element_ids = tuple(ids)
        polygon = tuple(points_px(body.get("polygon_px") or (), "polygon_px"))
        if not element_ids and len(polygon) < 3:
            raise ApiError(400, "an annotation needs element_ids or a polygon_px of >= 3 points")
        if polygon and p is None:
            raise ApiError(400, "a polygon_px needs the photo_id it was drawn on")
        status = str(body.get("status", ""))
        kind = str(body.get("kind") or ("status" if status else "note"))
        world: tuple[tuple[float, float, float], ...] = ()
        if polygon and p is not None and p.photo_id in self.state.registrations:
            world = self._lift_vertices(p.photo_id, polygon)
        try:
            rgba = tuple(int(c) for c in body.get("rgba") or (0, 0, 0, 0))
            if not all(0 <= c <= 255 for c in rgba):
                raise ValueError(f"rgba {rgba} is not 0-255")
            ann = Annotation(
                site=self.site,
                annotation_id=annotation_id or uuid.uuid4().hex[:12],
                kind=kind,  # type: ignore[arg-type]
                photo_id=photo_id,
                camera_id=p.camera_id if p is not None else None,
                polygon_px=polygon,
                element_ids=element_ids,
                status=status,  # type: ignore[arg-type]
                text=str(body.get("text", "")),
                author=str(body.get("author", "")),
                created_ns=prev.created_ns if prev is not None else now,
                rgba=rgba,  # type: ignore[arg-type]
                polygon_in_world_m=world,
                revision=prev.revision + 1 if prev is not None else 0,
                modified_ns=now,
            )
            ann = msgspec.convert(msgspec.to_builtins(ann), Annotation)  # validates literals and tuple lengths
        except (msgspec.ValidationError, TypeError, ValueError) as e:
            raise ApiError(400, f"bad annotation: {e}") from None
        self._emit(ann)
        return self.annotation_json(ann)

    # -- progress ---------------------------------------------------------------------------------------------

    def _elements_by_id(self) -> dict[str, BimElement]:
        """The model's elements (after its updates) by GlobalId; empty before a model arrives."""
        return {e.global_id: e for e in self.model().elements} if self.state.model is not None else {}

    def progress(self, photo_id: str) -> dict[str, Any]:
        """What the progress node read in a photo (:func:`nodes.workbench.progress.detections`)."""
        with self._lock:
            self.photo(photo_id)
            try:
                return progress_view.detections(self.state, photo_id, self._elements_by_id())
            except LookupError as e:
                raise ApiError(404, str(e)) from None

    def review_queue(self, limit: int = 50) -> list[dict[str, Any]]:
        """Readings that disagree with the plan, the farthest off first
        (:func:`nodes.workbench.progress.review_queue`)."""
        with self._lock:
            return progress_view.review_queue(self.state, self._elements_by_id(), limit)

    def review_detection(self, photo_id: str, body: dict[str, Any]) -> dict[str, Any]:
        """Confirm or correct what the progress node read of an element in a photo: a ``status`` annotation
        (:func:`nodes.workbench.progress.review_annotation`), published like any other."""
        with self._lock:
            self.photo(photo_id)
            try:
                ann = progress_view.review_annotation(self.state, photo_id, body)
            except LookupError as e:
                raise ApiError(404, str(e)) from None
            except ValueError as e:
                raise ApiError(400, str(e)) from None
        return self.create_annotation(ann)

    def delete_annotation(self, annotation_id: str) -> dict[str, Any]:
        revs = self.state.annotations.get(annotation_id)
        if not revs or revs[-1].deleted:
            raise ApiError(404, f"unknown annotation {annotation_id!r}")
        ann = msgspec.structs.replace(
            revs[-1], revision=revs[-1].revision + 1, deleted=True, modified_ns=time.time_ns()
        )
        self._emit(ann)
        return self.annotation_json(ann)

    def _emit(self, ann: Annotation) -> None:
        self.apply(ann)
        if self.publish is not None:
            self.publish(keys.key(keys.ANNOTATION, site=self.site, annotation=ann.annotation_id), ann)

    def history(self, annotation_id: str) -> list[dict[str, Any]]:
        revs = self.state.annotations.get(annotation_id)
        if not revs:
            raise ApiError(404, f"unknown annotation {annotation_id!r}")
        return [self.annotation_json(a) for a in revs]

    def annotation_json(self, ann: Annotation) -> dict[str, Any]:
        out = msgspec.to_builtins(ann)
        out.pop("type", None)
        if tuple(ann.rgba) == (0, 0, 0, 0):
            out["rgba"] = list(STATUS_RGBA.get(ann.status, STATUS_RGBA[""]))
        return out

    def annotations(self, photo_id: str | None = None) -> list[dict[str, Any]]:
        """Current annotations; for a photo each with ``polygons`` (photo pixels) where it shows there."""
        with self._lock:
            current = self.state.current_annotations()
        out = []
        for ann in current:
            entry = self.annotation_json(ann)
            if photo_id is not None:
                entry["polygons"] = self._transfer(ann, photo_id)
                if not entry["polygons"]:
                    continue
            out.append(entry)
        return out

    def _transfer(self, ann: Annotation, photo_id: str) -> list[list[list[float]]]:
        """Where an annotation shows on a photo: its elements' visible outlines (element-based), or its region
        carried through the model surface (region-based); the drawn polygon on its own photo."""
        registered = photo_id in self.state.registrations and self.state.status(photo_id) in ("anchor", "auto")
        if ann.element_ids:
            return self.outline(photo_id, list(ann.element_ids)) if registered else []
        if ann.photo_id == photo_id:
            return [[list(pt) for pt in ann.polygon_px]]
        if not registered or ann.photo_id is None or self.state.status(ann.photo_id) not in ("anchor", "auto"):
            return []
        if ann.kind == "occluder" and ann.camera_id is not None:
            p = self.photo(photo_id)
            return [[list(pt) for pt in ann.polygon_px]] if p.camera_id == ann.camera_id else []
        key = (ann.annotation_id, ann.revision)
        if key not in self._lifted:
            src, src_cam = self._render(ann.photo_id)
            mask = regions.region_mask(src.ids.shape, polygon=src.from_photo_px(np.asarray(ann.polygon_px)).tolist())
            self._lifted[key] = regions.lift_region(mask, src.depth_m, src_cam)
        img, tcam = self._render(photo_id)
        mask = regions.project_region(self._lifted[key], tcam, img.depth_m)
        occ = self._occluded(photo_id, img.ids.shape)
        if occ is not None:
            mask &= ~occ
        return self._outline(img, mask)

    def _lift_vertices(self, photo_id: str, polygon: tuple[tuple[float, float], ...]) -> tuple:
        g = self.geometry()
        try:
            camera = self.camera(photo_id)
        except ApiError:
            return ()
        vis = g.standing(self.photo(photo_id).capture_time_ns)
        out = []
        for u, v in polygon:
            pk = g.pick(camera, u, v, vis, snap_px=0)
            if pk.point_in_world_m is None:
                return ()
            out.append(pk.point_in_world_m)
        return tuple(out)

    # -- time -------------------------------------------------------------------------------------------------

    def peek(self, photo_id: str, at_ns: int, polygon: list[list[float]] | None) -> tuple[bytes, dict[str, Any]]:
        """RGBA PNG at photo size: inside ``polygon`` (photo pixels; None = whole photo), the photo's viewpoint
        group neighbour closest before ``at_ns`` warped by its homography (``at_ns`` before the capture), or the
        model as it will stand at ``at_ns`` (after)."""
        p = self.photo(photo_id)
        w, h = p.width_px, p.height_px
        if w <= 0 or h <= 0:
            h, w = decode_rgb(p.data).shape[:2]
        region = regions.region_mask((h, w), polygon=points_px(polygon, "polygon")) if polygon else None
        if polygon and (region is None or not region.any()):
            raise ApiError(400, "peek region is empty: give a polygon of >= 3 points inside the photo")
        if at_ns < p.capture_time_ns:
            vg = self.state.viewpoints.get(photo_id)
            cands = [
                n
                for n in (vg.neighbours if vg is not None else ())
                if n.photo_id in self.state.photos and self.state.photos[n.photo_id].capture_time_ns <= at_ns
            ]
            if not cands:
                raise ApiError(404, f"no photo from this viewpoint taken before the chosen time (photo {photo_id})")
            best = max(cands, key=lambda n: self.state.photos[n.photo_id].capture_time_ns)
            src = self.state.photos[best.photo_id]
            H = np.asarray(best.this_from_neighbour, np.float64).reshape(3, 3)
            rgba = regions.warp_region(decode_rgb(src.data), H, (h, w), region)
            return imagecodec.encode_png_rgb(rgba), {
                "direction": "backward",
                "source_photo_id": src.photo_id,
                "at_ns": at_ns,
            }
        img, _ = self._render(photo_id, at_ns)
        now, _ = self._render(photo_id)
        layer = np.zeros((*img.ids.shape, 4), np.uint8)
        new = (img.ids > 0) & (img.ids != now.ids)
        layer[img.ids > 0] = STANDING_RGBA
        layer[new] = FUTURE_RGBA
        edges = np.zeros(img.ids.shape, bool)
        edges[:, 1:] |= img.ids[:, 1:] != img.ids[:, :-1]
        edges[1:, :] |= img.ids[1:, :] != img.ids[:-1, :]
        layer[edges & (img.ids > 0)] = (40, 40, 40, 255)
        layer = np.asarray(cv2.resize(layer, (w, h), interpolation=cv2.INTER_NEAREST), np.uint8)
        if region is not None:
            layer[~region, 3] = 0
        return imagecodec.encode_png_rgb(layer), {"direction": "forward", "source_photo_id": None, "at_ns": at_ns}

    def preview(self, photo_id: str, element_ids: list[str]) -> bytes:
        """The photo with the render node's photoreal composite inside the selected elements' visible parts."""
        ov = self.state.overlays.get((photo_id, "photoreal"))
        if ov is None:
            raise ApiError(
                409,
                f"no photoreal overlay for photo {photo_id} yet (the render node renders it when its modes "
                "include photoreal)",
            )
        g = self.geometry()
        photo = decode_rgb(self.photo(photo_id).data)
        real = decode_rgb(ov.image_png)
        real = np.asarray(cv2.resize(real, (photo.shape[1], photo.shape[0]), interpolation=cv2.INTER_AREA), np.uint8)
        img, _ = self._render(photo_id)
        mask = regions.element_mask(img.ids, [g.index_of[x] for x in element_ids if x in g.index_of])
        mask = cv2.resize(mask.astype(np.uint8), (photo.shape[1], photo.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
        out = photo.copy()
        out[mask] = real[mask]
        return imagecodec.encode_png_rgb(out)

    def registration_of(self, photo_id: str) -> Registration | None:
        return self.state.registrations.get(photo_id)

    def close(self) -> None:
        if self._renderer is not None:
            self._gl.submit(self._renderer.close).result()
            self._renderer = None
        self._gl.shutdown(wait=True)
