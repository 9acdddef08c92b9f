"""Bad payloads of every message type for the fuzz test and bench/fuzz.py (Hypothesis strategies).

A case is ``(label, payload, must_refuse)``: ``must_refuse`` cases are wrong by construction (truncated, wrong
type, NaN / infinite numbers, negative or gigantic sizes, corrupt or bomb images, broken GLB, schedule cycles,
end before start, clicks off the image) and must be answered with a NodeError; the others (random bit flips)
may happen to be valid and must only never take the node down.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

import cv2
import msgspec
import numpy as np
from hypothesis import strategies as st

from schemas import codec
from schemas import messages as m

SITE = "fz"
W, H = 64, 48
T0 = 1_750_000_000_000_000_000
DAY = 86_400 * 10**9


def _jpeg(seed: int) -> bytes:
    img = np.random.default_rng(seed).integers(0, 255, (H, W, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def good_photo(photo_id: str, seed: int = 0) -> m.Photo:
    return m.Photo(
        site=SITE, photo_id=photo_id, camera_id="cam-a", capture_time_ns=T0 + seed, data=_jpeg(seed), width_px=W,
        height_px=H, focal_px=60.0,
    )  # fmt: skip


def _glb() -> bytes:
    import trimesh

    from constructaide.bimgeom import meshes_to_glb

    box = trimesh.creation.box(extents=(2, 2, 3))
    box.apply_translation((0.0, 0.0, 1.5))
    return meshes_to_glb({"A": (np.asarray(box.vertices), np.asarray(box.faces))})


def templates() -> dict[type, m.Message]:
    """One valid message of every type (small)."""
    intr = m.Intrinsics(width_px=W, height_px=H, f_px=60.0, cx_px=W / 2, cy_px=H / 2)
    pose = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, -10.0, 0.0, -1.0, 0.0, 1.5, 0.0, 0.0, 0.0, 1.0)
    el = m.BimElement(
        global_id="A", ifc_class="IfcWall", geometry_ref="A", bbox_min_m=(-1, -1, 0), bbox_max_m=(1, 1, 3)
    )
    tasks = (
        m.ScheduleTask(task_id="t1", name="t1", planned_start_ns=T0 - 3 * DAY, planned_finish_ns=T0 - DAY,
                       element_ids=("A",)),
        m.ScheduleTask(task_id="t2", name="t2", planned_start_ns=T0 - DAY, planned_finish_ns=T0 + DAY,
                       predecessor_ids=("t1",)),
    )  # fmt: skip
    pts = tuple(
        m.AnchorPoint(pixel_px=(float(5 + 9 * i), float(4 + 7 * i)), point_in_world_m=(i * 0.3, 0.0, 0.5 * i))
        for i in range(6)
    )
    mask = _png(np.zeros((H, W), np.uint8))
    xyz = np.zeros((2, 3), np.float32)
    ev = m.ElementEvidence(global_id="A", state="built", confidence=0.9, visible_px=100)
    return {
        m.Photo: good_photo("p0"),
        m.BimModel: m.BimModel(site=SITE, revision="r1", elements=(el,), tasks=tasks, geometry_glb=_glb()),
        m.BimUpdate: m.BimUpdate(site=SITE, base_revision="r1", revision="r2", changed=(el,), tasks=tasks),
        m.AnchorClicks: m.AnchorClicks(site=SITE, photo_id="p0", points=pts),
        m.Registration: m.Registration(
            site=SITE,
            photo_id="p0",
            camera_id="cam-a",
            capture_time_ns=T0,
            intrinsics=intr,
            world_from_camera=pose,
            status="anchor",
        ),  # fmt: skip
        m.SparseCloud: m.SparseCloud(
            site=SITE,
            revision=1,
            photo_ids=("p0",),
            points_xyz_f32=xyz.tobytes(),
            colors_rgb_u8=bytes(6),
            obs_point_i32=np.int32([0, 1]).tobytes(),
            obs_photo_i32=np.int32([0, 0]).tobytes(),
            obs_pixel_f32=np.float32([[1, 2], [3, 4]]).tobytes(),
        ),  # fmt: skip
        m.ViewpointGroup: m.ViewpointGroup(
            site=SITE,
            photo_id="p0",
            neighbours=(
                m.ViewpointNeighbour(
                    photo_id="p1", this_from_neighbour=(1, 0, 0, 0, 1, 0, 0, 0, 1), inlier_ratio=0.8, num_matches=50
                ),
            ),
        ),  # fmt: skip
        m.NeedsAnchor: m.NeedsAnchor(site=SITE, photo_id="p0", reason="no matches"),
        m.OcclusionMask: m.OcclusionMask(site=SITE, photo_id="p0", kind="dynamic", mask_png=mask, num_views=3),
        m.Overlay: m.Overlay(
            site=SITE, photo_id="p0", mode="state4d", at_ns=T0, image_png=_png(np.zeros((H, W, 4), np.uint8))
        ),  # fmt: skip
        m.Annotation: m.Annotation(
            site=SITE,
            annotation_id="a1",
            kind="note",
            photo_id="p0",
            text="hi",
            polygon_px=((1.0, 1.0), (10.0, 1.0), (10.0, 10.0)),
        ),  # fmt: skip
        m.NodeError: m.NodeError(site=SITE, node="x", topic="y", reason="z"),
        m.PhotoEvidence: m.PhotoEvidence(
            site=SITE,
            photo_id="p0",
            camera_id="cam-a",
            capture_time_ns=T0,
            elements=(ev,),
            working_width_px=W,
            working_height_px=H,
        ),  # fmt: skip
        m.ProgressUpdate: m.ProgressUpdate(
            site=SITE,
            as_of_ns=T0,
            elements=(m.ElementProgress(global_id="A", state="built"),),
            tasks=(m.TaskProgress(task_id="t1"),),
            storeys=(m.StoreyProgress(storey="L0"),),
        ),  # fmt: skip
    }


# ---------------------------------------------------------------------- mutations of the builtins tree


def _paths(tree: Any, want: Any, prefix: tuple = ()) -> list[tuple]:
    """Paths (tuples of keys / indices) to the leaves for which ``want(leaf, name)`` holds."""
    out: list[tuple] = []
    if isinstance(tree, dict):
        for k, v in tree.items():
            if k != "type":
                out += _paths(v, want, (*prefix, k))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            out += _paths(v, want, (*prefix, i))
    elif want(tree, prefix[-1] if prefix and isinstance(prefix[-1], str) else ""):
        out.append(prefix)
    return out


def _set(tree: Any, path: tuple, value: Any) -> Any:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(tree, dict):
        return {**tree, head: _set(tree[head], rest, value)}
    out = list(tree)
    out[head] = _set(tree[head], rest, value)
    return out


def _encode(tree: Any) -> bytes:
    return msgspec.msgpack.encode(tree)


def _bomb_png(side: int) -> bytes:
    """A PNG declaring side x side grey pixels whose zero rows compress to almost nothing (a decompression bomb)."""
    import struct

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    raw = zlib.compressobj(9)
    row = bytes(side + 1)
    body = b"".join(raw.compress(row) for _ in range(side)) + raw.flush()
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body) + chunk(b"IEND", b"")


_BOMB: dict[int, bytes] = {}


def bomb_png(side: int = 16384) -> bytes:
    if side not in _BOMB:
        _BOMB[side] = _bomb_png(side)
    return _BOMB[side]


def _image_fields(tree: dict) -> list[str]:
    return [k for k in ("data", "mask_png", "background_jpeg", "image_png") if k in tree and tree[k]]


@st.composite
def bad_payload(draw: st.DrawFn, msg_type: type) -> tuple[str, bytes, bool]:
    """One bad payload for ``msg_type``: (label, bytes, must_refuse)."""
    tmpl = templates()[msg_type]
    good = codec.encode(tmpl)
    tree = msgspec.to_builtins(tmpl)  # bytes stay bytes
    kinds = ["truncated", "random", "bitflip", "wrong_type", "missing_field", "other_type"]
    floats = _paths(tree, lambda v, n: isinstance(v, float))
    sizes = _paths(tree, lambda v, n: isinstance(v, int) and not isinstance(v, bool)
                   and (n.endswith("_px") or n.startswith("num_")))  # fmt: skip
    kinds += ["nonfinite"] * bool(floats) + ["negative", "gigantic"] * bool(sizes)
    kinds += ["corrupt_image", "bomb_image"] * bool(_image_fields(tree))
    if msg_type in (m.BimModel, m.BimUpdate):
        kinds += ["schedule_cycle", "end_before_start", "broken_glb", "bbox_inside_out"]
    if msg_type is m.AnchorClicks:
        kinds += ["click_off_image"]
    if msg_type is m.Registration:
        kinds += ["not_a_rotation", "pose_wrong_length"]
    if msg_type is m.SparseCloud:
        kinds += ["sparse_ragged"]
    kind = draw(st.sampled_from(kinds))
    if kind == "truncated":
        return kind, good[: draw(st.integers(0, len(good) - 1))], True
    if kind == "random":
        return kind, draw(st.binary(max_size=256)), True
    if kind == "other_type":
        other = draw(st.sampled_from([t for t in templates() if t is not msg_type]))
        return f"{kind}:{other.__name__}", codec.encode(templates()[other]), True
    if kind == "bitflip":
        buf = bytearray(good)
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, len(buf) - 1))
            buf[i] ^= 1 << draw(st.integers(0, 7))
        return kind, bytes(buf), False
    if kind == "wrong_type":
        fields = [k for k in tree if k not in ("type", "site")]
        f = draw(st.sampled_from(fields))
        wrong = draw(st.sampled_from([{"x": 1}, [1, "a"], "text", 12345678901, -1.5, True]))
        if isinstance(tree[f], bool) or (type(wrong) is type(tree[f])) or (tree[f] is None):
            wrong = {"x": [1]}
        return f"{kind}:{f}", _encode({**tree, f: wrong}), True
    if kind == "missing_field":
        required = [f for f in msg_type.__struct_fields__ if f in _required(msg_type)]
        f = draw(st.sampled_from(required))
        return f"{kind}:{f}", _encode({k: v for k, v in tree.items() if k != f}), True
    if kind == "nonfinite":
        p = draw(st.sampled_from(floats))
        return (
            f"{kind}:{_name(p)}",
            _encode(_set(tree, p, draw(st.sampled_from([math.nan, math.inf, -math.inf])))),
            True,
        )
    if kind in ("negative", "gigantic"):
        p = draw(st.sampled_from(sizes))
        if kind == "gigantic":
            p = draw(st.sampled_from([q for q in sizes if _name(q) in ("width_px", "height_px")] or [None]))
            if p is None:
                kind, p = "negative", draw(st.sampled_from(sizes))
        v = -draw(st.integers(1, 10**6)) if kind == "negative" else draw(st.integers(10**6, 10**9))
        return f"{kind}:{_name(p)}", _encode(_set(tree, p, v)), True
    if kind == "corrupt_image":
        f = draw(st.sampled_from(_image_fields(tree)))
        data = tree[f]
        how = draw(st.sampled_from(["truncated", "garbage", "header_only"]))
        bad = {"truncated": data[: max(2, len(data) // 3)], "garbage": b"\xff\xd8\xff\xe0" + bytes(200),
               "header_only": data[:20]}[how]  # fmt: skip
        return f"{kind}:{f}:{how}", _encode({**tree, f: bad}), True
    if kind == "bomb_image":
        f = draw(st.sampled_from(_image_fields(tree)))
        return f"{kind}:{f}", _encode({**tree, f: bomb_png()}), True
    if kind == "schedule_cycle":
        tasks = [dict(t) for t in tree["tasks"]]
        tasks[0]["predecessor_ids"] = ["t2"]
        return kind, _encode({**tree, "tasks": tasks}), True
    if kind == "end_before_start":
        tasks = [dict(t) for t in tree["tasks"]]
        i = draw(st.integers(0, len(tasks) - 1))
        tasks[i]["planned_finish_ns"] = tasks[i]["planned_start_ns"] - draw(st.integers(1, 10 * DAY))
        return kind, _encode({**tree, "tasks": tasks}), True
    if kind == "broken_glb":
        how = draw(st.sampled_from(["garbage", "truncated", "magic_only"]))
        glb = tree["geometry_glb"] or _glb()
        bad = {"garbage": draw(st.binary(min_size=1, max_size=64)), "truncated": glb[: len(glb) // 2],
               "magic_only": b"glTF" + bytes(8)}[how]  # fmt: skip
        return f"{kind}:{how}", _encode({**tree, "geometry_glb": bad}), True
    if kind == "bbox_inside_out":
        els = tree.get("elements") or tree.get("changed")
        key = "elements" if "elements" in tree and tree["elements"] else "changed"
        el = {**els[0], "bbox_min_m": [5.0, 5.0, 5.0], "bbox_max_m": [0.0, 0.0, 0.0]}
        return kind, _encode({**tree, key: [el]}), True
    if kind == "click_off_image":
        pts = [dict(p) for p in tree["points"]]
        i = draw(st.integers(0, len(pts) - 1))
        x = draw(st.sampled_from([W + draw(st.integers(1, 10**5)), -draw(st.integers(1, 10**5))]))
        pts[i]["pixel_px"] = [float(x), pts[i]["pixel_px"][1]]
        return kind, _encode({**tree, "points": pts}), True
    if kind == "not_a_rotation":
        pose = list(tree["world_from_camera"])
        pose[draw(st.sampled_from([0, 1, 2, 4, 5, 6, 8, 9, 10]))] += draw(st.sampled_from([0.5, 3.0, -2.0]))
        return kind, _encode({**tree, "world_from_camera": pose}), True
    if kind == "pose_wrong_length":
        n = draw(st.sampled_from([1, 9, 12, 15, 17]))
        return kind, _encode({**tree, "world_from_camera": [0.0] * n}), True
    if kind == "sparse_ragged":
        f = draw(st.sampled_from(["points_xyz_f32", "obs_pixel_f32", "obs_point_i32", "colors_rgb_u8"]))
        return f"{kind}:{f}", _encode({**tree, f: tree[f][:-1]}), True
    raise AssertionError(kind)


def _name(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def _required(t: type) -> set[str]:
    info = msgspec.inspect.type_info(t)
    return {f.name for f in info.fields if f.required}  # type: ignore[attr-defined]


@st.composite
def bad_upload(draw: st.DrawFn) -> tuple[str, bytes, bool]:
    """Raw upload bytes that are no usable photo: (label, bytes, must_refuse=True)."""
    good = _jpeg(draw(st.integers(0, 3)))
    kind = draw(st.sampled_from(["empty", "random", "truncated_jpeg", "jpeg_header_garbage", "bomb_png", "png_bad_crc",
                                 "gigantic_header"]))  # fmt: skip
    if kind == "empty":
        return kind, b"", True
    if kind == "random":
        return kind, draw(st.binary(min_size=1, max_size=512)), True
    if kind == "truncated_jpeg":
        return kind, good[: draw(st.integers(2, len(good) // 2))], True
    if kind == "jpeg_header_garbage":
        return kind, good[:30] + draw(st.binary(min_size=10, max_size=300)), True
    if kind == "bomb_png":
        return kind, bomb_png(), True
    if kind == "png_bad_crc":
        png = bytearray(_png(np.zeros((H, W), np.uint8)))
        png[30] ^= 0xFF
        return kind, bytes(png), True
    # a JPEG whose frame header declares 60000 x 60000
    i = good.index(b"\xff\xc0")
    hdr = bytearray(good)
    hdr[i + 5 : i + 9] = (60000).to_bytes(2, "big") * 2
    return kind, bytes(hdr), True
