"""Render node: draws the BIM into every registered photo and publishes ``Overlay`` messages.

Inputs: the BIM model (latched) and updates, photos (cached by photo_id, bounded), registrations
(each newly registered photo gets one overlay per configured mode), occlusion masks (the
``combined`` kind preferred; a newer mask re-renders the photo), annotations (status
annotations colour the progress modes) and detected progress (``ProgressUpdate`` colours the progress mode; the
photo whose evidence it carries is redrawn). Output: ``constructaide/{site}/overlay/{mode}/{photo}``.
The EGL context lives on the node's worker thread (created on first render).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import msgspec

from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from nodes.render import state
from nodes.render.engine import ALL_MODES, RenderEngine, presets_path_ok
from schemas import keys
from schemas import messages as m


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    modes: tuple[str, ...] = ("state4d", "progress", "xray", "future", "edges")
    """Modes rendered for each registered photo (add "photoreal" for the slower composite)."""
    max_width_px: int = 1920
    """Photos wider than this are rendered downscaled."""
    presets_file: str = ""
    """TOML file with material / lighting presets for photoreal (see nodes/render/photoreal.py)."""
    true_north_deg: float = 0.0
    """True north, degrees counter-clockwise from the site's +y axis (sun direction in photoreal)."""
    photo_cache: int = 512
    """Photos kept for (re-)rendering, at most this many and ``photo_cache_mib`` of JPEG bytes; photos already
    rendered are dropped first (oldest first). A photo dropped before its first render is reported as a
    NodeError (it will get no overlay)."""
    photo_cache_mib: float = 1024.0
    composite: bool = False
    """Publish the photo with the overlay blended in (RGB) instead of the RGBA layer alone (the layer is
    several times smaller on the bus and in recordings; dashboards draw it over the photo)."""


class RenderNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        bad = [mode for mode in config.modes if mode not in ALL_MODES]
        if bad:
            raise ValueError(f"unknown render modes {bad}; choose from {', '.join(ALL_MODES)}")
        self.config = config
        self.ctx = ctx
        self.engine = RenderEngine(
            max_width_px=config.max_width_px,
            presets_file=presets_path_ok(config.presets_file),
            true_north_deg=config.true_north_deg,
        )
        self.photos: OrderedDict[str, m.Photo] = OrderedDict()
        self.registrations: dict[str, m.Registration] = {}
        self.masks: dict[str, m.OcclusionMask] = {}
        self.dirty: OrderedDict[str, tuple[str, ...]] = OrderedDict()  # photo_id -> modes to (re-)render
        self.rendered: set[str] = set()  # photos drawn at least once
        self._photo_bytes = 0
        self.drawn_revision: str | None = None  # model revision the rendered photos were drawn with

    # durable state (with a state dir), snapshotted at most every state_every_secs (a crash redraws the photos
    # marked since: at least once)
    state_every_secs = 10.0

    def state_snapshot(self) -> dict[str, bytes]:
        return {"render": state.dump(self)}

    def restore_state(self, blobs: dict[str, bytes]) -> None:
        if "render" in blobs:
            state.load_into(self, blobs["render"])
            self.ctx.log.info("resumed: %d photos drawn, %d to draw", len(self.rendered), len(self.dirty))

    def adopt_state(self, sources: list[dict[str, bytes]], owns_camera: Callable[[str], bool]) -> None:
        """Partitioned worker: take over its cameras' cached photos from the other workers' state files."""
        taken = state.adopt_cameras(self, [b["render"] for b in sources if "render" in b], owns_camera)
        if taken:
            self._evict()
            self.ctx.log.info("took over cameras %s from other workers' state", ", ".join(taken))

    # -- inputs ---------------------------------------------------------------------------------------

    def on_model(self, msg: m.BimModel, key: str) -> None:
        self.engine.set_model(msg)
        self.ctx.log.info("model %s: %d elements, %d tasks", msg.revision, len(msg.elements), len(msg.tasks))
        if msg.revision != self.drawn_revision:  # the same model again (a restart): nothing to redraw
            self._render_all()
        self.drawn_revision = msg.revision

    def on_update(self, msg: m.BimUpdate, key: str) -> None:
        self.engine.apply_update(msg)
        self.drawn_revision = msg.revision
        self._render_all()

    def on_photo(self, msg: m.Photo, key: str) -> None:
        old = self.photos.pop(msg.photo_id, None)
        self._photo_bytes += len(msg.data) - (len(old.data) if old is not None else 0)
        self.photos[msg.photo_id] = msg
        self._evict()
        if msg.photo_id in self.registrations:
            self._mark(msg.photo_id)

    def _evict(self) -> None:
        """Keep the photo cache within its count and byte limits: rendered photos go first (oldest first), then
        the oldest unrendered one, reported as a NodeError since it will get no overlay."""
        limit_bytes = self.config.photo_cache_mib * 2**20
        while len(self.photos) > 1 and (len(self.photos) > self.config.photo_cache or self._photo_bytes > limit_bytes):
            victim = next((pid for pid in self.photos if pid in self.rendered and pid not in self.dirty), None)
            if victim is None:
                victim = next(iter(self.photos))
                self.ctx.error(
                    "photo",
                    f"photo {victim} dropped from the render cache before it was rendered "
                    f"(photo_cache={self.config.photo_cache}, photo_cache_mib={self.config.photo_cache_mib})",
                )
            self._photo_bytes -= len(self.photos.pop(victim).data)
            self._forget(victim)

    def _forget(self, photo_id: str) -> None:
        """Drop what is kept for a photo that left the cache (it cannot be drawn again without its pixels)."""
        self.registrations.pop(photo_id, None)
        self.masks.pop(photo_id, None)
        self.dirty.pop(photo_id, None)
        self.rendered.discard(photo_id)

    def _bound(self, table: dict) -> None:
        """Registrations and masks of photos not in the cache (arrived after their photo left it) stay bounded."""
        if len(table) > 2 * self.config.photo_cache:
            for pid in [p for p in table if p not in self.photos][: len(table) - self.config.photo_cache]:
                self._forget(pid)

    def on_registration(self, msg: m.Registration, key: str) -> None:
        if msg.status == "failed":
            return
        self.registrations[msg.photo_id] = msg
        self._bound(self.registrations)
        self._mark(msg.photo_id)

    def on_occlusion(self, msg: m.OcclusionMask, key: str) -> None:
        old = self.masks.get(msg.photo_id)
        if msg.status != "ok":
            return
        if old is not None and old.kind == "combined" and msg.kind != "combined":
            return
        self.masks[msg.photo_id] = msg
        self._bound(self.masks)
        self._mark(msg.photo_id)

    def on_annotation(self, msg: m.Annotation, key: str) -> None:
        self.engine.add_annotation(msg)
        if msg.kind == "status" and "progress" in self.config.modes:
            for pid in list(self.registrations):
                self._mark(pid, ("progress",))

    def on_progress(self, msg: m.ProgressUpdate, key: str) -> None:
        """Detected progress colours the progress mode; the photo whose evidence it is gets that mode redrawn."""
        self.engine.add_progress(msg)
        if "progress" in self.config.modes and msg.photo_id in self.registrations:
            self._mark(msg.photo_id, ("progress",))

    # -- work -----------------------------------------------------------------------------------------

    def _mark(self, photo_id: str, modes: tuple[str, ...] | None = None) -> None:
        """Queue a (re-)render; several triggers for one photo before the queue drains render once."""
        wanted = self.dirty.get(photo_id, ())
        self.dirty[photo_id] = tuple(self.config.modes) if modes is None else tuple(dict.fromkeys(wanted + modes))

    def on_idle(self) -> bool:
        """Draw one photo marked dirty and say whether more are (the runtime calls again while no message waits,
        so a newer mask for a queued photo is merged into its pending render instead of drawing it twice).
        Photos never drawn come first (a backlog of re-renders must not keep a newly registered photo without
        any overlay), then the order they were marked in."""
        if self.dirty:
            photo_id = next((pid for pid in self.dirty if pid not in self.rendered), next(iter(self.dirty)))
            self._render(photo_id, self.dirty.pop(photo_id))
        return bool(self.dirty)

    def _render_all(self) -> None:
        for pid in list(self.registrations):
            self._mark(pid)

    def _render(self, photo_id: str, modes: tuple[str, ...] | None = None) -> None:
        photo = self.photos.get(photo_id)
        reg = self.registrations.get(photo_id)
        if photo is None or reg is None or self.engine.model is None:
            return
        for mode in modes or self.config.modes:
            ov = self.engine.render(
                photo, reg, mode, occlusion=self.masks.get(photo_id), composite_photo=self.config.composite
            )
            self.ctx.publish(keys.key(keys.OVERLAY, site=self.ctx.site, mode=mode, photo=photo_id), ov)
        self.rendered.add(photo_id)

    def close(self) -> None:
        self.engine.close()


INPUTS = (
    Input(keys.BIM_MODEL, m.BimModel, "on_model", latched=True),
    Input(keys.BIM_UPDATE, m.BimUpdate, "on_update"),
    Input(keys.PHOTO, m.Photo, "on_photo"),
    Input(keys.REGISTRATION, m.Registration, "on_registration"),
    Input(keys.OCCLUSION, m.OcclusionMask, "on_occlusion"),
    Input(keys.ANNOTATION, m.Annotation, "on_annotation"),
    Input(keys.PROGRESS, m.ProgressUpdate, "on_progress"),
)
DESCRIPTION = "BIM overlays (4D state, progress, x-ray, future, edges, photoreal) for every registered photo"
SPEC = NodeSpec("render", DESCRIPTION, Config, RenderNode, INPUTS, (Output(keys.OVERLAY, m.Overlay),))


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
