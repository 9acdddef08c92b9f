"""Per-camera state stays bounded: many frames of one fixed camera leave the register, occlude and render nodes'
structures the same size (counted, not RSS)."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest
from occlude_scenes import dynamic_sequence
from test_register_stream_node import SITE, H, W, clicks_msg, make_photo
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide.runtime import NodeContext
from constructaide.runtime.local import LocalBus
from nodes.occlude.pipeline import Config as OccludeConfig
from nodes.occlude.pipeline import OcclusionPipeline
from nodes.register import state as register_state
from nodes.register.node import Config as RegisterConfig
from nodes.register.node import RegisterNode
from nodes.register.streaming import StreamConfig
from nodes.render.node import Config as RenderConfig
from nodes.render.node import RenderNode
from schemas import keys
from schemas.messages import OcclusionMask, Photo, Registration

MIN_NS = 60 * 10**9


def register_sizes(node: RegisterNode) -> dict[str, int]:
    r = node.registrar
    return {
        "poses": len(r.poses),
        "camera_frames": sum(len(v) for v in r.by_camera.values()),
        "viewpoint_photos": len(r.viewpoints),
        "map_images": len(r.recon.images),
        "fast_tracks": len(r.fast.tracks),
        "recent_photos": len(node.inbox.recent),
        "pending": len(node.inbox.pending),
    }


def _anchored_node(scene: PlaneScene, stream: StreamConfig):
    """A register node (in-process bus, 4 recent photos kept) whose camera cam-a's first frame is anchored:
    (node, registrations collector, that frame)."""
    intr, T = mast_camera(W, H)
    bus = LocalBus()
    regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
    node = RegisterNode(
        RegisterConfig(site=SITE, keep_recent_photos=4, stream=stream), NodeContext(bus, SITE, "register")
    )
    first = make_photo(encode_jpeg(scene.render(intr, T)), "cam-a", 0)
    px, pts = anchor_clicks(intr, T, noise_px=0.2)
    node.on_anchors(clicks_msg(first.photo_id, px, pts), "")
    node.on_photo(first, "")
    return node, regs, first


@pytest.mark.slow  # ~15-30 s on the shared 2-core machine (anchor solve, SIFT of the first frame)
def test_register_state_is_flat_over_many_frames_of_one_camera() -> None:
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(3)
    node, regs, first = _anchored_node(scene, StreamConfig(max_frames_per_camera=4, key_frame_every_secs=None))
    sizes = []
    for k in range(1, 15):
        i, t = jitter(T, intr, rng, 0.2, 0.004)
        node.on_photo(make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k * 60), "")
        if k in (7, 14):
            sizes.append(register_sizes(node))
    got = [r for _k, r in regs.items]
    assert len(got) == 15 and all(r.status != "failed" for r in got), [r.message for r in got if r.status == "failed"]
    assert sum(r.method == "fastpath" for r in got) >= 12
    assert sizes[0] == sizes[1], sizes
    assert sizes[1]["poses"] <= 5 and sizes[1]["recent_photos"] == 4 and sizes[1]["map_images"] == 1
    assert first.photo_id in node.registrar.poses  # the anchor frame is in the map: kept


@pytest.mark.slow  # ~10-20 s on the shared 2-core machine (SIFT of every key frame)
def test_register_map_keeps_a_bounded_number_of_key_frames_per_camera() -> None:
    """A camera whose frames keep joining the map as key frames (the site changes) retires its oldest ones: the
    map's images, features and pairs stay flat, the anchor stays, every frame still registers."""
    scene = PlaneScene(1)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(5)
    stream = StreamConfig(max_frames_per_camera=4, key_frame_every_secs=90.0, max_map_images_per_camera=3)
    node, regs, first = _anchored_node(scene, stream)
    held = []
    saved: dict[str, tuple[int, bool]] = {}
    for k in range(1, 17):
        i, t = jitter(T, intr, rng, 0.2, 0.004)
        node.on_photo(make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k * 60), "")
        if k in (8, 16):
            r = node.registrar.recon
            held.append((len(r.images), len(r.pairs), sum(im.features.descriptors.nbytes for im in r.images)))
            blobs = register_state.dump_map(node, saved)  # the durable state forgets retired images' features
            assert set(saved) == {im.name for im in r.images}
            assert k == 8 or any(v == b"" for n, v in blobs.items() if n.startswith("feat/"))
    got = [r for _k, r in regs.items]
    assert len(got) == 17 and all(r.status != "failed" for r in got), [r.message for r in got if r.status == "failed"]
    assert sum("joined the map as a key frame" in r.message for r in got) >= 6
    assert held[0][0] == held[1][0] == 3, held  # the anchor and the two newest key frames
    assert held[1][1] <= 3 and held[1][2] <= 1.2 * held[0][2], held
    assert first.photo_id in node.registrar.recon  # the anchor is never retired
    assert got[-1].photo_id in node.registrar.recon


