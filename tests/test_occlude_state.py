"""Durable occlude state: a restarted node keeps its time-lapse stacks (the next frame gets a stack at once), and so
does a camera that moves to another worker when the worker count changes (hand-over through the state files)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_occlude_node import DAY_NS, SITE, _frames, _is, _photo

from constructaide.bimgeom import meshes_to_glb
from constructaide.partition import Partition
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


def test_a_camera_moved_to_another_worker_keeps_its_stack(scene, tmp_path: Path) -> None:
    cameras = ("cam-a", "cam-b", "cam-c", "cam-d")
    camera = next(c for c in cameras if Partition.parse("1/2", cameras).owns_camera(c))  # worker 1 of 2 holds it
    images, _ = _frames(scene, 3)
    photos = [_photo(img, camera, (i + 1) * DAY_NS) for i, img in enumerate(images)]
    model = BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    photo_key = keys.key(keys.PHOTO, site=SITE, camera=camera)
    parts = [Partition.parse(f"{i}/2", cameras) for i in range(2)]
    with LocalBus() as bus:
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        with (
            start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path, partition=parts[0]) as w0,
            start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path, partition=parts[1]) as w1,
        ):
            got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
            for p in photos[:2]:
                bus.publish(photo_key, p)
            got.wait(where=_is("dynamic", photos[1].photo_id, "ok"))
            assert w0.wait_idle(30) and w1.wait_idle(30)
            assert not w0.obj.photos and set(w1.obj.photos) == {p.photo_id for p in photos[:2]}
    # One worker now (a plain instance, its own state file): it takes the camera's frames from worker 1's file.
    with LocalBus() as bus:
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        with start_node(SPEC, Config(site=SITE), bus, state_dir=tmp_path) as node:
            assert set(node.obj.photos) == {p.photo_id for p in photos[:2]}
            assert set(node.obj.store.by_camera[camera]) == {p.photo_id for p in photos[:2]}
            got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
            bus.publish(photo_key, photos[2])
            dyn = got.wait(where=_is("dynamic", photos[2].photo_id))[0][1]
            assert dyn.status == "ok" and dyn.num_views >= 2  # its stack holds the frames the other worker had
