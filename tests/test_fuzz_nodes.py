"""Every node fed bad payloads of every message type it takes (Hypothesis, through the in-process bus).

Each payload wrong by construction is answered with a NodeError naming its key; the node stays up and the next
good Photo is processed without an error. Bounded examples keep the whole file under a minute
(bench/fuzz.py runs longer).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from fuzz_payloads import SITE, bad_payload, bad_upload, good_photo, templates
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from schemas import codec, keys
from schemas.messages import Message, NodeError

FIELDS = {"site": SITE, "camera": "cam-a", "photo": "p0", "kind": "dynamic", "mode": "state4d", "annotation": "a1"}


def node_setups(tmp: Path) -> dict[str, tuple[Any, Any]]:
    """name -> (spec, config) of every node with message inputs (the dashboard logs to rerun: not here)."""
    from nodes.ingest.node import SPEC as INGEST
    from nodes.ingest.node import Config as IngestConfig
    from nodes.occlude.node import SPEC as OCCLUDE
    from nodes.occlude.pipeline import Config as OccludeConfig
    from nodes.progress.node import SPEC as PROGRESS
    from nodes.progress.node import Config as ProgressConfig
    from nodes.recorder.node import SPEC as RECORDER
    from nodes.recorder.node import Config as RecorderConfig
    from nodes.register.node import SPEC as REGISTER
    from nodes.register.node import Config as RegisterConfig
    from nodes.render.node import SPEC as RENDER
    from nodes.render.node import Config as RenderConfig
    from nodes.workbench.node import SPEC as WORKBENCH
    from nodes.workbench.node import Config as WorkbenchConfig

    return {
        "ingest": (INGEST, IngestConfig(site=SITE, tz="UTC", use_receive_time=True)),
        "register": (REGISTER, RegisterConfig(site=SITE)),
        "occlude": (OCCLUDE, OccludeConfig(site=SITE)),
        "render": (RENDER, RenderConfig(site=SITE, modes=("state4d",))),
        "progress": (PROGRESS, ProgressConfig(site=SITE)),
        "recorder": (RECORDER, RecorderConfig(site=SITE, directory=str(tmp))),
        "workbench": (WORKBENCH, WorkbenchConfig(site=SITE, port=0)),
    }


@dataclass
class Harness:
    """A started node on a LocalBus, its NodeErrors, and the counts of what was tried."""

    name: str
    node: Any
    bus: LocalBus
    errors: Any
    tried: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    seq: int = 0

    def send(self, key: str, payload: bytes) -> list[NodeError]:
        before = len(self.errors.items)
        self.bus.publish(key, payload)
        assert self.node.wait_idle(120), f"{self.name} did not finish a message within 120 s"
        assert self.node._worker.is_alive(), f"{self.name}'s worker died"
        return [e for _, e in self.errors.items[before:]]

    def good(self) -> None:
        """A fresh good Photo (upload bytes for ingest): handled, no NodeError."""
        self.seq += 1
        photo = good_photo(f"good{self.seq}", seed=self.seq)
        if self.name == "ingest":
            key, payload = keys.key(keys.UPLOAD, site=SITE, camera="cam-a"), photo.data
        else:
            key, payload = keys.key(keys.PHOTO, site=SITE, camera="cam-a"), codec.encode(photo)
        done = self.node.processed
        errs = self.send(key, payload)
        assert errs == [], f"{self.name}: the good photo after bad input failed: {[e.reason for e in errs]}"
        assert self.node.processed == done + 1

    def bad(self, inp: Any, case: tuple[str, bytes, bool]) -> None:
        label, payload, must_refuse = case
        key = keys.key(inp.key, **{k: v for k, v in FIELDS.items() if "{" + k + "}" in inp.key})
        if "/**" in inp.key:  # the recorder takes everything: feed a photo key
            key = keys.key(keys.PHOTO, site=SITE, camera="cam-a")
        kind = f"{inp.type.__name__}/{label.split(':')[0]}"
        self.tried[kind] = self.tried.get(kind, 0) + 1
        errs = self.send(key, payload)
        if errs:
            self.refused[kind] = self.refused.get(kind, 0) + 1
        for e in errs:
            assert e.node == self.name and e.key == key and e.reason, e
        if must_refuse and not inp.raw:
            assert errs, f"{self.name}: {label} on {key} ({inp.type.__name__}) was not answered with a NodeError"
        if must_refuse and inp.raw and self.name == "ingest":
            assert errs, f"ingest: {label} upload was not answered with a NodeError"


def start(name: str, tmp: Path):
    spec, cfg = node_setups(tmp)[name]
    bus = LocalBus()
    errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
    return spec, bus, errors, start_node(spec, cfg, bus)


def inputs_of(spec: Any) -> list[Any]:
    return list(spec.inputs)


def case_strategy(spec: Any) -> st.SearchStrategy:
    """(input, case) pairs over every input of the node and every kind of bad payload of its type."""
    choices = []
    for inp in inputs_of(spec):
        if inp.raw and inp.type is Message:  # the recorder: bad payloads of every message type
            choices += [st.tuples(st.just(inp), bad_payload(t)) for t in templates()]
        elif inp.raw:
            choices.append(st.tuples(st.just(inp), bad_upload()))
        elif inp.type is Message:
            choices += [st.tuples(st.just(inp), bad_payload(t)) for t in templates()]
        else:
            choices.append(st.tuples(st.just(inp), bad_payload(inp.type)))
    return st.one_of(*choices)


EXAMPLES = int(os.environ.get("CONSTRUCTAIDE_FUZZ_EXAMPLES", "25"))  # bounded: the whole file < 60 s
DERANDOMIZE = "CONSTRUCTAIDE_FUZZ_EXAMPLES" not in os.environ  # the suite is reproducible; longer runs explore
NODES = ["ingest", "register", "occlude", "render", "progress", "recorder", "workbench"]


@pytest.mark.parametrize("name", NODES)
def test_node_survives_bad_input(name: str, tmp_path: Path) -> None:
    spec, bus, errors, ctx = start(name, tmp_path)
    t0 = time.monotonic()
    with bus, ctx as node:
        h = Harness(name, node, bus, errors)
        h.good()
        if name != "ingest":  # the photo clicks and masks refer to
            h.send(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), codec.encode(templates()[type(good_photo("p0"))]))

        @settings(
            max_examples=EXAMPLES,
            derandomize=DERANDOMIZE,
            deadline=None,
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        @given(case_strategy(spec))
        def feed(pair: tuple[Any, tuple[str, bytes, bool]]) -> None:
            inp, case = pair
            h.bad(inp, case)
            h.good()

        feed()
    assert sum(h.tried.values()) >= EXAMPLES
    print(f"{name}: {sum(h.tried.values())} tried, {sum(h.refused.values())} NodeErrors, {time.monotonic() - t0:.1f} s")


def test_register_refuses_clicks_off_the_photo(tmp_path: Path) -> None:
    """Found by the fuzz run: clicks beyond the photo's width were taken; now a NodeError, the photo kept."""
    import msgspec

    from schemas.messages import AnchorClicks

    spec, bus, errors, ctx = start("register", tmp_path)
    with bus, ctx as node:
        h = Harness("register", node, bus, errors)
        h.send(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), codec.encode(good_photo("p0")))
        clicks = templates()[AnchorClicks]
        pts = list(clicks.points)
        pts[2] = msgspec.structs.replace(pts[2], pixel_px=(64.0 + 500.0, pts[2].pixel_px[1]))
        off = msgspec.structs.replace(clicks, points=tuple(pts))
        key = keys.key(keys.ANCHORS, site=SITE, photo="p0")
        (err,) = h.send(key, codec.encode(off))
        assert "point(s) [2] off the 64x48 image" in err.reason and err.key == key
        assert "p0" in node.obj.inbox.pending
        h.good()


