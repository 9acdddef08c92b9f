"""Durable occlude state: a restarted node keeps its time-lapse stacks (the next frame gets a stack at once)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_occlude_node import DAY_NS, SITE, _frames, _is, _photo

from constructaide.bimgeom import meshes_to_glb
from constructaide.runtime import start_node
from constructaide.runtime.history import Ledger
from constructaide.runtime.local import LocalBus
from nodes.occlude.node import SPEC, Config
from schemas import keys
from schemas.messages import BimModel


@pytest.fixture(scope="module")
def scene():
    from occlude_scenes import static_scene

    return static_scene(5)


def test_restart_keeps_the_stacks(scene, tmp_path: Path) -> None:
    images, _ = _frames(scene, 3)
    photos = [_photo(img, "cam-a", (i + 1) * DAY_NS) for i, img in enumerate(images)]
    model = BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    photo_key = keys.key(keys.PHOTO, site=SITE, camera="cam-a")
    with LocalBus() as bus:
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        with start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path) as node:
            got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
            for p in photos[:2]:
                bus.publish(photo_key, p)
            got.wait(where=_is("dynamic", photos[1].photo_id, "ok"))
            assert node.wait_idle(30)
            colour_before = node.obj.colour.__dict__.copy()
    led = Ledger(tmp_path / f"{SITE}-occlude.sqlite")
    assert set(led.load_state()) == {"pipeline"} and led.handled_count() >= 2  # the last snapshot at the stop
    led.close()
    with LocalBus() as bus:  # a new process: nothing to replay, the model is latched again
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        with start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path) as node:
            assert set(node.obj.photos) == {p.photo_id for p in photos[:2]}
            assert node.obj.renderer is not None
            assert node.obj.colour.__dict__.keys() == colour_before.keys()
            got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
            bus.publish(photo_key, photos[2])
            dyn = got.wait(where=_is("dynamic", photos[2].photo_id))[0][1]
            assert dyn.status == "ok" and dyn.num_views >= 2  # its stack holds the frames from before the restart
