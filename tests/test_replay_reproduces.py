"""Replaying a recording through the nodes reproduces the same outputs.

Run 1 feeds the small synthetic site's inputs (BIM, anchor clicks, one camera's frames) to the
register node while the recorder writes MCAP. Run 2 replays only the recorded *inputs* into a fresh
register node; its Registrations must equal the recorded ones.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np

from constructaide.bim.ifc import load_site_model
from constructaide.photos import photo_from_file
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.ingest.revisions import to_bim_model
from nodes.recorder import node as recorder_node
from nodes.recorder.mcapio import iter_recording, replay
from nodes.register import node as register_node
from schemas import codec, keys
from schemas.messages import AnchorClicks, AnchorPoint

SITE = "replay"
INPUT_TYPES = ("constructaide.BimModel", "constructaide.AnchorClicks", "constructaide.Photo")


def _inputs(site_dir: Path):
    doc = tomllib.loads((site_dir / "site.toml").read_text())
    tz = doc["site"]["tz"]
    model = to_bim_model(load_site_model([site_dir / doc["paths"]["ifc"]], tz=tz), SITE, "r1")
    photos_dir = site_dir / doc["paths"]["photos"]
    frames = sorted((photos_dir / "cam-north").glob("*.jpg"))[:4]
    photos = {f"cam-north/{f.name}": photo_from_file(f, camera_id="cam-north", site=SITE, tz=tz) for f in frames}
    anchors = []
    for a in json.loads((site_dir / doc["paths"]["anchors"]).read_text())["anchors"]:
        if a["image"] in photos:
            pts = tuple(
                AnchorPoint(pixel_px=tuple(p["pixel"]), point_in_world_m=tuple(p["world"])) for p in a["points"]
            )
            anchors.append(AnchorClicks(site=SITE, photo_id=photos[a["image"]].photo_id, points=pts))
    assert anchors, "the small site has an anchor on cam-north's first frame"
    return model, anchors, list(photos.values())


def _registrations(items):
    return {m.photo_id: m for _, m in items}


def test_replay_reproduces_registrations(small_site: Path, tmp_path: Path) -> None:
    model, anchors, photos = _inputs(small_site)
    mcap = tmp_path / "run1.mcap"
    with LocalBus() as bus:
        with (
            start_node(recorder_node.SPEC, recorder_node.Config(site=SITE, path=str(mcap)), bus),
            start_node(register_node.SPEC, register_node.Config(site=SITE), bus) as reg_node,
        ):
            regs1 = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
            bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
            for a in anchors:
                bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=a.photo_id), a)
            for p in photos:
                bus.publish(keys.key(keys.PHOTO, site=SITE, camera=p.camera_id), p)
            regs1.wait(len(photos), timeout=300, where=lambda k, m: True)
            assert reg_node.wait_idle(120)
    first = _registrations(regs1.items)
    assert len(first) == len(photos)
    assert sum(m.status != "failed" for m in first.values()) >= len(photos) - 1

    recorded = [(k, codec.decode(p)) for k, _, p, _ in iter_recording(mcap)]
    recorded_regs = _registrations([(k, m) for k, m in recorded if k.startswith(f"constructaide/{SITE}/registration/")])
    assert recorded_regs == first  # the recorder kept every output

    with LocalBus() as bus2, start_node(register_node.SPEC, register_node.Config(site=SITE), bus2) as node2:
        regs2 = bus2.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        n = replay(
            mcap, lambda k, p: bus2.publish(k, p, latched=k.endswith("/bim/model")), rate=None, types=INPUT_TYPES
        )
        assert n == 1 + len(anchors) + len(photos)
        regs2.wait(len(photos), timeout=300)
        assert node2.wait_idle(120)
    second = _registrations(regs2.items)
    assert second.keys() == first.keys()
    for pid, a in first.items():
        b = second[pid]
        assert (a.status, a.method) == (b.status, b.method)
        if a.status != "failed":
            np.testing.assert_allclose(a.world_from_camera, b.world_from_camera, atol=1e-6)
            assert a.intrinsics == b.intrinsics or abs(a.intrinsics.f_px - b.intrinsics.f_px) < 1e-6
