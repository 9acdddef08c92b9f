"""Bad HTTP requests for every workbench endpoint (Hypothesis strategies), shared by tests/test_workbench_fuzz.py
and bench/fuzz.py.

A request is ``(label, method, path, params, body)``; every one must be answered below 500 with, for 4xx, a JSON
``{"error": reason}`` without a traceback (:func:`check`), and the server must answer a good request afterwards.
Bad parts: path ids unknown, traversals (``..``, encoded or not), NUL, huge; query values not numbers, NaN,
infinite, beyond int64; bodies not JSON, JSON of the wrong shape, good bodies with one value replaced (NaN, 1e999,
huge integers, wrong types, clicks off the image), oversized bodies.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

import httpx
from hypothesis import strategies as st

from nodes.workbench.api import ENDPOINTS

SKIPPED = {"/api/events"}  # server-sent events never end: tested in test_workbench_api
BIG_BODY = 2 * 2**20  # larger than the API's body limit


def good_bodies(project: Any, T0: int) -> dict[str, list[dict[str, Any]]]:
    """Valid bodies per (method path), on the scene of tests/test_workbench_api (``project(world) -> pixel``)."""
    world = [(-3.0, -0.2, 0.0), (3.0, -0.2, 0.0), (3.0, -0.2, 3.0), (-3.0, -0.2, 3.0), (5.25, -0.25, 3.0), (0, -0.2, 1)]
    pts = [{"pixel": [float(c) for c in project(w)], "world": list(w)} for w in world]
    from test_workbench_api import CAM_A, INTR

    from constructaide import camera as cam

    intr = {
        "width_px": INTR.width_px,
        "height_px": INTR.height_px,
        "f_px": INTR.f_px,
        "cx_px": INTR.cx_px,
        "cy_px": INTR.cy_px,
    }
    poly = [[200.0, 200.0], [400.0, 200.0], [400.0, 350.0]]
    ann = {"photo_id": "p1", "element_ids": ["wall"], "status": "behind", "text": "late", "rgba": [255, 0, 0, 200]}
    return {
        "POST /api/pick": [
            {
                "world_from_camera": list(cam.pose_to_tuple(CAM_A)),
                "intrinsics": intr,
                "u": 320.0,
                "v": 240.0,
                "snap_px": 8,
            }
        ],
        "POST /api/photos/{photo_id}/solve": [{"points": pts}],
        "POST /api/photos/{photo_id}/anchors": [{"points": pts, "author": "fuzz"}],
        "POST /api/photos/{photo_id}/select": [
            {"mode": "click", "u": 320.0, "v": 240.0},
            {"mode": "grow", "element_ids": ["wall"], "by": "storey"},
            {"mode": "region", "polygon": poly},
            {"mode": "region", "brush": poly, "radius_px": 10},
            {"mode": "occlusion", "u": 100.0, "v": 430.0, "kind": "combined"},
        ],
        "POST /api/annotations": [ann, {"photo_id": "p1", "polygon_px": poly, "text": "region"}],
        "PUT /api/annotations/{annotation_id}": [{"text": "edited", "status": "on_time"}],
        "POST /api/photos/{photo_id}/peek": [{"at_ns": T0 - 1, "polygon": poly}, {"at_ns": T0 + 30 * 86_400 * 10**9}],
        "POST /api/photos/{photo_id}/progress/review": [
            {"global_id": "wall", "verdict": "confirm"},
            {"global_id": "wall", "verdict": "not_built", "text": "fuzz", "author": "fuzz"},
        ],
    }


GOOD_PARAMS = {
    "photo_id": "p2",
    "u": "320",
    "v": "240",
    "snap_px": "8",
    "at_ns": "1800000000000000000",
    "element_ids": "wall,col",
    "limit": "20",
}
BAD_IDS = [
    "nope",
    "..",
    "../../etc/passwd",
    "%2e%2e%2f%2e%2e%2fetc%2fpasswd",
    "p1%00",
    "a" * 3000,
    "\u00fc\u4e2d",
    "p1/../p2",
    " ",
    "-1",
]
BAD_NUMBERS = [
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e999",
    "-1e400",
    "99999999999999999999999999",
    "-5",
    "0x10",
    "",
    "1,2",
    "1e308",
    str(2**63),
    "abc",
]
BAD_VALUES: list[Any] = [
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    10**30,
    -(10**30),
    -1,
    0,
    "text",
    None,
    True,
    [],
    {},
    [1, "a"],
    {"x": [1]},
    "x" * 5000,
    2**63,
    -0.0,
]


def _json_values() -> st.SearchStrategy[Any]:
    leaf = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=20))
    return st.recursive(
        leaf,
        lambda c: st.one_of(st.lists(c, max_size=5), st.dictionaries(st.text(max_size=8), c, max_size=5)),
        max_leaves=20,
    )


def _leaves(tree: Any, prefix: tuple = ()) -> list[tuple]:
    if isinstance(tree, dict):
        return [p for k, v in tree.items() for p in _leaves(v, (*prefix, k))] + [prefix]
    if isinstance(tree, list):
        return [p for i, v in enumerate(tree) for p in _leaves(v, (*prefix, i))] + [prefix]
    return [prefix]


def _set(tree: Any, path: tuple, value: Any) -> Any:
    if not path:
        return value
    out: Any = dict(tree) if isinstance(tree, dict) else list(tree)
    out[path[0]] = _set(tree[path[0]], path[1:], value)
    return out


def _dumps(x: Any) -> bytes:
    return json.dumps(x, allow_nan=True).encode()  # NaN / Infinity literals on purpose


@st.composite
def bad_request(draw: st.DrawFn, bodies: dict[str, list[dict[str, Any]]], annotation_ids: tuple[str, str]) -> tuple:
    """(label, method, path, params, body bytes or None) for one endpoint, bad in one or more parts.
    ``annotation_ids``: one to edit and read, one to delete (so edits keep a target after the delete)."""
    eps = [e for e in ENDPOINTS if e.path not in SKIPPED]
    extra = ["static_traversal", "unknown_path", "wrong_method"]
    e = draw(st.sampled_from(eps + extra))  # type: ignore[operator]
    if isinstance(e, str):
        if e == "static_traversal":
            p = draw(
                st.sampled_from(
                    [
                        "/static/../../../etc/passwd",
                        "/static/%2e%2e/%2e%2e/etc/passwd",
                        "/static/..%2f..%2fpyproject.toml",
                        "/static/%00",
                        "/static/" + "a" * 3000,
                    ]
                )
            )
            return e, "GET", p, {}, None
        if e == "unknown_path":
            return (
                e,
                draw(st.sampled_from(["GET", "POST"])),
                "/api/" + quote(draw(st.text(max_size=30)), safe=""),
                {},
                None,
            )
        return e, draw(st.sampled_from(["PATCH", "DELETE", "PUT"])), "/api/photos", {}, None
    label = [f"{e.method} {e.path}"]
    path = e.path
    for name in [p[1:-1] for p in e.path.split("/") if p.startswith("{")]:
        good = {
            "photo_id": draw(st.sampled_from(["p1", "p2", "p5"])),
            "annotation_id": annotation_ids[e.method == "DELETE"],
            "global_id": "wall",
            "mode": "photoreal",
            "kind": "combined",
        }[name]
        if draw(st.booleans()):
            value = quote(draw(st.sampled_from(BAD_IDS)), safe="%/.")
            label.append(f"bad {name}")
        else:
            value = good
        path = path.replace("{" + name + "}", value)
    params: dict[str, str] = {}
    for name in e.params:
        if draw(st.integers(0, 2)) == 0:
            continue  # missing
        if draw(st.booleans()):
            params[name] = draw(st.one_of(st.sampled_from(BAD_NUMBERS), st.text(max_size=12)))
            label.append(f"bad ?{name}")
        else:
            params[name] = GOOD_PARAMS[name]
    body: bytes | None = None
    if e.method in ("POST", "PUT"):
        goods = bodies.get(f"{e.method} {e.path}", [{}])
        how = draw(
            st.sampled_from(
                [
                    "good",
                    "mutated",
                    "mutated",
                    "mutated",
                    "random_json",
                    "not_json",
                    "bytes",
                    "oversized",
                    "empty",
                    "deep",
                ]
            )
        )
        label.append(f"body {how}")
        tmpl = draw(st.sampled_from(goods))
        if how == "good":
            body = _dumps(tmpl)
        elif how == "mutated":
            for _ in range(draw(st.integers(1, 3))):
                leaf = draw(st.sampled_from(_leaves(tmpl)))
                tmpl = _set(tmpl, leaf, draw(st.one_of(st.sampled_from(BAD_VALUES), _json_values())))
            body = _dumps(tmpl)
        elif how == "random_json":
            body = _dumps(draw(_json_values()))
        elif how == "not_json":
            body = draw(st.sampled_from([b"{", b"{'a': 1}", b"[1,", b"\xff\xfe", b"nul", b'{"points": [}']))
        elif how == "bytes":
            body = draw(st.binary(max_size=200))
        elif how == "oversized":
            body = b'{"points": [' + b"1, " * (BIG_BODY // 3) + b"1]}"
        elif how == "empty":
            body = b""
        else:  # deeply nested: recursion limits
            body = b"[" * 100_000 + b"]" * 100_000
    return " / ".join(label), e.method, path, params, body


def check(resp: httpx.Response, label: str) -> None:
    """Below 500; a 4xx is JSON {"error": reason} without a traceback."""
    assert resp.status_code < 500, f"{label}: {resp.status_code} {resp.text[:300]}"
    if resp.status_code >= 400:
        body = resp.json()
        assert isinstance(body, dict) and set(body) == {"error"}, f"{label}: {resp.text[:300]}"
        assert isinstance(body["error"], str) and body["error"] and "Traceback" not in body["error"], label


def send(http: httpx.Client, req: tuple) -> httpx.Response:
    label, method, path, params, body = req
    # The path as given (no normalisation of dot segments by the client): a raw request target.
    url = httpx.URL(str(http.base_url).rstrip("/") + path, params=params or None)
    return http.request(method, url, content=body, headers={"content-type": "application/json"} if body else None)


@contextlib.contextmanager
def workbench_server() -> Iterator[tuple[httpx.Client, Any, str]]:
    """The workbench node on an in-process bus (real HTTP server, any free port), fed the scene of
    tests/test_workbench_api over the bus; yields (client, good bodies, annotation ids to edit and to delete)."""
    from test_workbench_api import CAM_A, T0, S, _feed, _project

    from constructaide.runtime import start_node
    from constructaide.runtime.local import LocalBus
    from nodes.workbench.node import SPEC, Config
    from schemas import keys
    from schemas import messages as m

    msgs: list[m.Message] = []

    class _Collect:
        apply = staticmethod(msgs.append)

    _feed(_Collect())  # type: ignore[arg-type]

    def key_of(msg: Any) -> str:
        pid = getattr(msg, "photo_id", None)
        cam = getattr(msg, "camera_id", None)
        return {
            m.BimModel: lambda: keys.key(keys.BIM_MODEL, site=S),
            m.Photo: lambda: keys.key(keys.PHOTO, site=S, camera=cam),
            m.Registration: lambda: keys.key(keys.REGISTRATION, site=S, camera=cam, photo=pid),
            m.NeedsAnchor: lambda: keys.key(keys.NEEDS_ANCHOR, site=S, photo=pid),
            m.ViewpointGroup: lambda: keys.key(keys.VIEWPOINTS, site=S, photo=pid),
            m.OcclusionMask: lambda: keys.key(keys.OCCLUSION, site=S, kind=msg.kind, photo=pid),
            m.Overlay: lambda: keys.key(keys.OVERLAY, site=S, mode=msg.mode, photo=pid),
        }[type(msg)]()

    with LocalBus() as bus, start_node(SPEC, Config(site=S, port=0), bus) as node:
        errors = bus.collect(keys.key(keys.ERRORS, site=S))
        for msg in msgs:
            bus.publish(key_of(msg), msg, latched=isinstance(msg, m.BimModel))
        assert node.wait_idle(60)
        assert errors.items == [], [e.reason for _, e in errors.items]
        with httpx.Client(base_url=node.obj.url, timeout=60) as http:
            assert len(http.get("/api/photos").json()) == 6
            ids = []
            for text in ("edit me", "delete me"):
                made = http.post("/api/annotations", json={"photo_id": "p1", "element_ids": ["col"], "text": text})
                assert made.status_code == 201, made.text
                ids.append(made.json()["annotation_id"])
            yield http, good_bodies(lambda w: _project(CAM_A, w), T0), (ids[0], ids[1])
