"""A minimal node for runtime tests: answers each Photo with a failed Registration echoing its id.

Run as a script (``python tests/echo_node.py --site S --hub-port P``) to get a real node process.
"""

from __future__ import annotations

import sys

import msgspec

from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from schemas import keys
from schemas.messages import Photo, Registration


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    reply_message: str = "echo"


class EchoNode:
    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx

    def on_photo(self, msg: Photo, key: str) -> None:
        if msg.photo_id == "raise":
            raise ValueError("asked to raise")
        reg = Registration(
            site=msg.site,
            photo_id=msg.photo_id,
            camera_id=msg.camera_id,
            status="failed",
            message=self.config.reply_message,
        )
        self.ctx.publish(keys.key(keys.REGISTRATION, site=self.ctx.site, camera=msg.camera_id, photo=msg.photo_id), reg)


SPEC = NodeSpec(
    name="echo",
    description="test node: Photo in, Registration out",
    config_type=Config,
    factory=EchoNode,
    inputs=(Input(keys.PHOTO, Photo, "on_photo", check_images=False),),  # opaque bytes
    outputs=(Output(keys.REGISTRATION, Registration),),
)

if __name__ == "__main__":
    sys.exit(run_node_cli(SPEC))
