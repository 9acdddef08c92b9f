"""Occlude node: dynamic, static, user and combined occlusion masks per photo (the shell).

Inputs: photos, registrations, viewpoint groups, the sparse cloud, the BIM model (latched) and updates,
annotations. Outputs: ``OcclusionMask`` on ``constructaide/{site}/occlusion/{kind}/{photo}`` for kinds ``dynamic``
(with the clean background plate), ``static``, ``user`` and ``combined`` (union of the ``ok`` masks of the other
kinds; what the render node should use). Which mask is (re)computed when is :mod:`nodes.occlude.pipeline`.
"""

from __future__ import annotations

import sys

from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from nodes.occlude.pipeline import Config, OcclusionPipeline
from schemas import keys
from schemas.messages import (
    Annotation,
    BimModel,
    BimUpdate,
    OcclusionMask,
    Photo,
    Registration,
    SparseCloud,
    ViewpointGroup,
)

__all__ = ["SPEC", "Config", "OccludeNode", "main"]


class OccludeNode:
    """Wires the topics to an :class:`OcclusionPipeline` and publishes the masks it emits."""

    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.ctx = ctx
        self.pipeline = OcclusionPipeline(config, self._emit, site=ctx.site)

    def _emit(self, msg: OcclusionMask, mask: object) -> None:
        self.ctx.publish(keys.key(keys.OCCLUSION, site=self.ctx.site, kind=msg.kind, photo=msg.photo_id), msg)

    def on_photo(self, msg: Photo, key: str) -> None:
        self.pipeline.add_photo(msg)

    def on_viewpoints(self, msg: ViewpointGroup, key: str) -> None:
        self.pipeline.set_viewpoints(msg)

    def on_registration(self, msg: Registration, key: str) -> None:
        self.pipeline.add_registration(msg)

    def on_sparse(self, msg: SparseCloud, key: str) -> None:
        self.pipeline.set_sparse(msg)

    def on_bim_model(self, msg: BimModel, key: str) -> None:
        self.pipeline.set_model(msg)

    def on_bim_update(self, msg: BimUpdate, key: str) -> None:
        self.pipeline.apply_update(msg)

    def on_annotation(self, msg: Annotation, key: str) -> None:
        self.pipeline.add_annotation(msg)

    def on_idle(self) -> bool:
        return self.pipeline.idle()

    def close(self) -> None:
        self.pipeline.close()


SPEC = NodeSpec(
    name="occlude",
    description="dynamic (time-lapse median), static (sparse points vs BIM), user and combined occlusion masks",
    config_type=Config,
    factory=OccludeNode,
    inputs=(
        Input(keys.PHOTO, Photo, "on_photo"),
        Input(keys.REGISTRATION, Registration, "on_registration"),
        Input(keys.VIEWPOINTS, ViewpointGroup, "on_viewpoints"),
        Input(keys.SPARSE, SparseCloud, "on_sparse", latched=True),
        Input(keys.BIM_MODEL, BimModel, "on_bim_model", latched=True),
        Input(keys.BIM_UPDATE, BimUpdate, "on_bim_update"),
        Input(keys.ANNOTATION, Annotation, "on_annotation"),
    ),
    outputs=(Output(keys.OCCLUSION, OcclusionMask),),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
