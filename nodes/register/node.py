"""The register node (streaming): photos and anchor clicks in, registrations, viewpoint groups and the sparse map out.

Thin shell around :class:`nodes.register.streaming.StreamingRegistrar`. Photos that cannot be registered yet (no
anchor, or not enough matches) wait in a bounded queue and are retried whenever new anchor clicks arrive; a photo
pushed out of a full queue gets a ``failed`` Registration, so no photo disappears silently. The BIM model (and its
updates) only feeds the depth lookup that gives anchor features 3D points; it never triggers re-registration.
"""

from __future__ import annotations

from collections.abc import Callable

import msgspec

from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from constructaide.sparsecloud import encode_sparse_cloud
from nodes.register import state
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.bimsite import BimMeshes
from nodes.register.inbox import Inbox, click_arrays, dropped_registration, late_clicks_note, photo_input
from nodes.register.streaming import Outcome, StreamConfig, StreamingRegistrar
from schemas import keys
from schemas import messages as m


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
    again)."""
    stream: StreamConfig = StreamConfig()


class RegisterNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx
        self.inbox = Inbox(config.max_pending, config.max_pending_anchors, config.keep_recent_photos)
        self.registrar = StreamingRegistrar(config.stream, site=ctx.site)
        self.bim = BimMeshes()
        self.sparse_revision = 0
        self._map_changes = 0
        self._bim_dirty = False
        self._saved_features: dict[str, tuple[int, bool]] = {}

    # -- durable state (saved by the runtime when the node has a state dir) -----------------------------------

    # the map grows to many MB: snapshots at most every few seconds (and when the inbox runs dry); the runtime
    # holds the registrations published since and sends them with the snapshot (an outbox)
    state_every_secs = 5.0
    hold_outputs = True

    def state_snapshot(self) -> dict[str, bytes]:
        out = state.dump_map(self, self._saved_features)
        if self._bim_dirty:
            out["bim"] = state.dump_bim(self)
            self._bim_dirty = False
        return out

    def restore_state(self, blobs: dict[str, bytes]) -> None:
        if state.load_into(self, blobs):
            self._rebuild_depth()
        self._saved_features = state.saved_features(self.registrar.recon)
        n_reg, n_wait = self.registrar.num_registered, len(self.inbox.pending)
        self.ctx.log.info("resumed: %d photos registered, %d waiting for anchors", n_reg, n_wait)

    def adopt_state(self, sources: list[dict[str, bytes]], owns_camera: Callable[[str], bool]) -> None:
        """Partitioned worker: take over its cameras' state from the other workers' state files."""
        taken = state.adopt_cameras(self, sources, owns_camera)
        if taken:
            self.ctx.log.info("took over cameras %s from other workers' state", ", ".join(taken))

    # -- handlers -------------------------------------------------------------

    def on_photo(self, msg: m.Photo, key: str) -> None:
        photo = photo_input(msg)
        if msg.photo_id in self.inbox.pending_anchors:
            try:
                self._register_anchor(msg, self.inbox.pending_anchors.pop(msg.photo_id))
            except ValueError as exc:
                # Refused clicks (too few left after dropping mis-clicks, ...): said so, and the photo goes on as
                # any other — registered from the map when it can be, else waiting (and asking) for new clicks.
                self.ctx.error(keys.PHOTO, f"anchor clicks for {msg.photo_id} refused: {exc}", key)
            else:
                self._retry_pending()
                return
        if not self.registrar.has_registrations() and not self.registrar.can_track(msg.camera_id):
            if (found := self.registrar.register_by_model(photo)) is not None:  # a fixed camera the model finds
                self._publish(found)
                self.inbox.remember(msg)
                self._retry_pending()
                return
            self._enqueue(msg)
            self.inbox.unreported.add(msg.photo_id)
            if self.inbox.first_ask(msg):
                self._publish_needs_anchor(msg.photo_id, "no registered photos yet: please click anchors on this photo")
            return
        out = self.registrar.register(photo)
        self._publish(out)
        if out.registration.status == "failed":
            self._enqueue(msg)
        else:
            self.inbox.remember(msg)
            if out.map_changed:
                self._retry_pending()

    def on_anchors(self, msg: m.AnchorClicks, key: str) -> None:
        if len(msg.points) < 4:
            raise ValueError(f"anchor clicks for {msg.photo_id}: need at least 4 points, got {len(msg.points)}")
        self.inbox.check_clicks_on_image(msg)
        photo = self.inbox.photo_for_clicks(msg.photo_id)
        if photo is None:
            if msg.photo_id in self.registrar.poses:
                self._check_late_clicks(msg)
                return
            self.inbox.keep_anchors(msg)
            self.ctx.log.info("anchors for %s wait for the photo", msg.photo_id)
            return
        try:
            self._register_anchor(photo, msg)
        except ValueError:
            if msg.photo_id not in self.registrar.poses:
                self.inbox.pending[msg.photo_id] = photo  # keep the photo for corrected clicks
            raise
        self._retry_pending()

    def on_bim_model(self, msg: m.BimModel, key: str) -> None:
        self.bim.set_model(msg)
        self._bim_dirty = True
        self._rebuild_depth()

    def on_bim_update(self, msg: m.BimUpdate, key: str) -> None:
        self.bim.apply_update(msg)
        self._bim_dirty = True
        self._rebuild_depth()

    # -- internals ------------------------------------------------------------

    def _rebuild_depth(self) -> None:
        old = self.registrar.depth_lookup
        if isinstance(old, MeshDepthLookup):
            old.close()
        self.registrar.depth_lookup = None
        if not self.config.use_bim_depth or not self.bim.meshes:
            return
        try:
            self.registrar.depth_lookup = self.bim.depth_lookup()
        except ValueError as e:
            self.ctx.log.warning("no depth lookup: %s", e)
            return
        if old is None:  # the first model: photos registered before it get their model points now
            added = self.registrar.add_model_points_to_map()
            if added:
                self.ctx.log.info("BIM depth now available: %d model points for the map images before it", added)

    def _check_late_clicks(self, clicks: m.AnchorClicks) -> None:
        """Clicks for a registered photo whose pixels are gone check its registration (``late_clicks_note``)."""
        off_px = self.registrar.click_disagreement_px(clicks.photo_id, *click_arrays(clicks))
        width_px = self.registrar.poses[clicks.photo_id].intrinsics.width_px
        cfg = self.config
        ok, note = late_clicks_note(clicks.photo_id, off_px, width_px, cfg.late_click_max_frac, cfg.keep_recent_photos)
        if ok:
            self.ctx.log.info(note)
            return
        self.inbox.keep_anchors(clicks)
        raise ValueError(note)

    def _register_anchor(self, photo: m.Photo, clicks: m.AnchorClicks) -> None:
        px, pts = click_arrays(clicks)
        out = self.registrar.register_anchor(photo_input(photo), px, pts, focal_px=clicks.focal_px)
        self._publish(out)
        self.inbox.remember(photo)

    def _retry_pending(self) -> None:
        self.inbox.retry_waiting(self.registrar.retry, self._publish)

    def _enqueue(self, msg: m.Photo) -> None:
        for old in self.inbox.enqueue(msg):
            self.registrar.forget(old.photo_id)  # its features and matches leave the map too
            reg = dropped_registration(self.ctx.site, old, self.config.max_pending)
            self.ctx.publish(
                keys.key(keys.REGISTRATION, site=self.ctx.site, camera=old.camera_id, photo=old.photo_id), reg
            )

    def _publish_needs_anchor(self, photo_id: str, reason: str, num_tracks: int = 0) -> None:
        self.ctx.publish(
            keys.key(keys.NEEDS_ANCHOR, site=self.ctx.site, photo=photo_id),
            m.NeedsAnchor(site=self.ctx.site, photo_id=photo_id, reason=reason, num_matched_tracks=num_tracks),
        )

    def _publish(self, out: Outcome, ask: bool = True) -> None:
        self.inbox.unreported.discard(out.registration.photo_id)
        reg = out.registration
        if self.registrar.depth_error:
            self.ctx.error("bim", self.registrar.depth_error)
            self.registrar.depth_error = ""
        key = keys.key(keys.REGISTRATION, site=self.ctx.site, camera=reg.camera_id, photo=reg.photo_id)
        self.ctx.publish(key, reg)
        if reg.status != "failed":
            polished = self.registrar.polish_registration(reg)  # the BIM's outlines: an update that follows
            if polished is not None:
                self.ctx.publish(key, polished)
        if out.needs_anchor is not None and ask:
            self._publish_needs_anchor(reg.photo_id, out.needs_anchor, out.num_matched_tracks)
        if self.config.publish_viewpoints:
            for pid in out.viewpoint_changed:
                msg: m.ViewpointGroup = self.registrar.viewpoints.group_message(self.ctx.site, pid)
                self.ctx.publish(keys.key(keys.VIEWPOINTS, site=self.ctx.site, photo=pid), msg)
        if out.map_changed and self.config.sparse_every > 0:
            self._map_changes += 1
            if self._map_changes >= self.config.sparse_every:
                self._map_changes = 0
                self._publish_sparse()

    def _publish_sparse(self) -> None:
        self.sparse_revision += 1
        cloud = encode_sparse_cloud(self.ctx.site, self.sparse_revision, self.registrar.sparse_arrays())
        self.ctx.publish(keys.key(keys.SPARSE, site=self.ctx.site), cloud)


SPEC = NodeSpec(
    name="register",
    description="registers photos to the BIM: anchors, fixed-camera fast path, full SIFT path, viewpoint groups",
    config_type=Config,
    factory=RegisterNode,
    inputs=(
        Input(keys.PHOTO, m.Photo, "on_photo"),
        Input(keys.ANCHORS, m.AnchorClicks, "on_anchors"),
        Input(keys.BIM_MODEL, m.BimModel, "on_bim_model", latched=True),
        Input(keys.BIM_UPDATE, m.BimUpdate, "on_bim_update"),
    ),
    outputs=(
        Output(keys.REGISTRATION, m.Registration),
        Output(keys.VIEWPOINTS, m.ViewpointGroup),
        Output(keys.SPARSE, m.SparseCloud, latched=True),
        Output(keys.NEEDS_ANCHOR, m.NeedsAnchor),
    ),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
