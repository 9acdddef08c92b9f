"""Progress engine: model + photos + registrations + masks + sparse points -> evidence and fused progress.

Pure core used by the node (streaming) and by ``constructaide progress --recording`` (batch): no bus, no rerun,
no MCAP. Feed it messages with the ``add_*`` / ``set_*`` methods, then :meth:`ProgressEngine.process` a photo
once it is registered (and, preferably, has its combined occlusion mask). Processing a photo renders the model's
layers at its pose (believed-built elements and the schedule window's candidates, see
:mod:`nodes.progress.modelview`), computes its cues (:mod:`nodes.progress.evidence`) against the camera's
reference plate (:mod:`nodes.progress.plates`), adds them to the tracks of the elements it sees and recomputes
only those tracks (:mod:`nodes.progress.fusion`). Call from one thread (the renderer's EGL context).
"""

from __future__ import annotations

import datetime as dt
import time
from dataclasses import dataclass, field, replace
from zoneinfo import ZoneInfo

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.bimgeom import glb_to_meshes, load_bim_model_glb
from constructaide.camera import invert_rigid, pose_from_tuple, registered_camera, scaled_intrinsics
from constructaide.imagecodec import decode_rgb, mask_of_message
from constructaide.schedule4d import ElementWindow, element_windows, task_ancestors, task_elements
from constructaide.sparsecloud import SparseArrays, decode_sparse_cloud
from nodes.progress.evidence import ElementCue, MaterialModel, PhotoCache, photo_evidence, to_lab
from nodes.progress.fusion import (
    NS_PER_DAY,
    ElementEstimate,
    ElementTrack,
    Observation,
    Posterior,
    coupled,
    estimate,
    fit_slip_days,
    working_midpoint,
)
from nodes.progress.modelview import LayerRenderer, Mesh, below_terrain
from nodes.progress.occlusion import fixed_camera_hiding, union_of
from nodes.progress.params import EngineParams
from nodes.progress.passes import behind_candidates, covering, settle_deferred
from nodes.progress.plates import ReferencePlate, same_segment
from nodes.progress.registrations import ignores_polish
from nodes.progress.support import dependants_of, mesh_boxes, support_graph
from schemas.messages import (
    SPARSE_POINT_FROM_MODEL,
    SPARSE_POINT_VERIFIED,
    Annotation,
    BimModel,
    BimUpdate,
    ElementEvidence,
    ElementProgress,
    Intrinsics,
    OcclusionMask,
    Photo,
    PhotoEvidence,
    ProgressUpdate,
    Registration,
    ScheduleTask,
    SparseCloud,
    StoreyProgress,
    TaskProgress,
)

ANNOTATION_LLR = 8.0  # a person's status annotation outweighs any image cue


@dataclass
class _Frame:
    """A processed fixed-camera frame kept for the camera's reference plate."""

    photo_id: str
    time_ns: int
    intr: Intrinsics
    world_from_camera: NDArray[np.float64]
    lab: NDArray[np.float32]
    keep: NDArray[np.bool_]


@dataclass
class PhotoRecord:
    """What one processed photo showed: per element index (status, visible px, occluded fraction)."""

    photo_id: str
    camera_id: str | None
    capture_time_ns: int
    filename: str
    cues: dict[int, tuple[str, int, float]]
    processing_ms: float
    behind: dict[tuple[int, int], tuple[int, int]] = field(default_factory=dict)
    """(candidate index, believed-built element index behind it) -> (pixels, unoccluded pixels) where the
    candidate hid that element in the last evidence pass (see :meth:`ProgressEngine.photo_cues`)."""


