"""Progress node: which elements stand, read from the photos; fused per element over photos and time.

Inputs: the BIM model (latched) and updates, photos, registrations, occlusion masks, the sparse cloud and status
annotations. A registered photo is processed once its first ``combined`` occlusion mask arrives (or on
registration with ``require_mask = false``); a newer combined mask re-runs it from ``on_idle``. Outputs:
``PhotoEvidence`` on ``constructaide/{site}/progress/evidence/{photo}`` and ``ProgressUpdate`` (the elements
whose estimate changed, their tasks, one S-curve point per storey) on ``constructaide/{site}/progress/update``.
The algorithms live in :mod:`nodes.progress.engine`; this shell only wires topics to it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import replace

import msgspec

from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from nodes.progress.engine import ProgressEngine
from nodes.progress.params import EngineParams
from schemas import keys
from schemas import messages as m

_ENGINE = EngineParams()


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The node's settings; the engine's own defaults (one source: :class:`EngineParams`, the batch
    ``constructaide progress`` reads with them too)."""

    site: str = "demo"
    working_width_px: int = _ENGINE.working_width_px
    """Evidence is computed at ``working_scale`` of a photo's width, but at least this wide."""
    working_scale: float = _ENGINE.working_scale
    require_mask: bool = True
    """Wait for a photo's combined occlusion mask before reading it (false: read it on registration)."""
    lookahead_days: float = _ENGINE.lookahead_days
    """Elements planned to start within this many days of a photo are looked for in it."""
    schedule_weight: float = _ENGINE.fusion.schedule_weight
    """Share of each element's prior that follows the schedule (the rest is flat over the project)."""
    tolerance_days: float = _ENGINE.fusion.tolerance_days
    """Deviation tolerance around the planned windows."""
    work_hours: tuple[float, float] = _ENGINE.work_hours
    """Local working hours, Mon-Fri (the middle of a finish interval is taken in working time)."""
    max_photos: int = 2000
    """Photos kept for re-reading on newer masks (the oldest processed ones leave first)."""


def engine_params(config: Config) -> EngineParams:
    return replace(
        _ENGINE,
        working_width_px=config.working_width_px,
        working_scale=config.working_scale,
        lookahead_days=config.lookahead_days,
        work_hours=config.work_hours,
        fusion=replace(_ENGINE.fusion, schedule_weight=config.schedule_weight, tolerance_days=config.tolerance_days),
    )


class ProgressNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx
        self.engine = ProgressEngine(engine_params(config))
        self.dirty: OrderedDict[str, None] = OrderedDict()  # processed photos to re-read (newer mask)
        self.waiting: set[str] = set()  # registered, waiting for a mask

    # -- inputs ---------------------------------------------------------------------------------------

    def on_model(self, msg: m.BimModel, key: str) -> None:
        self.engine.set_model(msg)
        self.ctx.log.info("model %s: %d elements, %d tasks", msg.revision, len(msg.elements), len(msg.tasks))
        self._publish_update(list(self.engine.global_ids))
        for pid in sorted(self.waiting):
            self._try(pid)

    def on_update(self, msg: m.BimUpdate, key: str) -> None:
        self.engine.apply_update(msg)
        self._publish_update(list(self.engine.global_ids))

    def on_photo(self, msg: m.Photo, key: str) -> None:
        self.engine.add_photo(msg)
        while len(self.engine.photos) > self.config.max_photos:
            old = next((p for p in self.engine.photos if p in self.engine.records), next(iter(self.engine.photos)))
            self.engine.photos.pop(old)
        self._try(msg.photo_id)

    def on_registration(self, msg: m.Registration, key: str) -> None:
        if self.engine.add_registration(msg):
            self._read_again(msg.photo_id)

    def on_occlusion(self, msg: m.OcclusionMask, key: str) -> None:
        self.engine.add_mask(msg)
        if msg.kind == "combined":
            self._read_again(msg.photo_id)

    def _read_again(self, photo_id: str) -> None:
        """A photo's registration or mask changed: redo it when it was read already, else read it if it can be."""
        if photo_id in self.engine.records:
            self._mark(photo_id)
        else:
            self._try(photo_id)

    def on_sparse(self, msg: m.SparseCloud, key: str) -> None:
        self.engine.set_sparse(msg)

    def on_annotation(self, msg: m.Annotation, key: str) -> None:
        touched = self.engine.add_annotation(msg)
        if touched:
            self._publish_update(touched)

    # -- work -----------------------------------------------------------------------------------------

    def _try(self, photo_id: str) -> None:
        """Read a photo now if it can be read for the first time."""
        if photo_id in self.engine.records or not self.engine.ready(photo_id):
            self.waiting.add(photo_id)
            return
        if self.config.require_mask and not self.engine.has_mask(photo_id):
            self.waiting.add(photo_id)
            return
        self.waiting.discard(photo_id)
        self._process(photo_id)

    def _mark(self, photo_id: str) -> None:
        self.dirty[photo_id] = None

    def on_idle(self) -> bool:
        """Re-read one photo whose mask or registration changed; True while more wait."""
        if self.dirty:
            photo_id, _ = self.dirty.popitem(last=False)
            if self.engine.ready(photo_id):
                self._process(photo_id)
        return bool(self.dirty)

    def _process(self, photo_id: str) -> None:
        evidence, update = self.engine.process(photo_id)
        site = self.ctx.site
        self.ctx.publish(keys.key(keys.PHOTO_EVIDENCE, site=site, photo=photo_id), evidence)
        self.ctx.publish(keys.key(keys.PROGRESS, site=site), update)

    def _publish_update(self, gids: list[str]) -> None:
        if self.engine.model is not None:
            self.ctx.publish(keys.key(keys.PROGRESS, site=self.ctx.site), self.engine.update_message(gids))

    def close(self) -> None:
        if self.engine.renderer is not None:
            self.engine.renderer.close()


SPEC = NodeSpec(
    name="progress",
    description="per-photo evidence of which elements stand; per-element and per-task progress and deviations",
    config_type=Config,
    factory=ProgressNode,
    inputs=(
        Input(keys.BIM_MODEL, m.BimModel, "on_model", latched=True),
        Input(keys.BIM_UPDATE, m.BimUpdate, "on_update"),
        Input(keys.PHOTO, m.Photo, "on_photo"),
        Input(keys.REGISTRATION, m.Registration, "on_registration"),
        Input(keys.OCCLUSION, m.OcclusionMask, "on_occlusion"),
        Input(keys.SPARSE, m.SparseCloud, "on_sparse", latched=True),
        Input(keys.ANNOTATION, m.Annotation, "on_annotation"),
    ),
    outputs=(Output(keys.PHOTO_EVIDENCE, m.PhotoEvidence), Output(keys.PROGRESS, m.ProgressUpdate)),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
