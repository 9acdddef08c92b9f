"""Workbench node: the browser page where people anchor photos, select and annotate elements and move through time.

Subscribes to everything the page shows (model, photos, registrations, anchor requests, overlays, masks, viewpoint
groups, annotations, the progress node's readings and fused progress) and serves the page and its JSON API over HTTP
(:mod:`nodes.workbench.api`). What people make
goes back on the bus: anchor clicks (``anchors/{photo}``) and annotations (``annotation/{id}``), unless ``live`` is
off (review: answers are solved and shown, nothing is published). Binding a non-loopback ``host`` needs a
``token`` (one is generated and printed when none is configured).
"""

from __future__ import annotations

import secrets

import msgspec

from constructaide.errors import UserError
from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from nodes.workbench.api import HttpServer, is_loopback, make_app
from nodes.workbench.service import Workbench
from schemas import keys
from schemas import messages as m


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    host: str = "127.0.0.1"
    """Address to serve on; anything but loopback requires ``token``."""
    port: int = 8770
    """TCP port (0: any free port; the URL is logged)."""
    token: str = ""
    """Access token (Authorization: Bearer TOKEN, or ?token=TOKEN in the page URL). Empty on a non-loopback host:
    a random one is generated and logged."""
    live: bool = True
    """Publish anchor clicks and annotations on the bus (off: review only)."""
    render_width_px: int = 960
    """Width of the server's element-ID renders (selection regions, annotation transfer, peeks)."""


def access_token(config: Config) -> str:
    """The token to require: the configured one; a generated one on a non-loopback host without one."""
    if config.token:
        return config.token
    return "" if is_loopback(config.host) else secrets.token_urlsafe(16)


class WorkbenchNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.ctx = ctx
        self.workbench = Workbench(
            ctx.site, publish=ctx.publish if config.live else None, render_width_px=config.render_width_px
        )
        self.token = access_token(config)
        try:
            self.server = HttpServer(make_app(self.workbench, self.token), config.host, config.port).start()
        except OSError as e:
            self.workbench.close()
            raise UserError(f"workbench: {e}") from None
        self.url = self.server.url + (f"?token={self.token}" if self.token else "")
        ctx.log.info("workbench at %s (%s)", self.url, "live" if config.live else "review only")

    def on_message(self, msg: m.Message, key: str) -> None:
        self.workbench.apply(msg)

    # One handler name per input (the runtime names a failing input's topic by its handler).
    on_model = on_update = on_photo = on_registration = on_needs_anchor = on_message
    on_overlay = on_occlusion = on_viewpoints = on_annotation = on_evidence = on_progress = on_message

    def close(self) -> None:
        self.server.stop()
        self.workbench.close()


SPEC = NodeSpec(
    name="workbench",
    description="Browser workbench: anchor photos, select and annotate elements, 4D navigation (HTTP + JSON API)",
    config_type=Config,
    factory=WorkbenchNode,
    inputs=(
        Input(keys.BIM_MODEL, m.BimModel, "on_model", latched=True),
        Input(keys.BIM_UPDATE, m.BimUpdate, "on_update"),
        Input(keys.PHOTO, m.Photo, "on_photo"),
        Input(keys.REGISTRATION, m.Registration, "on_registration"),
        Input(keys.NEEDS_ANCHOR, m.NeedsAnchor, "on_needs_anchor"),
        Input(keys.OVERLAY, m.Overlay, "on_overlay"),
        Input(keys.OCCLUSION, m.OcclusionMask, "on_occlusion"),
        Input(keys.VIEWPOINTS, m.ViewpointGroup, "on_viewpoints"),
        Input(keys.ANNOTATION, m.Annotation, "on_annotation"),
        Input(keys.PHOTO_EVIDENCE, m.PhotoEvidence, "on_evidence"),
        Input(keys.PROGRESS, m.ProgressUpdate, "on_progress"),
    ),
    outputs=(Output(keys.ANCHORS, m.AnchorClicks), Output(keys.ANNOTATION, m.Annotation)),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