def _photo(img: np.ndarray, camera: str, t_ns: int) -> Photo:
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    return Photo(
        site=SITE, photo_id=hashlib.sha256(data).hexdigest()[:16], camera_id=camera, capture_time_ns=t_ns, data=data
    )


def occlude_sizes(p: OcclusionPipeline) -> dict[str, int]:
    out = {
        "photos": len(p.photos),
        "stack_frames": sum(len(v) for v in p.store.by_camera.values()),
        "masks": len(p.masks),
    }
    for name in ("dynamic_stack_ids", "dynamic_had_later", "dynamic_plate", "model_region", "dynamic_colour_seen"):
        out[name] = len(getattr(p, name))
    return out


def test_occlude_state_is_flat_over_many_frames_of_one_camera() -> None:
    emitted: list[OcclusionMask] = []
    pipe = OcclusionPipeline(
        OccludeConfig(site=SITE, max_photos_per_camera=5, max_views=4), lambda m, _mask: emitted.append(m), site=SITE
    )
    frames = dynamic_sequence(2, 18, h=135, w=240)
    sizes = []
    for k, fr in enumerate(frames):
        pipe.add_photo(_photo(fr.image, "cam-a", k * MIN_NS))
        while pipe.idle():
            pass
        if k in (8, 17):
            sizes.append(occlude_sizes(pipe))
    assert sizes[0] == sizes[1], sizes
    assert sizes[1]["photos"] == 5 and sizes[1]["stack_frames"] == 5
    dyn = [m for m in emitted if m.kind == "dynamic"]
    assert len({m.photo_id for m in dyn}) == len(frames)  # every frame still got its mask


def test_render_state_is_bounded_by_its_photo_cache() -> None:
    bus = LocalBus()
    node = RenderNode(RenderConfig(site=SITE, photo_cache=4), NodeContext(bus, SITE, "render"))
    for k in range(30):
        data = f"frame {k}".encode()
        pid = hashlib.sha256(data).hexdigest()[:16]
        node.on_photo(Photo(site=SITE, photo_id=pid, camera_id="cam-a", capture_time_ns=k * MIN_NS, data=data), "")
        node.on_registration(Registration(site=SITE, photo_id=pid, camera_id="cam-a", status="auto"), "")
        node.on_occlusion(OcclusionMask(site=SITE, photo_id=pid, kind="combined", status="ok"), "")
        node.rendered.add(pid)  # as if drawn (no model here: nothing is drawn)
        node.dirty.pop(pid, None)
    # registrations and masks of photos that arrive without their photo (it left the cache) stay bounded too
    for k in range(30):
        node.on_registration(Registration(site=SITE, photo_id=f"gone{k}", camera_id="cam-a", status="auto"), "")
    assert len(node.photos) == 4
    assert len(node.masks) <= 8 and len(node.registrations) <= 8 and len(node.rendered) <= 4, (
        len(node.masks),
        len(node.registrations),
        len(node.rendered),
    )


def test_workbench_state_keeps_a_bounded_number_of_photos() -> None:
    from nodes.workbench.state import SiteState

    st = SiteState(max_photos=20)
    for k in range(200):
        pid = f"p{k:04d}"
        st.apply(Photo(site=SITE, photo_id=pid, camera_id="cam-a", capture_time_ns=k * MIN_NS, data=b"x"))
        st.apply(Registration(site=SITE, photo_id=pid, camera_id="cam-a", status="auto"))
        st.apply(OcclusionMask(site=SITE, photo_id=pid, kind="combined", status="ok"))
    assert 20 <= len(st.photos) <= 22 and "p0199" in st.photos and "p0000" not in st.photos
    assert len(st.registrations) <= 44 and len(st.masks) <= 44
    assert all(p in st.photos for p in st.registrations)
