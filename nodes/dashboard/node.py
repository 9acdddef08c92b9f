"""Dashboard node: streams a site to rerun (file, gRPC server or a running viewer).

``rerun`` config / ``--set rerun=...``: ``save:PATH.rrd`` (``{site}`` is replaced), ``serve`` or
``serve:PORT`` (gRPC server; connect a viewer with ``rerun rerun+http://HOST:PORT/proxy``), or
``connect`` / ``connect:URL`` (a running viewer, default ``rerun+http://127.0.0.1:9876/proxy``).
The scene logic lives in :mod:`nodes.dashboard.scene`; this shell maps its ops to rerun calls
and keeps the default blueprint up to date: the 3D view, the storeys' progress plot and the log, and per registered
camera one 2D view showing one overlay mode (``overlay_mode``; other modes and the occlusion masks are layers the
user toggles in the blueprint panel) above the camera's status line.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from constructaide.errors import UserError
from constructaide.runtime import Input, NodeContext, NodeSpec, run_node_cli
from nodes.dashboard.scene import LOG, PROGRESS, STATUS, WORLD, EntityPath, LogOp, Scene, image_path
from schemas import keys
from schemas import messages as m


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    rerun: str = "save:recordings/dashboard.rrd"
    """Sink: ``save:PATH.rrd`` | ``serve`` | ``serve:PORT`` | ``connect`` | ``connect:URL``."""
    photo_cache: int = 512
    """Photos kept (by photo_id) to pair with registrations arriving later (photos already shown leave first)."""
    photo_cache_mib: float = 512.0
    """... and at most this many MiB of photo bytes (the newest photo is always kept)."""
    image_plane_distance_m: float = 1.0
    point_radius_m: float = 0.03
    application_id: str = "constructaide"
    overlay_mode: str = "progress"
    """Overlay mode each camera view shows (the other modes and the occlusion masks are layers a user toggles)."""


def entity_path(parts: EntityPath) -> str:
    """Escaped rerun entity path string of unescaped parts."""
    return "/" + "/".join(rr.escape_entity_path_part(p) for p in parts)


def camera_view(camera: str, overlay_mode: str) -> rrb.Vertical:
    """A camera's photo with one overlay mode (the other modes and the masks hidden, toggled by the user in the
    blueprint panel), above its status line."""
    img = image_path(camera)
    hidden = rrb.EntityBehavior(visible=False)
    overrides = {
        entity_path((*img, "overlay")): hidden,
        entity_path((*img, "overlay", overlay_mode)): rrb.EntityBehavior(visible=True),
        entity_path((*img, "occlusion")): hidden,
    }
    return rrb.Vertical(
        rrb.Spatial2DView(origin=entity_path(img), name=f"{camera}: {overlay_mode}", overrides=overrides),  # type: ignore[arg-type]
        rrb.TextDocumentView(origin=entity_path((*STATUS, camera)), name=f"{camera} status"),
        row_shares=[6, 1],
    )


def make_blueprint(cameras: Iterable[str], overlay_mode: str = "progress") -> rrb.Blueprint:
    """3D view of the world, the storeys' planned-vs-detected progress and the log, plus one 2D view per camera
    (with its status line)."""
    views_2d = [camera_view(c, overlay_mode) for c in cameras]
    left = rrb.Vertical(
        rrb.Spatial3DView(origin=entity_path(WORLD), name="site"),
        rrb.TimeSeriesView(origin=entity_path(PROGRESS), name="progress per storey: planned vs detected (%)"),
        rrb.TextLogView(origin=entity_path(LOG), name="log"),
        row_shares=[4, 2, 1],
    )
    if not views_2d:
        return rrb.Blueprint(left, collapse_panels=False)
    return rrb.Blueprint(rrb.Horizontal(left, rrb.Grid(*views_2d), column_shares=[3, 2]), collapse_panels=False)


def _archetype(op: LogOp) -> Any:
    f = op.fields
    kind = op.kind
    if kind == "view_coordinates":
        return getattr(rr.ViewCoordinates, f["xyz"])
    if kind == "annotation_context":
        return rr.AnnotationContext(
            [rr.AnnotationInfo(id=i, label=label, color=rgba) for i, label, rgba in f["classes"]]
        )
    if kind == "mesh":
        return rr.Mesh3D(
            vertex_positions=f["vertex_positions"],
            triangle_indices=f["triangle_indices"],
            albedo_factor=f.get("albedo_factor"),
        )
    if kind == "mesh_color":
        return rr.Mesh3D.from_fields(albedo_factor=f["albedo_factor"])
    if kind == "transform":
        return rr.Transform3D(translation=f["translation"], mat3x3=f["mat3x3"])
    if kind == "pinhole":
        return rr.Pinhole(
            image_from_camera=f["image_from_camera"],
            resolution=list(f["resolution"]),
            camera_xyz=rr.ViewCoordinates.RDF,
            image_plane_distance=f["image_plane_distance"],
        )
    if kind == "image":
        return rr.EncodedImage(
            contents=f["contents"], media_type=f["media_type"], opacity=f.get("opacity"), draw_order=f.get("draw_order")
        )
    if kind == "segmentation":
        return rr.SegmentationImage(f["image"], opacity=f.get("opacity"), draw_order=f.get("draw_order"))
    if kind == "points":
        return rr.Points3D(f["positions"], colors=f.get("colors"), radii=f.get("radii"))
    if kind == "text":
        return rr.TextLog(f["text"], level=f.get("level"))
    if kind == "lines2d":
        return rr.LineStrips2D(
            f["strips"], labels=f.get("labels"), colors=f.get("colors"), draw_order=f.get("draw_order")
        )
    if kind == "text_document":
        return rr.TextDocument(f["text"], media_type=rr.MediaType.MARKDOWN)
    if kind == "scalars":
        return rr.Scalars(f["value"])
    if kind == "series_style":
        return rr.SeriesLines(names=f["name"], colors=f["color"])
    if kind == "clear":
        return rr.Clear(recursive=bool(f.get("recursive", False)))
    raise ValueError(f"unknown op kind {kind!r}")


def open_stream(spec: str, site: str, application_id: str, blueprint: rrb.Blueprint) -> tuple[rr.RecordingStream, str]:
    """A recording stream connected to the sink named by ``spec``; returns it and a description."""
    rec = rr.RecordingStream(application_id, recording_id=f"{site}-{uuid.uuid4().hex[:12]}")
    kind, _, arg = spec.partition(":")
    if kind == "save":
        if not arg:
            raise UserError("rerun sink 'save:' needs a path, e.g. save:recordings/dashboard.rrd")
        path = Path(arg.replace("{site}", site))
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path, default_blueprint=blueprint)
        return rec, f"saving to {path}"
    if kind == "serve":
        if arg and not arg.isdigit():
            raise UserError(f"rerun sink serve:PORT needs a port number, got {arg!r}")
        port = int(arg) if arg else None
        uri = rec.serve_grpc(grpc_port=port, default_blueprint=blueprint)
        return rec, f"serving at {uri}"
    if kind == "connect":
        rec.connect_grpc(arg or None, default_blueprint=blueprint)
        return rec, f"connected to {arg or 'rerun+http://127.0.0.1:9876/proxy'}"
    raise UserError(f"rerun sink must be save:PATH, serve[:PORT] or connect[:URL], got {spec!r}")


class DashboardNode:
    """Feeds each message to the :class:`Scene` and logs the resulting ops to rerun."""

    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx
        self.scene = Scene(
            photo_cache_size=config.photo_cache,
            photo_cache_bytes=int(config.photo_cache_mib * 2**20),
            image_plane_distance_m=config.image_plane_distance_m,
            point_radius_m=config.point_radius_m,
        )
        self._blueprint_cameras: tuple[str, ...] = ()
        self.rec, where = open_stream(
            config.rerun, ctx.site, config.application_id, make_blueprint((), config.overlay_mode)
        )
        ctx.log.info("dashboard for site %s: %s", ctx.site, where)

    def _log(self, ops: list[LogOp]) -> None:
        for op in ops:
            self.rec.reset_time()
            if not op.static:
                self.rec.set_time("event", sequence=op.event)
                if op.time_ns is not None:
                    self.rec.set_time("capture_time", timestamp=np.datetime64(op.time_ns, "ns"))
            self.rec.log(entity_path(op.path), _archetype(op), static=op.static, strict=True)
        cams = tuple(self.scene.cameras)
        if cams != self._blueprint_cameras:
            self._blueprint_cameras = cams
            self.rec.send_blueprint(make_blueprint(cams, self.config.overlay_mode), make_active=True, make_default=True)

    def on_message(self, msg: m.Message) -> None:
        """Feed a message to the scene method named for its type in :data:`SUBSCRIPTIONS`; log the ops."""
        self._log(getattr(self.scene, _SCENE_METHOD[type(msg)])(msg))

    def close(self) -> None:
        """Flush and close the sink (finishes the .rrd file)."""
        self.rec.flush()
        self.rec.disconnect()


SUBSCRIPTIONS: tuple[tuple[str, type[m.Message], str], ...] = (  # (key template, message type, Scene method)
    (keys.BIM_MODEL, m.BimModel, "on_bim_model"),
    (keys.BIM_UPDATE, m.BimUpdate, "on_bim_update"),
    (keys.PHOTO, m.Photo, "on_photo"),
    (keys.REGISTRATION, m.Registration, "on_registration"),
    (keys.SPARSE, m.SparseCloud, "on_sparse"),
    (keys.OVERLAY, m.Overlay, "on_overlay"),
    (keys.OCCLUSION, m.OcclusionMask, "on_occlusion"),
    (keys.NEEDS_ANCHOR, m.NeedsAnchor, "on_needs_anchor"),
    (keys.ANNOTATION, m.Annotation, "on_annotation"),
    (keys.ERRORS, m.NodeError, "on_error"),
    (keys.PHOTO_EVIDENCE, m.PhotoEvidence, "on_photo_evidence"),
    (keys.PROGRESS, m.ProgressUpdate, "on_progress"),
)
_SCENE_METHOD = {t: method for _, t, method in SUBSCRIPTIONS}
INPUTS = tuple(Input(k, t, "on_message", latched=t is m.BimModel, with_key=False) for k, t, _ in SUBSCRIPTIONS)
DESCRIPTION = "Streams the BIM, registered cameras with photos, sparse points, overlays and masks to rerun."
SPEC = NodeSpec("dashboard", DESCRIPTION, Config, DashboardNode, INPUTS, ())


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
