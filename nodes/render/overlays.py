"""Overlay modes: the BIM drawn over a photo from element-ID / shade rasters (pure core).

Every mode turns a :class:`raster.RasterResult` into an RGBA layer (H, W, 4) uint8 at photo size
plus a legend; :func:`composite` blends the layer over the photo (RGB uint8). Modes:

* ``state4d``  elements that should stand at ``at_ns`` per the plan, tinted by IFC class;
* ``progress`` elements coloured by the deviation the progress node detected from the photos
  (``ProgressUpdate``; paper Sec. 4.2 colours: ahead green, on time translucent white, behind red, due but not
  built a red outline, needs review dark blue); without any such evidence for the site, as ``progress_planned``;
* ``progress_planned`` elements due or built by ``at_ns`` coloured by schedule status (actual dates and status
  annotations of the schedule, not the photos);
* ``xray``     selected elements hidden behind other elements, the ground or occluders, ghosted
  with outlines;
* ``future``   elements scheduled after ``at_ns`` ghosted over what stands;
* ``edges``    crisp outlines of standing elements.

Element "standing" (built) at t: its construction finished (actual finish when the schedule has
actuals for it, else planned) and it is not removed; elements no task names always stand.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.modelscene import GROUND_INDEX, BimScene
from constructaide.modelview import GLRasterizer, RasterResult
from constructaide.schedule4d import ElementWindow, element_windows, planned_state, stands, task_elements
from nodes.render.scene import filter_mask
from schemas.messages import Annotation, BimModel, ElementFilter, ElementProgress, Intrinsics, LegendEntry

MODES = ("state4d", "progress", "xray", "future", "edges", "progress_planned")

AHEAD_RGBA = (40, 200, 60, 150)
ON_TIME_RGBA = (255, 255, 255, 110)
BEHIND_RGBA = (230, 40, 40, 160)
REVIEW_RGBA = (20, 40, 150, 190)
MISSING_RGBA = (230, 40, 40, 255)
XRAY_RGBA = (0, 220, 255, 110)
FUTURE_RGBA = (255, 170, 0, 120)
EDGE_RGBA = (255, 230, 40, 255)

_JUDGED = {"ahead": 0, "on_time": 1, "behind": 2}


@dataclass
class ScheduleView:
    """Per-element schedule windows of a model, indexed like a :class:`BimScene` (row 0 unused; replace the list
    rather than editing it in place: distinct windows are cached by its length)."""

    windows: list[ElementWindow | None]
    task_elements: dict[str, tuple[str, ...]]
    annotations: dict[str, Annotation] = field(default_factory=dict)
    evidence: dict[str, ElementProgress] = field(default_factory=dict)
    """Latest detected progress per element GlobalId (from ``ProgressUpdate``)."""
    _distinct: tuple[list[ElementWindow | None], NDArray[np.int64], int] | None = field(
        default=None, init=False, repr=False
    )

    @classmethod
    def from_model(cls, model: BimModel, scene: BimScene) -> ScheduleView:
        w = element_windows(model.tasks)
        return cls(
            windows=[None, *(w.get(g) for g in scene.global_ids)],
            task_elements=task_elements(model.tasks),  # a summary task selects its sub-tasks' elements
        )

    def built(self, at_ns: int, basis: str = "actual") -> NDArray[np.bool_]:
        """(n + 1,) bool: element stands at ``at_ns``. ``basis``: "planned" or "actual" (actual when known)."""
        b: Literal["actual", "planned"] = "actual" if basis == "actual" else "planned"
        return self._per_window(lambda w: stands(w, at_ns, b))

    def future(self, at_ns: int) -> NDArray[np.bool_]:
        """(n + 1,) bool: element is planned to be built after ``at_ns`` (not yet complete per plan)."""
        return self._per_window(lambda w: planned_state(w, at_ns) in ("not_started", "under_construction"))

    def _per_window(self, fn: Callable[[ElementWindow | None], bool]) -> NDArray[np.bool_]:
        """(n + 1,) bool of ``fn`` per element (row 0 False), evaluated once per distinct window (elements of one
        task share theirs: a few hundred calls for a model of tens of thousands of elements)."""
        if self._distinct is None or self._distinct[2] != len(self.windows):
            index: dict[ElementWindow | None, int] = {}
            rows = np.fromiter((index.setdefault(w, len(index)) for w in self.windows[1:]), np.int64)
            self._distinct = (list(index), rows, len(self.windows))
        distinct, rows, _ = self._distinct
        out = np.zeros(len(self.windows), bool)
        out[1:] = np.array([fn(w) for w in distinct], bool)[rows] if len(rows) else False
        return out

    def progress(self, at_ns: int, global_ids: list[str], tolerance_ns: int = 86_400 * 10**9) -> NDArray[np.int8]:
        """(n + 1,) int8 status: -1 not shown, 0 ahead, 1 on time, 2 behind, 3 needs review.

        Due = planned finish <= t. Ahead: actually finished before the planned finish (by more than
        ``tolerance_ns``), or finished by t though not yet due. On time: finished within tolerance, or
        due with no actual dates known for it (the plan is all we have). Behind: due but not actually
        finished by t, or finished later than planned. Status annotations override: ``ahead`` / ``on_time`` /
        ``behind`` -> 0 / 1 / 2, ``needs_review`` -> 3, ``not_built`` on a due element -> 2, ``built`` on an
        element not due -> 0.
        """
        out = np.full(len(self.windows), -1, np.int8)
        for i, w in enumerate(self.windows[1:], start=1):
            if w is None or w.build_finish_ns is None:
                continue
            due = w.build_finish_ns <= at_ns
            af = w.actual_build_finish_ns
            done = af is not None and af <= at_ns
            if not w.has_actuals:
                out[i] = 1 if due else -1
            elif done:
                assert af is not None
                if af < w.build_finish_ns - tolerance_ns:
                    out[i] = 0
                elif af <= w.build_finish_ns + tolerance_ns:
                    out[i] = 1
                else:
                    out[i] = 2
            elif due:
                out[i] = 2
            ann = self.annotations.get(global_ids[i - 1])
            if ann is not None and ann.created_ns <= at_ns:
                if ann.status in _JUDGED:  # the user's own schedule judgement (workbench)
                    out[i] = _JUDGED[ann.status]
                elif ann.status == "needs_review":
                    out[i] = 3
                elif ann.status == "not_built" and due:
                    out[i] = 2
                elif ann.status == "built" and not due:
                    out[i] = 0
        return out

    def detected(self, at_ns: int, global_ids: list[str]) -> NDArray[np.int8]:
        """(n + 1,) int8 status from detected progress: -1 not shown, 0 ahead, 1 on time, 2 behind (built late),
        3 needs review (annotation), 4 due by ``at_ns`` but detected absent then. An element counts as standing at
        ``at_ns`` once it was first seen standing (``first_present_ns``)."""
        out = np.full(len(self.windows), -1, np.int8)
        for i, gid in enumerate(global_ids, start=1):
            ep = self.evidence.get(gid)
            if ep is None:
                continue
            if ep.state == "built" and ep.first_present_ns is not None and ep.first_present_ns <= at_ns:
                out[i] = {"ahead": 0, "behind": 2}.get(ep.deviation, 1)
            elif ep.planned_finish_ns is not None and ep.planned_finish_ns <= at_ns:
                absent = ep.state == "not_built" or (ep.last_absent_ns is not None and ep.last_absent_ns >= at_ns)
                out[i] = 4 if absent else -1
            ann = self.annotations.get(gid)
            if ann is not None and ann.created_ns <= at_ns and ann.status == "needs_review":
                out[i] = 3
        return out

    def apply_annotation(self, ann: Annotation) -> None:
        """Remember the latest status annotation per element (kind ``status`` only); a later revision of an
        annotation (an edit, or ``deleted``) replaces it."""
        if ann.kind != "status":
            return
        for gid, old in list(self.annotations.items()):
            if old.annotation_id == ann.annotation_id and old.revision <= ann.revision:
                del self.annotations[gid]
        if ann.deleted or not ann.status:
            return
        for gid in ann.element_ids:
            prev = self.annotations.get(gid)
            if prev is None or prev.created_ns <= ann.created_ns:
                self.annotations[gid] = ann


def class_rgb(ifc_class: str) -> tuple[int, int, int]:
    """Stable, saturated colour per IFC class name."""
    fixed = {
        "IfcWall": (230, 120, 60),
        "IfcWallStandardCase": (230, 120, 60),
        "IfcSlab": (80, 160, 230),
        "IfcColumn": (200, 80, 200),
        "IfcBeam": (240, 200, 40),
        "IfcWindow": (60, 220, 220),
        "IfcDoor": (150, 100, 60),
        "IfcRoof": (200, 60, 60),
        "IfcFooting": (130, 130, 130),
        "IfcStair": (120, 200, 80),
    }
    if ifc_class in fixed:
        return fixed[ifc_class]
    h = int(hashlib.sha1(ifc_class.encode()).hexdigest()[:4], 16) % 180
    hsv = np.array([[[h, 180, 230]]], np.uint8)
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


def id_edges(
    ids: NDArray[np.uint32], shade: NDArray[np.float32] | None = None, thickness_px: int = 1
) -> NDArray[np.bool_]:
    """(H, W) bool outlines: element-ID changes (and face-orientation creases when ``shade`` given)."""
    e = np.zeros(ids.shape, bool)
    dx = ids[:, 1:] != ids[:, :-1]
    dy = ids[1:, :] != ids[:-1, :]
    if shade is not None:
        dx |= np.abs(shade[:, 1:] - shade[:, :-1]) > 0.04
        dy |= np.abs(shade[1:, :] - shade[:-1, :]) > 0.04
    e[:, 1:] |= dx
    e[1:, :] |= dy
    if thickness_px > 1:
        e = cv2.dilate(e.astype(np.uint8), np.ones((thickness_px, thickness_px), np.uint8)) > 0
    return e


def _fill(layer: NDArray[np.uint8], mask: NDArray[np.bool_], rgba: tuple[int, ...], shade=None) -> None:
    if not mask.any():
        return
    rgb = np.asarray(rgba[:3], np.float32)
    if shade is not None:
        k = (0.55 + 0.45 * shade[mask])[:, None]
        layer[mask, :3] = np.clip(rgb[None, :] * k, 0, 255).astype(np.uint8)
    else:
        layer[mask, :3] = rgb.astype(np.uint8)
    layer[mask, 3] = rgba[3]


def _fill_lut(layer, mask, rgb_per_pixel, alpha: int, shade=None) -> None:
    """Fill masked pixels with per-pixel RGB (M, 3) uint8, optionally shaded, constant alpha."""
    if not mask.any():
        return
    if shade is not None:
        k = (0.55 + 0.45 * shade[mask])[:, None]
        layer[mask, :3] = np.clip(rgb_per_pixel.astype(np.float32) * k, 0, 255).astype(np.uint8)
    else:
        layer[mask, :3] = rgb_per_pixel
    layer[mask, 3] = alpha


def composite(photo_rgb: NDArray[np.uint8], layer_rgba: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Alpha-blend an RGBA layer over an RGB photo of the same size."""
    if photo_rgb.shape[:2] != layer_rgba.shape[:2]:
        raise ValueError(f"photo {photo_rgb.shape[:2]} and overlay {layer_rgba.shape[:2]} differ in size")
    a = layer_rgba[..., 3]
    a3 = cv2.merge([a, a, a])
    # Integer blend: (photo * (255 - a) + rgb * a) / 255, rounded.
    x = cv2.multiply(np.ascontiguousarray(photo_rgb), cv2.bitwise_not(a3), dtype=cv2.CV_16U)
    y = cv2.multiply(np.ascontiguousarray(layer_rgba[..., :3]), a3, dtype=cv2.CV_16U)
    return np.asarray(cv2.convertScaleAbs(cv2.add(x, y), alpha=1.0 / 255.0), np.uint8)