@pytest.mark.parametrize("name", ["register", "occlude", "render", "progress", "workbench"])
def test_photo_nodes_refuse_bodies_that_are_not_the_declared_image(name: str, tmp_path: Path) -> None:
    """Found by bench/fuzz.py: a garbage JPEG body reached register's handler. The runtime now decodes every Photo
    (constructaide.photos.photo_problem) before any handler: each bad body is a NodeError naming the photo id."""
    import msgspec
    from fuzz_payloads import bomb_png

    good = good_photo("p0")
    bodies = {
        "garbage": (b"\xff\xd8\xff\xe0" + bytes(200), "not an image"),
        "truncated": (good.data[: len(good.data) // 3], "truncated"),
        "not_an_image": (b"GIF89a" + bytes(40), "not an image (unrecognised bytes: starts 474946"),
        "bomb": (bomb_png(), "decompression bomb"),  # refused by schemas.validate from the header
        "wrong_size": (good_photo("x", seed=3).data, "decodes to 64x48 px, declares 65x48"),
    }
    spec, bus, errors, ctx = start(name, tmp_path)
    with bus, ctx as node:
        h = Harness(name, node, bus, errors)
        key = keys.key(keys.PHOTO, site=SITE, camera="cam-a")
        for label, (data, why) in bodies.items():
            pid = f"bad-{label}"
            bad = msgspec.structs.replace(good, photo_id=pid, data=data, width_px=65 if label == "wrong_size" else 64)
            done = node.processed
            (err,) = h.send(key, codec.encode(bad))
            assert err.key == key and f"photo {pid}" in err.reason and why in err.reason, (label, err.reason)
            assert node.processed == done, f"{label} reached the handler"
        h.good()


def test_photo_problem_accepts_png_and_undeclared_size() -> None:
    import cv2
    import msgspec
    import numpy as np

    from constructaide.photos import photo_problem

    png = cv2.imencode(".png", np.zeros((48, 64, 3), np.uint8))[1].tobytes()
    p = msgspec.structs.replace(good_photo("p"), data=png, media_type="image/png")
    assert photo_problem(p) is None
    assert photo_problem(msgspec.structs.replace(p, width_px=0, height_px=0)) is None
    assert "declares 48x64" in (photo_problem(msgspec.structs.replace(p, width_px=48, height_px=64)) or "")
    assert "limit 1000 px" in (photo_problem(good_photo("q"), max_pixels=1000) or "")
