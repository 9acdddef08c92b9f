"""The register node (streaming): photos and anchor clicks in, registrations, viewpoint groups and the sparse map out.

Thin shell around :class:`nodes.register.streaming.StreamingRegistrar`. Photos that cannot be registered yet (no
anchor, or not enough matches) wait in a bounded queue and are retried whenever new anchor clicks arrive; a photo
pushed out of a full queue gets a ``failed`` Registration, so no photo disappears silently. The BIM model (and its
updates) only feeds the depth lookup that gives anchor features 3D points; it never triggers re-registration.
"""

from __future__ import annotations

from collections import OrderedDict

import msgspec
import numpy as np

from constructaide.bimgeom import glb_to_meshes
from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from constructaide.schedule4d import standing_elements
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.photo import FrameImage, PhotoInput
from nodes.register.streaming import Outcome, StreamConfig, StreamingRegistrar
from schemas import keys
from schemas.messages import (
    AnchorClicks,
    BimModel,
    BimUpdate,
    NeedsAnchor,
    Photo,
    Registration,
    SparseCloud,
    ViewpointGroup,
)


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    max_pending: int = 256
    """Photos waiting for an anchor (oldest pushed out with a failed Registration when full)."""
    max_pending_anchors: int = 64
    """Anchor clicks waiting for their photo."""
    use_bim_depth: bool = True
    """Give anchor features 3D points from the BIM mesh (ray casting)."""
    publish_viewpoints: bool = True
    sparse_every: int = 1
    """Publish the SparseCloud after this many map changes (0: never)."""
    keep_recent_photos: int = 32
    """Registered photos kept (bytes) so late anchor clicks can correct their registration."""
    late_click_max_frac: float = 0.02
    """Clicks arriving for a registered photo whose pixels are gone confirm its registration when their median
    distance to the projected model points is at most this fraction of the width (else an error asks for the photo
    again; correct automatic poses on the synthetic default site put clicks <= 0.6 % of the width off)."""
    stream: StreamConfig = StreamConfig()


def _photo_input(msg: Photo) -> PhotoInput:
    if not msg.data:
        raise ValueError(f"photo {msg.photo_id} has no image data")
    return PhotoInput(
        photo_id=msg.photo_id,
        image=FrameImage(data=msg.data),
        camera_id=msg.camera_id,
        capture_time_ns=msg.capture_time_ns,
        focal_px=msg.focal_px,
        width_px=msg.width_px,
        height_px=msg.height_px,
        gps=msg.gps,
    )


class RegisterNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        if config.max_pending < 1:
            raise ValueError("max_pending must be >= 1")
        self.config = config
        self.ctx = ctx
        self.registrar = StreamingRegistrar(config.stream, site=ctx.site)
        self.pending: OrderedDict[str, Photo] = OrderedDict()
        self.pending_anchors: OrderedDict[str, AnchorClicks] = OrderedDict()
        self.recent: OrderedDict[str, Photo] = OrderedDict()
        self.asked_anchor: set[str] = set()
        self.meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.ref_of: dict[str, str] = {}
        self.tasks: tuple = ()
        self.terrain_height_m: float | None = None
        self.sparse_revision = 0
        self._map_changes = 0

    # -- handlers -------------------------------------------------------------

    def on_photo(self, msg: Photo, key: str) -> None:
        photo = _photo_input(msg)
        if msg.photo_id in self.pending_anchors:
            clicks = self.pending_anchors.pop(msg.photo_id)
            self._register_anchor(msg, clicks)
            self._retry_pending()
            return
        if not self.registrar.has_registrations():
            self._enqueue(msg)
            group = msg.camera_id or f"phone:{msg.photo_id}"
            if group not in self.asked_anchor:
                self.asked_anchor.add(group)
                self._publish_needs_anchor(msg.photo_id, "no registered photos yet: please click anchors on this photo")
            return
        out = self.registrar.register(photo)
        self._publish(out)
        if out.registration.status == "failed":
            self._enqueue(msg)
        else:
            self._remember(msg)
            if out.map_changed:
                self._retry_pending()

    def on_anchors(self, msg: AnchorClicks, key: str) -> None:
        if len(msg.points) < 4:
            raise ValueError(f"anchor clicks for {msg.photo_id}: need at least 4 points, got {len(msg.points)}")
        known = self.pending.get(msg.photo_id) or self.recent.get(msg.photo_id)
        if known is not None and known.width_px > 0 and known.height_px > 0:
            off = [i for i, p in enumerate(msg.points)
                   if not (0 <= p.pixel_px[0] <= known.width_px and 0 <= p.pixel_px[1] <= known.height_px)]  # fmt: skip
            if off:
                raise ValueError(f"anchor clicks for {msg.photo_id}: point(s) {off} off the "
                                 f"{known.width_px}x{known.height_px} image")  # fmt: skip
        photo = self.pending.pop(msg.photo_id, None) or self.recent.get(msg.photo_id)
        if photo is None:
            if msg.photo_id in self.registrar.poses:
                self._check_late_clicks(msg)
                return
            self._keep_anchors(msg)
            self.ctx.log.info("anchors for %s wait for the photo", msg.photo_id)
            return
        try:
            self._register_anchor(photo, msg)
        except ValueError:
            if msg.photo_id not in self.registrar.poses:
                self.pending[msg.photo_id] = photo  # keep the photo for corrected clicks
            raise
        self._retry_pending()

    def on_bim_model(self, msg: BimModel, key: str) -> None:
        self.meshes = dict(glb_to_meshes(msg.geometry_glb))
        self.ref_of = {e.global_id: (e.geometry_ref or e.global_id) for e in msg.elements}
        self.tasks = msg.tasks
        self.terrain_height_m = msg.terrain_height_m
        self._rebuild_depth()

    def on_bim_update(self, msg: BimUpdate, key: str) -> None:
        for gid in msg.removed:
            self.meshes.pop(self.ref_of.pop(gid, gid), None)
        for e in (*msg.added, *msg.changed):
            self.ref_of[e.global_id] = e.geometry_ref or e.global_id
        self.meshes.update(glb_to_meshes(msg.geometry_glb))
        if msg.tasks is not None:
            self.tasks = msg.tasks
        self._rebuild_depth()

    # -- internals ------------------------------------------------------------

    def _rebuild_depth(self) -> None:
        if not self.config.use_bim_depth or not self.meshes:
            self.registrar.depth_lookup = None
            return
        # Schedule states are per GlobalId; meshes are keyed by geometry_ref.
        gid_of = {ref: gid for gid, ref in self.ref_of.items()}
        by_gid = standing_elements(self.tasks, set(gid_of.values()) | {r for r in self.meshes if r not in gid_of})

        def refs_at(t_ns: int) -> set[str] | None:
            gids = by_gid(t_ns)
            if gids is None:
                return None
            return {ref for ref in self.meshes if gid_of.get(ref, ref) in gids}

        old = self.registrar.depth_lookup
        if isinstance(old, MeshDepthLookup):
            old.close()
        try:
            self.registrar.depth_lookup = MeshDepthLookup(
                self.meshes, elements_at=refs_at, ground_height_m=self.terrain_height_m
            )
        except ValueError as e:
            self.registrar.depth_lookup = None
            self.ctx.log.warning("no depth lookup: %s", e)

    def _keep_anchors(self, clicks: AnchorClicks) -> None:
        """Hold clicks until their photo is pushed (the oldest pushed out beyond ``max_pending_anchors``)."""
        self.pending_anchors[clicks.photo_id] = clicks
        while len(self.pending_anchors) > self.config.max_pending_anchors:
            self.pending_anchors.popitem(last=False)

    def _check_late_clicks(self, clicks: AnchorClicks) -> None:
        """Clicks for a photo registered meanwhile whose pixels are no longer kept (a request answered after the
        photo registered on its own): they check that registration. Within ``late_click_max_frac`` of the width
        (median) they confirm it (logged); otherwise they are kept for the photo's next push (which re-anchors it)
        and the error says so."""
        px = np.array([p.pixel_px for p in clicks.points], np.float64)
        pts = np.array([p.point_in_world_m for p in clicks.points], np.float64)
        off_px = self.registrar.click_disagreement_px(clicks.photo_id, px, pts)
        width_px = self.registrar.poses[clicks.photo_id].intrinsics.width_px
        if off_px <= self.config.late_click_max_frac * width_px:
            self.ctx.log.info(
                "clicks for %s confirm its registration (median %.1f px off); it registered before they came",
                clicks.photo_id,
                off_px,
            )
            return
        self._keep_anchors(clicks)
        raise ValueError(
            f"clicks for {clicks.photo_id} disagree with its registration (median {off_px:.1f} px off) and its pixels "
            f"are no longer kept (only the last {self.config.keep_recent_photos} photos are): the clicks are kept; "
            "push the photo again to re-anchor it with them"
        )

    def _register_anchor(self, photo: Photo, clicks: AnchorClicks) -> None:
        px = np.array([p.pixel_px for p in clicks.points], np.float64)
        pts = np.array([p.point_in_world_m for p in clicks.points], np.float64)
        out = self.registrar.register_anchor(_photo_input(photo), px, pts, focal_px=clicks.focal_px)
        self._publish(out)
        self._remember(photo)

    def _remember(self, msg: Photo) -> None:
        if self.config.keep_recent_photos <= 0:
            return
        self.recent[msg.photo_id] = msg
        self.recent.move_to_end(msg.photo_id)
        while len(self.recent) > self.config.keep_recent_photos:
            self.recent.popitem(last=False)

    def _retry_pending(self) -> None:
        """Try the waiting photos again while the map grows (each registration can connect others)."""
        grown = True
        while grown and self.pending:
            grown = False
            for msg in sorted(self.pending.values(), key=lambda p: p.capture_time_ns):
                out = self.registrar.retry(_photo_input(msg))
                if out is None:
                    continue
                if out.registration.status == "failed":
                    continue
                del self.pending[msg.photo_id]
                self._publish(out, ask=False)
                self._remember(msg)
                grown = grown or out.map_changed

    def _enqueue(self, msg: Photo) -> None:
        self.pending[msg.photo_id] = msg
        while len(self.pending) > self.config.max_pending:
            _, old = self.pending.popitem(last=False)
            reg = Registration(
                site=self.ctx.site,
                photo_id=old.photo_id,
                camera_id=old.camera_id,
                capture_time_ns=old.capture_time_ns,
                status="failed",
                message=f"dropped from the waiting queue ({self.config.max_pending} photos wait for anchors)",
            )
            self.ctx.publish(
                keys.key(keys.REGISTRATION, site=self.ctx.site, camera=old.camera_id, photo=old.photo_id), reg
            )

    def _publish_needs_anchor(self, photo_id: str, reason: str, num_tracks: int = 0) -> None:
        self.ctx.publish(
            keys.key(keys.NEEDS_ANCHOR, site=self.ctx.site, photo=photo_id),
            NeedsAnchor(site=self.ctx.site, photo_id=photo_id, reason=reason, num_matched_tracks=num_tracks),
        )

    def _publish(self, out: Outcome, ask: bool = True) -> None:
        reg = out.registration
        if self.registrar.depth_error:
            self.ctx.error("bim", self.registrar.depth_error)
            self.registrar.depth_error = ""
        self.ctx.publish(keys.key(keys.REGISTRATION, site=self.ctx.site, camera=reg.camera_id, photo=reg.photo_id), reg)
        if out.needs_anchor is not None and ask:
            self._publish_needs_anchor(reg.photo_id, out.needs_anchor, out.num_matched_tracks)
        if self.config.publish_viewpoints:
            for pid in out.viewpoint_changed:
                msg: ViewpointGroup = self.registrar.viewpoints.group_message(self.ctx.site, pid)
                self.ctx.publish(keys.key(keys.VIEWPOINTS, site=self.ctx.site, photo=pid), msg)
        if out.map_changed and self.config.sparse_every > 0:
            self._map_changes += 1
            if self._map_changes >= self.config.sparse_every:
                self._map_changes = 0
                self._publish_sparse()

    def _publish_sparse(self) -> None:
        arr = self.registrar.sparse_arrays()
        self.sparse_revision += 1
        cloud = SparseCloud(
            site=self.ctx.site,
            revision=self.sparse_revision,
            photo_ids=tuple(arr["photo_ids"]),  # type: ignore[arg-type]
            points_xyz_f32=np.ascontiguousarray(arr["points_xyz"], "<f4").tobytes(),
            colors_rgb_u8=np.ascontiguousarray(arr["colors_rgb"], np.uint8).tobytes(),
            obs_point_i32=np.ascontiguousarray(arr["obs_point"], "<i4").tobytes(),
            obs_photo_i32=np.ascontiguousarray(arr["obs_photo"], "<i4").tobytes(),
            obs_pixel_f32=np.ascontiguousarray(arr["obs_pixel"], "<f4").tobytes(),
            point_flags_u8=np.ascontiguousarray(arr["point_flags"], np.uint8).tobytes(),
        )
        self.ctx.publish(keys.key(keys.SPARSE, site=self.ctx.site), cloud)


SPEC = NodeSpec(
    name="register",
    description="registers photos to the BIM: anchors, fixed-camera fast path, full SIFT path, viewpoint groups",
    config_type=Config,
    factory=RegisterNode,
    inputs=(
        Input(keys.PHOTO, Photo, "on_photo"),
        Input(keys.ANCHORS, AnchorClicks, "on_anchors"),
        Input(keys.BIM_MODEL, BimModel, "on_bim_model", latched=True),
        Input(keys.BIM_UPDATE, BimUpdate, "on_bim_update"),
    ),
    outputs=(
        Output(keys.REGISTRATION, Registration),
        Output(keys.VIEWPOINTS, ViewpointGroup),
        Output(keys.SPARSE, SparseCloud, latched=True),
        Output(keys.NEEDS_ANCHOR, NeedsAnchor),
    ),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
