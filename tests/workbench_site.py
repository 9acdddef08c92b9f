"""A synthetic site run through the real nodes in-process (LocalBus: register, render and the workbench), for the
workbench's browser tests and its benchmark. The site's anchors.json clicks are published as a user's clicks
would be; the phone photos the register node cannot place stay as NeedsAnchor requests for the page."""

from __future__ import annotations

import contextlib
import json
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from constructaide.bim.ifc import load_site_model
from constructaide.runtime import Collector, start_node
from constructaide.runtime.local import LocalBus
from nodes.ingest.photos import photo_from_file
from nodes.ingest.revisions import to_bim_model
from nodes.progress.node import SPEC as PROGRESS
from nodes.progress.node import Config as ProgressConfig
from nodes.register.node import SPEC as REGISTER
from nodes.register.node import Config as RegisterConfig
from nodes.render.node import SPEC as RENDER
from nodes.render.node import Config as RenderConfig
from nodes.workbench.node import SPEC as WORKBENCH
from nodes.workbench.node import Config as WorkbenchConfig
from schemas import keys
from schemas.messages import AnchorClicks, AnchorPoint, BimModel, Photo

SITE = "wb"
MODES = ("state4d", "progress", "future", "edges")


@dataclass
class RunningSite:
    site_dir: Path
    url: str
    bus: LocalBus
    model: BimModel
    photos: dict[str, Photo]  # by path relative to photos/
    rel_of: dict[str, str]  # photo_id -> path relative to photos/
    registrations: Collector
    workbench: object  # the WorkbenchNode


def site_photos(site_dir: Path) -> tuple[dict[str, Photo], str]:
    doc = tomllib.loads((site_dir / "site.toml").read_text())
    tz = doc["site"]["tz"]
    photos = {}
    for f in sorted((site_dir / "photos").rglob("*.jpg")):
        rel = f.relative_to(site_dir / "photos").as_posix()
        cam = rel.split("/")[0]
        photos[rel] = photo_from_file(f, camera_id=None if cam == keys.PHONE else cam, site=SITE, tz=tz)
    return photos, tz


@contextlib.contextmanager
def running_site(
    site_dir: Path, modes: tuple[str, ...] = MODES, timeout: float = 900.0, progress: bool = False
) -> Iterator[RunningSite]:
    """The site's model, anchors.json clicks and photos through register + render (and, with ``progress``, the
    progress node reading each registered photo without waiting for occlusion masks), with the workbench (live, any
    free port) beside them; yields once the nodes are idle."""
    photos, tz = site_photos(site_dir)
    model = to_bim_model(load_site_model([site_dir / "model" / "building.ifc"], tz=tz), SITE, "r1", 0.0)
    with (
        LocalBus() as bus,
        start_node(WORKBENCH, WorkbenchConfig(site=SITE, port=0), bus) as wb,
        start_node(REGISTER, RegisterConfig(site=SITE), bus) as reg,
        start_node(RENDER, RenderConfig(site=SITE, modes=modes), bus) as ren,
        contextlib.ExitStack() as more,
    ):
        prog = (
            more.enter_context(start_node(PROGRESS, ProgressConfig(site=SITE, require_mask=False), bus))
            if progress
            else None
        )
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        for a in json.loads((site_dir / "anchors.json").read_text())["anchors"]:
            p = photos[a["image"]]
            pts = tuple(
                AnchorPoint(pixel_px=tuple(q["pixel"]), point_in_world_m=tuple(q["world"])) for q in a["points"]
            )
            bus.publish(
                keys.key(keys.ANCHORS, site=SITE, photo=p.photo_id),
                AnchorClicks(site=SITE, photo_id=p.photo_id, points=pts, image_name=a["image"]),
            )
        for rel in sorted(photos, key=lambda r: (photos[r].capture_time_ns, r)):
            p = photos[rel]
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera=p.camera_id), p)
        assert reg.wait_idle(timeout) and ren.wait_idle(timeout)
        assert (prog is None or prog.wait_idle(timeout)) and wb.wait_idle(60)
        yield RunningSite(
            site_dir=site_dir,
            url=wb.obj.url,
            bus=bus,
            model=model,
            photos=photos,
            rel_of={p.photo_id: rel for rel, p in photos.items()},
            registrations=regs,
            workbench=wb.obj,
        )
