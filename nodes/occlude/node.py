"""Occlude node: dynamic, static, user and combined occlusion masks per photo (the shell).

Inputs: photos, registrations, viewpoint groups, the sparse cloud, the BIM model (latched) and updates,
annotations. Outputs: ``OcclusionMask`` on ``constructaide/{site}/occlusion/{kind}/{photo}`` for kinds ``dynamic``
(with the clean background plate), ``static``, ``user`` and ``combined`` (union of the ``ok`` masks of the other
kinds; what the render node should use). Which mask is (re)computed when is :mod:`nodes.occlude.pipeline`; the
inputs go straight to its methods.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from constructaide.modelview import ModelView
from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from nodes.occlude import state
from nodes.occlude.pipeline import Config, OcclusionPipeline
from schemas import keys
from schemas import messages as m

__all__ = ["SPEC", "Config", "OccludeNode", "main"]


class OccludeNode(OcclusionPipeline):
    """The occlusion pipeline publishing every mask it makes on the bus."""

    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.ctx = ctx
        super().__init__(config, self._publish_mask, site=ctx.site)

    def _publish_mask(self, msg: m.OcclusionMask, mask: NDArray[np.uint8] | None) -> None:
        self.ctx.publish(keys.key(keys.OCCLUSION, site=self.ctx.site, kind=msg.kind, photo=msg.photo_id), msg)

    def on_idle(self) -> bool:
        return self.idle()

    # durable state (with a state dir): stacks and masks are large, so snapshots are taken at most every
    # state_every_secs; a crash re-handles the messages since the last one (their masks are published again)
    state_every_secs = 10.0

    def state_snapshot(self) -> dict[str, bytes]:
        return {"pipeline": state.dump(self)}

    def restore_state(self, blobs: dict[str, bytes]) -> None:
        if "pipeline" not in blobs:
            return
        state.load_into(self, blobs["pipeline"])
        if self.meshes:
            self.renderer = ModelView(self.meshes)
        self.ctx.log.info("resumed: %d photos, %d registrations", len(self.photos), len(self.registrations))

    def adopt_state(self, sources: list[dict[str, bytes]], owns_camera: Callable[[str], bool]) -> None:
        """Partitioned worker: take over its cameras' frames from the other workers' state files."""
        taken = state.adopt_cameras(self, [b["pipeline"] for b in sources if "pipeline" in b], owns_camera)
        if taken:
            self.ctx.log.info("took over cameras %s from other workers' state", ", ".join(taken))


INPUTS = (
    Input(keys.PHOTO, m.Photo, "add_photo", with_key=False),
    Input(keys.REGISTRATION, m.Registration, "add_registration", with_key=False),
    Input(keys.VIEWPOINTS, m.ViewpointGroup, "set_viewpoints", with_key=False),
    Input(keys.SPARSE, m.SparseCloud, "set_sparse", latched=True, with_key=False),
    Input(keys.BIM_MODEL, m.BimModel, "set_model", latched=True, with_key=False),
    Input(keys.BIM_UPDATE, m.BimUpdate, "apply_update", with_key=False),
    Input(keys.ANNOTATION, m.Annotation, "add_annotation", with_key=False),
)
DESCRIPTION = "dynamic (time-lapse vote), static (sparse points vs BIM), user and combined occlusion masks"
SPEC = NodeSpec("occlude", DESCRIPTION, Config, OccludeNode, INPUTS, (Output(keys.OCCLUSION, m.OcclusionMask),))


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