class ProgressEngine:
    """Stateful progress estimator of one site (see the module docstring)."""

    def __init__(self, params: EngineParams | None = None, renderer: LayerRenderer | None = None) -> None:
        self.params = params or EngineParams()
        self.renderer = renderer
        self.model: BimModel | None = None
        self.meshes: dict[str, Mesh] = {}
        self.global_ids: list[str] = []
        self.index_of: dict[str, int] = {}
        self.material_of: list[str] = [""]
        self.storey_of: dict[str, str] = {}
        self.windows: dict[str, ElementWindow] = {}
        self.tasks: dict[str, ScheduleTask] = {}
        self.element_tasks: dict[str, tuple[str, ...]] = {}
        self.task_elements: dict[str, tuple[str, ...]] = {}
        self.task_ancestors: dict[str, tuple[str, ...]] = {}
        self.tracks: dict[str, ElementTrack] = {}
        self.posteriors: dict[str, Posterior] = {}
        """Posterior per element with its supports' and dependants' beliefs (what the engine uses)."""
        self._own: dict[str, Posterior] = {}
        """Posterior per element from its own evidence and schedule only."""
        self.supports: dict[str, tuple[str, ...]] = {}
        self.dependants: dict[str, tuple[str, ...]] = {}
        self.photos: dict[str, Photo] = {}
        self.registrations: dict[str, Registration] = {}
        self.masks: dict[str, dict[str, OcclusionMask]] = {}
        self.sparse: SparseArrays | None = None
        self.frames: dict[str, list[_Frame]] = {}
        self._plates: dict[str, tuple[tuple[str, ...], ReferencePlate]] = {}
        self.records: dict[str, PhotoRecord] = {}
        self.materials = MaterialModel()
        self.as_of_ns = 0
        self.tz = "UTC"
        self.annotations: list[Annotation] = []
        self._estimates: dict[tuple[str, int], ElementEstimate] | None = None
        """Estimates memoised while one update message is built (the belief does not change meanwhile)."""
        self.fusion = self.params.fusion
        """The fusion parameters in use: ``params.fusion`` with the slip learnt from the photos (see
        :meth:`refit_slip`)."""

    # -- inputs ---------------------------------------------------------------------------------------

    def set_model(self, model: BimModel) -> None:
        """A new model revision: tracks of elements that still exist keep their evidence."""
        self.model = model
        self.meshes = load_bim_model_glb(model)
        self.tz = model.tz or self.tz
        self._rebuild()

    def apply_update(self, update: BimUpdate) -> None:
        if self.model is None or update.base_revision != self.model.revision:
            raise ValueError(f"BIM update {update.base_revision} -> {update.revision} does not apply")
        gone = set(update.removed) | {e.global_id for e in update.changed}
        elements = [e for e in self.model.elements if e.global_id not in gone] + [*update.changed, *update.added]
        for gid in update.removed:
            self.meshes.pop(gid, None)
        self.meshes.update(glb_to_meshes(update.geometry_glb))
        tasks = self.model.tasks if update.tasks is None else update.tasks
        self.model = BimModel(
            site=self.model.site,
            revision=update.revision,
            elements=tuple(elements),
            tasks=tasks,
            geometry_glb=b"",
            origin_offset_m=self.model.origin_offset_m,
            gps=self.model.gps,
            tz=self.model.tz,
            terrain_height_m=self.model.terrain_height_m,
        )
        self._rebuild()

    def _rebuild(self) -> None:
        assert self.model is not None
        els = self.model.elements
        self.global_ids = [e.global_id for e in els]
        self.index_of = {g: i for i, g in enumerate(self.global_ids, start=1)}
        self.material_of = [""] + [(e.material or e.ifc_class).lower() for e in els]
        self.storey_of = {e.global_id: e.storey for e in els}
        terrain = self.model.terrain_height_m
        # (n + 1,) whether an element's box reaches below the terrain (only their pixels can be hidden by it)
        self._reaches_below = np.array(
            [False] + [terrain is not None and e.bbox_min_m[2] < terrain - self.params.terrain_margin_m for e in els]
        )
        self.windows = element_windows(self.model.tasks)
        self.tasks = {t.task_id: t for t in self.model.tasks}
        self.task_elements = task_elements(self.model.tasks)
        self.task_ancestors = task_ancestors(self.model.tasks)
        by_el: dict[str, list[str]] = {}
        for t in self.model.tasks:
            for g in t.element_ids:
                by_el.setdefault(g, []).append(t.task_id)
        self.element_tasks = {g: tuple(v) for g, v in by_el.items()}
        starts = [t.planned_start_ns for t in self.model.tasks] or [0]
        finishes = [t.planned_finish_ns for t in self.model.tasks] or [0]
        span = (min(starts), max(finishes))
        old = self.tracks
        self.tracks = {}
        for g in self.global_ids:
            tr = ElementTrack(g, self.windows.get(g), span)
            if g in old:
                tr.observations = old[g].observations
            self.tracks[g] = tr
        self.posteriors, self._own = {}, {}
        meshes = {
            e.global_id: self.meshes[e.geometry_ref or e.global_id]
            for e in els
            if (e.geometry_ref or e.global_id) in self.meshes
        }
        coupling = self.params.support_floor is not None or self.params.dependant_floor is not None
        self.supports = support_graph(mesh_boxes(meshes), self.windows) if coupling else {}
        self.dependants = dependants_of(self.supports)
        if self.renderer is None:
            self.renderer = LayerRenderer()
        self.renderer.set_model(self.global_ids, meshes)

    def add_photo(self, photo: Photo) -> None:
        self.photos[photo.photo_id] = photo

    def add_registration(self, reg: Registration) -> bool:
        """Take a photo's registration; returns whether it changed (see :func:`ignores_polish`)."""
        if ignores_polish(self.registrations.get(reg.photo_id), reg):
            return False
        if registered_camera(reg) is None:
            return self.registrations.pop(reg.photo_id, None) is not None
        self.registrations[reg.photo_id] = reg
        return True

    def add_mask(self, mask: OcclusionMask) -> None:
        self.masks.setdefault(mask.photo_id, {})[mask.kind] = mask

    def set_sparse(self, cloud: SparseCloud) -> None:
        self.sparse = decode_sparse_cloud(cloud)

    def add_annotation(self, ann: Annotation) -> list[str]:
        """A person's status annotation (built / not built) on elements: strong evidence at the photo's time (or
        the annotation's). Returns the elements it touched."""
        if ann.kind != "status" or ann.status not in ("built", "not_built"):
            return []
        photo = self.photos.get(ann.photo_id or "") if ann.photo_id else None
        t = photo.capture_time_ns if photo is not None else ann.created_ns
        sign = 1.0 if ann.status == "built" else -1.0
        touched = []
        for gid in ann.element_ids:
            tr = self.tracks.get(gid)
            if tr is None:
                continue
            tr.add(Observation(photo_id=f"annotation:{ann.annotation_id}", time_ns=t, llr_state=sign * ANNOTATION_LLR))
            self._forget(gid)
            touched.append(gid)
        self.annotations.append(ann)
        return touched

    def ready(self, photo_id: str) -> bool:
        return self.model is not None and photo_id in self.photos and photo_id in self.registrations

    def has_mask(self, photo_id: str) -> bool:
        return any(m.status == "ok" for m in self.masks.get(photo_id, {}).values())

    # -- fusion state ---------------------------------------------------------------------------------

    def own_posterior(self, gid: str) -> Posterior:
        """An element's posterior from its own evidence and schedule."""
        post = self._own.get(gid)
        if post is None:
            post = self._own[gid] = self.tracks[gid].posterior(self.fusion)
        return post

    def posterior(self, gid: str) -> Posterior:
        """An element's posterior with what carries it and what it carries (``params.support_floor``)."""
        post = self.posteriors.get(gid)
        if post is None:
            post = self.own_posterior(gid)
            up, down = self.params.support_floor, self.params.dependant_floor
            if up is not None or down is not None:
                post = coupled(
                    post,
                    [self.own_posterior(s) for s in self.supports.get(gid, ())] if up is not None else [],
                    [self.own_posterior(d) for d in self.dependants.get(gid, ())] if down is not None else [],
                    up,
                    down,
                    self.params.support_mean,
                )
            self.posteriors[gid] = post
        return post

    def _forget(self, gid: str) -> None:
        """Drop the cached posteriors that depend on ``gid``'s evidence."""
        self._own.pop(gid, None)
        for g in (gid, *self.supports.get(gid, ()), *self.dependants.get(gid, ())):
            self.posteriors.pop(g, None)

    def estimate(self, gid: str, as_of_ns: int | None = None) -> ElementEstimate:
        t = self.as_of_ns if as_of_ns is None else as_of_ns
        if self._estimates is not None and (gid, t) in self._estimates:
            return self._estimates[(gid, t)]
        hours = self.params.work_hours
        est = estimate(
            self.tracks[gid],
            self.posterior(gid),
            t,
            self.fusion,
            midpoint=lambda lo, hi: working_midpoint(lo, hi, self.tz, hours),
        )
        if self._estimates is not None:
            self._estimates[(gid, t)] = est
        return est

    def refit_slip(self, tolerance: float = 0.1) -> bool:
        """Learn the schedule's slip scale from the elements seen appearing so far (:func:`fit_slip_days`); a change
        beyond ``tolerance`` (relative) redoes every posterior. Returns whether it changed."""
        base = self.params.fusion
        if not base.fit_slip:
            return False
        width = fit_slip_days(list(self.tracks.values()), base)
        width = base.schedule_width_days if width is None else width
        if abs(width - self.fusion.schedule_width_days) <= tolerance * self.fusion.schedule_width_days:
            return False
        self.fusion = replace(base, schedule_width_days=width)
        self.posteriors, self._own = {}, {}
        return True

    def _present(self, t_ns: int) -> NDArray[np.float64]:
        out = np.zeros(len(self.global_ids) + 1)
        for i, g in enumerate(self.global_ids, start=1):
            out[i] = self.posterior(g).present_at(t_ns)
        return out

    def _stood_at(self, indices: NDArray[np.int64], times_ns: NDArray[np.int64]) -> NDArray[np.float64]:
        """P(element ``indices[k]`` (1-based) stood at ``times_ns[k]``), each (K,)."""
        out = np.zeros(len(indices))
        for i in np.unique(indices):
            sel = indices == i
            out[sel] = self.posterior(self.global_ids[int(i) - 1]).present_curve(times_ns[sel])
        return out

    # -- processing -----------------------------------------------------------------------------------

    def _occlusion(self, photo_id: str, shape: tuple[int, int]) -> NDArray[np.bool_]:
        kinds = self.masks.get(photo_id, {})
        combined = kinds.get("combined")
        if combined is not None and combined.status == "ok":
            m = mask_of_message(combined, shape)
            return m if m is not None else np.zeros(shape, bool)
        return union_of(kinds, ("dynamic", "static", "user"), shape)

    def _points(
        self, photo_id: str, reg: Registration, scale: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None:
        cloud = self.sparse
        if cloud is None or photo_id not in cloud.photo_ids:
            return None
        k = cloud.photo_ids.index(photo_id)
        sel = cloud.obs_photo == k
        if not sel.any():
            return None
        pts = cloud.points_m.astype(np.float64)
        idx = cloud.obs_point[sel]
        px = cloud.obs_pixel_px[sel].astype(np.float64)
        if cloud.point_flags is not None:
            flags = cloud.point_flags[idx]
            w = np.where(
                (flags & SPARSE_POINT_FROM_MODEL) > 0,
                0.0,
                np.where((flags & SPARSE_POINT_VERIFIED) > 0, 1.0, self.params.unverified_point_weight),
            )
        else:
            w = np.full(len(idx), self.params.unverified_point_weight)
        cam_from_world = invert_rigid(pose_from_tuple(reg.world_from_camera))
        z = pts[idx] @ cam_from_world[2, :3] + cam_from_world[2, 3]
        keep = w > 0
        # pixel centres scale about the half-pixel offset
        return (px[keep] + 0.5) * scale - 0.5, z[keep], w[keep]

    def _plate(self, camera: str, t_ns: int, world_from_camera: NDArray[np.float64]) -> ReferencePlate | None:
        """Reference plate of a fixed camera from its frames before ``t_ns`` in the same pose segment."""
        earlier = [f for f in self.frames.get(camera, []) if f.time_ns < t_ns]
        run: list[_Frame] = []
        for f in reversed(earlier):
            if not same_segment(world_from_camera, f.world_from_camera):
                break
            run.append(f)
        if not run:
            return None
        run.reverse()
        ids = tuple(f.photo_id for f in run)
        cached = self._plates.get(camera)
        if cached is not None and ids[: len(cached[0])] == cached[0]:
            used, plate = cached
            todo = run[len(used) :]
        else:
            plate = ReferencePlate.empty(run[0].intr, run[0].world_from_camera)
            todo = run
        for f in todo:
            plate.update(f.lab, f.keep, f.time_ns, f.intr, f.world_from_camera)
        self._plates[camera] = (ids, plate)
        return plate

    def process(self, photo_id: str) -> tuple[PhotoEvidence, ProgressUpdate]:
        """Evidence of one registered photo and the progress update it causes."""
        t0 = time.perf_counter()
        if not self.ready(photo_id):
            raise ValueError(f"photo {photo_id} cannot be processed yet (model, photo and registration needed)")
        assert self.renderer is not None and self.model is not None
        photo, reg = self.photos[photo_id], self.registrations[photo_id]
        rgb = decode_rgb(photo.data, f"photo {photo_id}")
        h, w = rgb.shape[:2]
        W = min(w, max(self.params.working_width_px, round(w * self.params.working_scale)))
        H = max(1, round(h * W / w))
        small = np.asarray(cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA), np.uint8) if W != w else rgb
        assert reg.intrinsics is not None
        intr = scaled_intrinsics(reg.intrinsics, W, H)
        T = pose_from_tuple(reg.world_from_camera)
        t = photo.capture_time_ns
        lab = to_lab(small)
        occluded = self._occlusion(photo_id, (H, W))
        # drop this photo's earlier evidence (a re-run after a newer mask) before taking the belief
        for tr in self.tracks.values():
            if tr.observations.pop(photo_id, None) is not None:
                self._forget(tr.global_id)
        present = self._present(t - 1)
        built = present >= self.params.sure_probability
        built[0] = False
        horizon = t + int(self.params.lookahead_days * NS_PER_DAY)
        cand = np.zeros_like(built)
        for i, g in enumerate(self.global_ids, start=1):
            wdw = self.windows.get(g)
            start = (
                None if wdw is None else (wdw.build_start_ns if wdw.build_start_ns is not None else wdw.build_finish_ns)
            )
            cand[i] = not built[i] and (start is None or start <= horizon)
        plate = self._plate(photo.camera_id, t, T) if photo.camera_id else None
        reference = plate.warp_to(intr, T) if plate is not None else None
        points = self._points(photo_id, reg, W / w)
        ev = self.params.evidence
        # the look of each material: elements seen appearing (confirmed) and those the belief draws as built
        seen_appearing = self._confirmed(t - 1)
        confirmed = np.maximum(seen_appearing, built.astype(np.float64))
        lenient = bool(photo.camera_id) and not self.params.dynamic_hides_unseen
        static = union_of(self.masks.get(photo_id, {}), ("static", "user"), (H, W)) if lenient else occluded
        looks = self.materials.counts if lenient and self.params.dynamic_spares_material_like else None
        cache = PhotoCache(lab)
        terrain = self.model.terrain_height_m if self.params.terrain_hides else None
        bins = cache.bins() if looks is not None else None
        seen: dict[int, ElementCue] = {}
        touched: list[str] = []
        layers = None
        # candidates the belief finds unlikely are read after the likelier ones (nodes.progress.passes)
        deferred = {int(i) for i in np.nonzero(cand & (present < self.params.defer_probability))[0]}
        passes = self.params.peel_passes + 1 + int(bool(deferred))
        cand[list(deferred)] = False
        held: tuple[NDArray[np.uint32], list[ElementCue]] | None = None
        for k in range(passes):
            layers = self.renderer.render(intr, T, built, cand)
            hide = occluded
            if lenient:
                seen_ids = seen_appearing >= 0.5
                hide = fixed_camera_hiding(bins, occluded, static, layers, seen_ids, self.material_of, looks)
            if terrain is not None:
                hide = hide | below_terrain(layers, intr, T, terrain, self.params.terrain_margin_m, self._reaches_below)
            cues = photo_evidence(
                lab,
                hide,
                layers,
                self.material_of,
                ev,
                reference,
                points,
                self.materials,
                present,
                confirmed,
                self._stood_at,
                cache,
                # a later pass only adds elements the earlier ones did not read
                [i for i, c in seen.items() if c.status == "seen"],
            )
            if held is None and deferred:
                # hold this reading until the deferred candidates, drawn in front where nearer, are read
                held = (layers.ids_all, cues)
                cand[list(deferred)] = True
                continue
            if held is not None:
                mine = [c for c in cues if c.index in deferred]
                touched += self._observe(photo_id, t, [c for c in mine if c.status == "seen"], reference is not None)
                seen.update((c.index, c) for c in mine)
                gid = self.global_ids
                stands = [
                    i for i in deferred if self.posterior(gid[i - 1]).present_at(t) >= self.params.peel_probability
                ]
                cover = covering(held[0], layers.ids_all)
                cues = settle_deferred(held[1], cues, deferred, cover, set(stands).__contains__) + mine
                held = None
            new = [c for c in cues if c.index not in seen or (seen[c.index].status != "seen" and c.status == "seen")]
            for c in new:
                seen[c.index] = c
            touched += self._observe(
                photo_id, t, [c for c in new if c.status == "seen" and c.index not in deferred], reference is not None
            )
            deferred = set()
            if k == passes - 1:
                break
            # read again without what this photo now shows absent: what stands behind those shows through
            gone = [
                c.index
                for c in cues
                if c.status == "seen"
                and self.posterior(self.global_ids[c.index - 1]).present_at(t) < self.params.peel_probability
            ]
            if not gone:
                break
            built[gone] = False
            cand[gone] = False
        assert layers is not None
        cues = [seen[i] for i in sorted(seen)]
        self.as_of_ns = max(self.as_of_ns, t)
        self.refit_slip()
        self._learn_materials(cache.bins(), occluded, layers.ids_all, t)
        if photo.camera_id:
            frames = self.frames.setdefault(photo.camera_id, [])
            frames[:] = [f for f in frames if f.photo_id != photo_id]
            frames.append(_Frame(photo_id, t, intr, T, lab, ~occluded))
            frames.sort(key=lambda f: f.time_ns)
            del frames[: max(0, len(frames) - self.params.max_frames_per_camera)]
            if any(f.time_ns > t for f in frames):
                self._plates.pop(photo.camera_id, None)  # arrived out of order: later plates change
        ms = (time.perf_counter() - t0) * 1000.0
        record = PhotoRecord(
            photo_id,
            photo.camera_id,
            t,
            photo.filename,
            {c.index: (c.status, c.visible_px, c.occluded_fraction) for c in cues},
            ms,
            behind_candidates(layers, occluded),
        )
        self.records[photo_id] = record
        evidence = self.photo_evidence_message(record, cues, (W, H))
        return evidence, self.update_message(touched, photo_id)

    def photo_cues(self, record: PhotoRecord) -> dict[int, tuple[str, int, float]]:
        """What a processed photo shows, per element index (status, visible px, occluded fraction): its cues, plus
        the believed-built elements it showed only behind candidates that, with every photo since, most probably did
        not stand at its capture time (below ``peel_probability``): in view, with status ``unknown`` (their pixels
        were read as the candidate's), so their rows report the fused state. Recomputed from the current belief."""
        out = dict(record.cues)
        acc: dict[int, list[int]] = {}
        t = record.capture_time_ns
        gone: dict[int, bool] = {}
        for (f, b), (px, vis) in record.behind.items():
            if b in out:
                continue
            if f not in gone:
                gone[f] = self.posterior(self.global_ids[f - 1]).present_at(t) < self.params.peel_probability
            if gone[f]:
                a = acc.setdefault(b, [0, 0])
                a[0] += px
                a[1] += vis
        for b, (px, vis) in acc.items():
            if vis >= self.params.evidence.min_pixels:
                out[b] = ("unknown", vis, 1.0 - vis / px)
        return out

    def _observe(self, photo_id: str, t: int, cues: list[ElementCue], has_plate: bool = False) -> list[str]:
        """Adds a photo's seen cues to the tracks; ``has_plate``: a fixed camera's photo with a reference plate."""
        touched = []
        group = self._visit(photo_id, t)
        for c in cues:
            if c.status != "seen":
                continue
            gid = self.global_ids[c.index - 1]
            edge = c.llr_edge
            if self.params.repeated_no_edge_once and has_plate and not c.reference_ns:
                edge = max(edge, 0.0)
            look = c.llr_appearance + edge
            if self.params.unchanged_discount and c.reference_ns:
                ev = self.params.evidence
                ramp = float(np.clip((c.changed_fraction - ev.change_noise) / (ev.change_hit - ev.change_noise), 0, 1))
                look *= self.params.unchanged_floor + (1.0 - self.params.unchanged_floor) * ramp
            llr_state = c.llr_points + look
            if llr_state == 0.0 and c.reference_ns == 0:
                continue
            self.tracks[gid].add(
                Observation(
                    photo_id,
                    t,
                    llr_state=llr_state,
                    llr_change=c.llr_change,
                    reference_ns=c.reference_ns,
                    group=group,
                )
            )
            self._forget(gid)
            touched.append(gid)
        return touched

    def _visit(self, photo_id: str, t_ns: int) -> str:
        """Group of a photo's observations (``params.visit_looks_once``): a phone visit = its local day; "" else."""
        photo = self.photos.get(photo_id)
        if not self.params.visit_looks_once or photo is None or photo.camera_id:
            return ""
        return "visit:" + dt.datetime.fromtimestamp(t_ns / 1e9, ZoneInfo(self.tz)).date().isoformat()

    def _confirmed(self, t_ns: int) -> NDArray[np.float64]:
        """(n + 1,) 1.0 for elements seen appearing (a strong transition) and standing at ``t_ns``: their pixels
        show what their material looks like."""
        out = np.zeros(len(self.global_ids) + 1)
        for i, g in enumerate(self.global_ids, start=1):
            obs = self.tracks[g].observations.values()
            if any(o.llr_change >= self.params.confirm_llr for o in obs) or any(
                o.llr_state >= ANNOTATION_LLR for o in obs
            ):
                out[i] = float(self.posterior(g).present_at(t_ns) >= self.params.material_learn_probability)
        return out

    def _learn_materials(
        self, bins: NDArray[np.int32], occluded: NDArray[np.bool_], ids: NDArray[np.uint32], t: int
    ) -> None:
        """Adds the colours (``bins``, :func:`~nodes.progress.evidence.colour_bins` of the photo) of the elements
        seen appearing and standing at ``t`` to their materials' looks."""
        confirmed = self._confirmed(t) > 0
        keep = ~occluded & (ids > 0) & (ids < len(confirmed))
        idx = ids[keep].astype(np.int64)
        mine = confirmed[idx]
        idx, px_bins = idx[mine], bins[keep][mine]
        order = np.argsort(idx, kind="stable")
        idx, px_bins = idx[order], px_bins[order]
        n_px = np.bincount(idx, minlength=len(confirmed))
        ends = np.cumsum(n_px)
        for i in np.nonzero(n_px >= self.params.evidence.min_pixels)[0]:  # ascending index, as elements are listed
            self.materials.add(self.material_of[int(i)], px_bins[ends[i] - n_px[i] : ends[i]], weight=1.0)

    # -- messages -------------------------------------------------------------------------------------

    def photo_evidence_message(
        self, record: PhotoRecord, cues: list[ElementCue], size: tuple[int, int]
    ) -> PhotoEvidence:
        out = []
        for c in cues:
            gid = self.global_ids[c.index - 1]
            state, conf = self.photo_state(gid, c.status, record.capture_time_ns, c.occluded_fraction)
            out.append(
                ElementEvidence(
                    global_id=gid,
                    state=state,  # type: ignore[arg-type]
                    confidence=conf,
                    visible_px=c.visible_px,
                    occluded_fraction=c.occluded_fraction,
                    llr_change=c.llr_change,
                    llr_points=c.llr_points,
                    llr_appearance=c.llr_appearance,
                    reference_ns=c.reference_ns,
                    changed_fraction=None if np.isnan(c.changed_fraction) else c.changed_fraction,
                )
            )
        return PhotoEvidence(
            site=self.model.site if self.model is not None else "",
            photo_id=record.photo_id,
            camera_id=record.camera_id,
            capture_time_ns=record.capture_time_ns,
            filename=record.filename,
            elements=tuple(out),
            working_width_px=size[0],
            working_height_px=size[1],
            processing_ms=record.processing_ms,
        )

    def photo_state(self, gid: str, status: str, t_ns: int, occluded_fraction: float) -> tuple[str, float]:
        """State of an element in a photo: the fused estimate at its capture time (given every photo) where it is
        in view and not hidden by the occlusion mask, also when too few of its pixels show for this photo's own
        cues (status ``unknown``); ``occluded`` where the mask hides it."""
        if status == "occluded":
            return "occluded", occluded_fraction
        if status not in ("seen", "unknown") or not self.tracks[gid].observations:
            return "unknown", 0.0
        p = self.posterior(gid).present_at(t_ns)
        b = self.fusion.built_probability
        if p >= b:
            return "built", p
        if p <= 1.0 - b:
            return "not_built", 1.0 - p
        return "unknown", max(p, 1.0 - p)

    def element_progress(self, gid: str, as_of_ns: int | None = None) -> ElementProgress:
        e = self.estimate(gid, as_of_ns)
        w = self.windows.get(gid)
        obs = self.tracks[gid].observations
        photos = tuple(sorted((o for o in obs.values()), key=lambda o: o.time_ns))
        return ElementProgress(
            global_id=gid,
            state=e.state,
            present_probability=0.0 if np.isnan(e.present_probability) else e.present_probability,
            detected_start_ns=e.last_absent_ns if e.first_present_ns is not None else None,
            detected_finish_ns=e.finish_ns,
            last_absent_ns=e.last_absent_ns,
            first_present_ns=e.first_present_ns,
            finish_probability=e.finish_probability,
            planned_start_ns=None if w is None else w.build_start_ns,
            planned_finish_ns=None if w is None else w.build_finish_ns,
            deviation=e.deviation,
            task_ids=self.element_tasks.get(gid, ()),
            num_observations=e.num_observations,
            evidence_photo_ids=tuple(o.photo_id for o in photos[-20:]),
        )

    def task_progress(self, task: ScheduleTask, as_of_ns: int | None = None) -> TaskProgress:
        t = self.as_of_ns if as_of_ns is None else as_of_ns
        ests = [self.estimate(g, t) for g in self.task_elements.get(task.task_id, task.element_ids) if g in self.tracks]
        observed = [e for e in ests if e.num_observations]
        built = [e for e in ests if e.state == "built"]
        n = len(ests)
        pct = (
            100.0 * sum(0.0 if np.isnan(e.present_probability) else e.present_probability for e in observed) / max(n, 1)
        )
        dur = max(task.planned_finish_ns - task.planned_start_ns, 1)
        planned = 100.0 * float(np.clip((t - task.planned_start_ns) / dur, 0.0, 1.0))
        starts = [e.last_absent_ns for e in built if e.last_absent_ns is not None]
        finishes = [e.finish_ns for e in built]
        actual_finish = max(f for f in finishes if f is not None) if n and len(built) == n and all(finishes) else None  # type: ignore[type-var]
        dev = "unknown"
        if observed:
            if len(built) == n:
                devs = {e.deviation for e in ests}
                dev = "behind" if "behind" in devs else "ahead" if devs == {"ahead"} else "on_time"
            elif t > task.planned_finish_ns:
                dev = "not_built" if not built else "behind"
            else:
                dev = "behind" if pct < planned - 25.0 else "ahead" if pct > planned + 25.0 else "on_time"
        return TaskProgress(
            task_id=task.task_id,
            name=task.name,
            planned_start_ns=task.planned_start_ns,
            planned_finish_ns=task.planned_finish_ns,
            actual_start_ns=min(starts) if starts else None,
            actual_finish_ns=actual_finish,
            percent_complete=pct,
            planned_percent=planned,
            deviation=dev,  # type: ignore[arg-type]
            num_elements=n,
            num_built=len(built),
            num_observed=len(observed),
        )

    def storey_progress(self, as_of_ns: int | None = None) -> list[StoreyProgress]:
        t = self.as_of_ns if as_of_ns is None else as_of_ns
        acc: dict[str, list[float]] = {}
        for g in self.global_ids:
            w = self.windows.get(g)
            if w is None or w.build_finish_ns is None:
                continue
            s = w.build_start_ns if w.build_start_ns is not None else w.build_finish_ns
            planned = float(np.clip((t - s) / max(w.build_finish_ns - s, 1), 0.0, 1.0))
            p = self.posterior(g).present_at(t) if self.tracks[g].observations else 0.0
            a = acc.setdefault(self.storey_of.get(g, "") or "(no storey)", [0.0, 0.0, 0.0])
            a[0] += planned
            a[1] += p
            a[2] += 1
        return [
            StoreyProgress(
                storey=s, planned_fraction=a[0] / a[2], detected_fraction=a[1] / a[2], num_elements=int(a[2])
            )
            for s, a in sorted(acc.items())
        ]

    def update_message(self, touched: list[str], photo_id: str = "") -> ProgressUpdate:
        gids = list(dict.fromkeys(touched))
        direct = [tid for g in gids for tid in self.element_tasks.get(g, ())]
        task_ids = dict.fromkeys(a for tid in direct for a in (tid, *self.task_ancestors.get(tid, ())))
        self._estimates = {}
        try:
            return self._update_message(gids, task_ids, photo_id)
        finally:
            self._estimates = None

    def _update_message(self, gids: list[str], task_ids: dict[str, None], photo_id: str) -> ProgressUpdate:
        return ProgressUpdate(
            site=self.model.site if self.model is not None else "",
            as_of_ns=self.as_of_ns,
            photo_id=photo_id,
            elements=tuple(self.element_progress(g) for g in gids),
            tasks=tuple(self.task_progress(self.tasks[tid]) for tid in task_ids if tid in self.tasks),
            storeys=tuple(self.storey_progress()),
            tz=self.tz,
        )