@dataclass(frozen=True)
class OverlayResult:
    layer_rgba: NDArray[np.uint8]
    legend: tuple[LegendEntry, ...]
    raster: RasterResult


def render_overlay(
    rasterizer: GLRasterizer,
    scene: BimScene,
    schedule: ScheduleView,
    intr: Intrinsics,
    world_from_camera: NDArray[np.float64],
    mode: str,
    at_ns: int,
    flt: ElementFilter | None = None,
    occlusion: NDArray[np.bool_] | None = None,
    ground_z_m: float | None = 0.0,
) -> OverlayResult:
    """RGBA overlay layer (H, W, 4) of one mode for one camera at ``at_ns``.

    ``occlusion`` (H, W) bool marks photo pixels where something stands in front of the model:
    nothing is drawn there except in ``xray``, which ghosts what is hidden. ``ground_z_m`` is the
    terrain height used as an occluder in ``xray`` (``None``: no ground).
    """
    if mode not in MODES:
        raise ValueError(f"unknown overlay mode {mode!r}; choose one of {', '.join(MODES)}")
    sel = filter_mask(scene, flt or ElementFilter(), schedule.task_elements)
    h, w = intr.height_px, intr.width_px
    if occlusion is not None and occlusion.shape != (h, w):
        raise ValueError(f"occlusion mask {occlusion.shape} does not match the photo ({h}, {w})")
    free = np.ones((h, w), bool) if occlusion is None else ~occlusion
    layer = np.zeros((h, w, 4), np.uint8)
    legend: list[LegendEntry] = []

    if mode == "state4d":
        built = schedule.built(at_ns, basis="planned")
        ras = rasterizer.render(scene, intr, world_from_camera, built)
        show = sel[ras.ids.clip(0, scene.num_elements)] & (ras.ids <= scene.num_elements) & free
        classes = sorted({e.ifc_class for e in scene.elements})
        lut = np.zeros((scene.num_elements + 2, 3), np.uint8)
        rgb = {c: class_rgb(c) for c in classes}
        if scene.elements:
            lut[1 : scene.num_elements + 1] = np.array([rgb[e.ifc_class] for e in scene.elements], np.uint8)
        ids_c = np.minimum(ras.ids, scene.num_elements + 1)
        _fill_lut(layer, show, lut[ids_c[show]], 120, ras.shade)
        present = {scene.elements[i - 1].ifc_class for i in np.unique(ids_c[show]) if 0 < i <= scene.num_elements}
        legend = [LegendEntry(label=c, rgba=(*class_rgb(c), 120)) for c in classes if c in present]
        edges = id_edges(np.where(show, ras.ids, 0).astype(np.uint32)) & show
        _fill(layer, edges, (*EDGE_RGBA[:3], 200))
    elif mode in ("progress", "progress_planned"):
        from_photos = mode == "progress" and bool(schedule.evidence)
        status = (
            schedule.detected(at_ns, scene.global_ids) if from_photos else schedule.progress(at_ns, scene.global_ids)
        )
        status[~sel] = -1
        visible = status >= 0
        if not from_photos:
            visible |= schedule.built(at_ns, basis="actual")
        ras = rasterizer.render(scene, intr, world_from_camera, visible)
        st = np.full(ras.ids.shape, -1, np.int8)
        inside = (ras.ids > 0) & (ras.ids <= scene.num_elements) & free
        st[inside] = status[ras.ids[inside]]
        for code, label, rgba in (
            (0, "ahead of schedule", AHEAD_RGBA),
            (1, "on time", ON_TIME_RGBA),
            (2, "behind schedule", BEHIND_RGBA),
            (3, "deviation / needs review", REVIEW_RGBA),
        ):
            _fill(layer, st == code, rgba, ras.shade)
            legend.append(LegendEntry(label=label, rgba=rgba))
        if from_photos:
            missing = st == 4
            _fill(layer, missing, (*BEHIND_RGBA[:3], 40))
            _fill(
                layer, id_edges(np.where(missing, ras.ids, 0).astype(np.uint32), thickness_px=2) & missing, MISSING_RGBA
            )
            legend.append(LegendEntry(label="due, not built (detected)", rgba=MISSING_RGBA))
            legend = [LegendEntry(label=f"{e.label} (detected)", rgba=e.rgba) for e in legend[:3]] + legend[3:]
        edges = id_edges(np.where(st >= 0, ras.ids, 0).astype(np.uint32)) & (st >= 0) & (st != 4)
        layer[edges, 3] = np.maximum(layer[edges, 3], 220)
    elif mode == "xray":
        built = schedule.built(at_ns, basis="actual")
        ras = rasterizer.render(scene, intr, world_from_camera, built, ground_z_m=ground_z_m)
        only = rasterizer.render(scene, intr, world_from_camera, built & sel)
        target = only.ids > 0
        hidden = target & ((ras.ids != only.ids) | ~free)
        visible_sel = target & ~hidden
        _fill(layer, hidden, XRAY_RGBA, only.shade)
        outline = id_edges(only.ids, only.shade) & target
        _fill(layer, outline & hidden, (*XRAY_RGBA[:3], 255))
        _fill(layer, outline & visible_sel, (255, 255, 255, 110))
        legend = [
            LegendEntry(label="hidden (behind elements, ground or occluders)", rgba=XRAY_RGBA),
            LegendEntry(label="visible outline", rgba=(255, 255, 255, 110)),
        ]
        ras = only
    elif mode == "future":
        built = schedule.built(at_ns, basis="actual")
        fut = schedule.future(at_ns) & ~built & sel
        ras = rasterizer.render(scene, intr, world_from_camera, built | fut)
        m = fut[ras.ids.clip(0, scene.num_elements)] & (ras.ids <= scene.num_elements) & (ras.ids > 0) & free
        _fill(layer, m, FUTURE_RGBA, ras.shade)
        edges = id_edges(np.where(m, ras.ids, 0).astype(np.uint32), ras.shade) & m
        _fill(layer, edges, (*FUTURE_RGBA[:3], 255))
        legend = [LegendEntry(label="scheduled after this photo", rgba=FUTURE_RGBA)]
    else:  # edges
        built = schedule.built(at_ns, basis="actual")
        ras = rasterizer.render(scene, intr, world_from_camera, built & sel)
        target = (ras.ids > 0) & (ras.ids != GROUND_INDEX)
        # Outlines drawn on the element side only (and never on occluded pixels), 2 px wide.
        e = id_edges(ras.ids, ras.shade, thickness_px=2) & target & free
        _fill(layer, e, EDGE_RGBA)
        legend = [LegendEntry(label="element outlines", rgba=EDGE_RGBA)]
    return OverlayResult(layer_rgba=layer, legend=tuple(legend), raster=ras)
