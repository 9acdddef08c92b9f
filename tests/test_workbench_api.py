"""The workbench's JSON API through an HTTP client, on a small scene of boxes with known cameras: the three fixed
contracts (photos, pick, anchors), selection, annotations with transfer and history, peeks, previews, access
tokens, bad input (clear 4xx, never a traceback), the node over a real socket with server-sent events, and the
``constructaide workbench --recording`` entry point."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest
import trimesh
from conftest import ROOT

from constructaide import camera as cam
from constructaide.bimgeom import meshes_to_glb
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.workbench.api import HttpServer, make_app, openapi_document
from nodes.workbench.node import SPEC, Config, access_token
from nodes.workbench.service import Workbench
from schemas import keys
from schemas.messages import (
    AnchorClicks,
    Annotation,
    BimElement,
    BimModel,
    ElementEvidence,
    ElementProgress,
    NeedsAnchor,
    OcclusionMask,
    Overlay,
    Photo,
    PhotoEvidence,
    ProgressUpdate,
    Registration,
    ScheduleTask,
    ViewpointGroup,
    ViewpointNeighbour,
)

S = "t"
W, H = 640, 480
DAY = 86_400 * 10**9
T0 = 1_800_000_000 * 10**9
INTR = cam.centered_intrinsics(W, H, 500.0)
CAM_A = cam.look_at([4.0, -16.0, 5.0], [1.0, 0.0, 1.5])
CAM_B = cam.look_at([-12.0, -10.0, 4.0], [1.0, 0.0, 1.5])
BOXES = {  # global_id: (ifc_class, storey, material, task, centre, extents)
    "wall": ("IfcWall", "L0", "brick", "t1", (0.0, 0.0, 1.5), (6.0, 0.4, 3.0)),
    "col": ("IfcColumn", "L0", "concrete", "t2", (5.0, 0.0, 1.5), (0.5, 0.5, 3.0)),
    "slab": ("IfcSlab", "L1", "concrete", "t3", (1.0, 0.5, 3.1), (9.0, 2.0, 0.2)),
}


def _model() -> BimModel:
    meshes, elements, tasks = {}, [], []
    for i, (gid, (cls, storey, mat, task, c, ext)) in enumerate(BOXES.items()):
        box = trimesh.creation.box(extents=ext)
        meshes[gid] = (np.asarray(box.vertices) + c, np.asarray(box.faces, np.int32))
        elements.append(BimElement(global_id=gid, ifc_class=cls, storey=storey, material=mat, geometry_ref=gid))
        start = T0 - 10 * DAY + i * 5 * DAY  # wall, column before photo 1; the slab between photos 1 and 2
        tasks.append(
            ScheduleTask(
                task_id=task,
                name=f"build {gid}",
                planned_start_ns=start,
                planned_finish_ns=start + DAY,
                element_ids=(gid,),
            )
        )
    return BimModel(
        site=S, revision="r1", elements=tuple(elements), tasks=tuple(tasks), geometry_glb=meshes_to_glb(meshes)
    )


def _png(seed: int) -> bytes:
    img = np.random.default_rng(seed).integers(0, 255, (H, W, 3), dtype=np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 3)
    return cv2.imencode(".png", img)[1].tobytes()


def _photo(pid: str, camera: str | None, t: int, seed: int) -> Photo:
    return Photo(
        site=S,
        photo_id=pid,
        camera_id=camera,
        capture_time_ns=t,
        data=_png(seed),
        media_type="image/png",
        width_px=W,
        height_px=H,
        filename=f"{pid}.png",
    )


def _reg(pid: str, T: np.ndarray, status: str = "auto", camera: str | None = "cam-a") -> Registration:
    return Registration(
        site=S,
        photo_id=pid,
        camera_id=camera,
        intrinsics=INTR,
        world_from_camera=cam.pose_to_tuple(T),
        status=status,
        method="test",
        num_inliers=100,
        reprojection_rms_px=0.5,
    )  # type: ignore[arg-type]


def _feed(wb: Workbench) -> None:
    wb.apply(_model())
    wb.apply(_photo("p1", "cam-a", T0, 1))
    wb.apply(_photo("p2", "cam-a", T0 + 10 * DAY, 2))
    wb.apply(_photo("p3", None, T0 + 10 * DAY + 3600 * 10**9, 3))
    wb.apply(_photo("p4", "cam-a", T0 + 11 * DAY, 4))
    wb.apply(_photo("p5", None, T0 + 12 * DAY, 5))
    wb.apply(_photo("p6", None, T0 + 13 * DAY, 6))
    wb.apply(_reg("p1", CAM_A))
    wb.apply(_reg("p2", CAM_A))
    wb.apply(_reg("p3", CAM_B, "anchor", None))
    wb.apply(Registration(site=S, photo_id="p4", status="failed", message="no matches"))
    wb.apply(Registration(site=S, photo_id="p5", status="failed"))
    wb.apply(NeedsAnchor(site=S, photo_id="p5", reason="please click"))
    wb.apply(
        ViewpointGroup(
            site=S,
            photo_id="p2",
            neighbours=(
                ViewpointNeighbour(
                    photo_id="p1",
                    this_from_neighbour=(1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0),
                    inlier_ratio=0.9,
                    num_matches=300,
                ),
            ),
        )
    )
    mask = np.zeros((H, W), np.uint8)
    mask[400:470, 20:200] = 255
    wb.apply(OcclusionMask(site=S, photo_id="p2", kind="combined", mask_png=cv2.imencode(".png", mask)[1].tobytes()))
    wb.apply(Overlay(site=S, photo_id="p2", mode="photoreal", image_png=_png(9)))


@contextlib.contextmanager
def serve(workbench: Workbench, token: str = "") -> Iterator[httpx.Client]:
    """The workbench's app on a real loopback socket, and an HTTP client for it."""
    with (
        HttpServer(make_app(workbench, token), "127.0.0.1", 0) as server,
        httpx.Client(base_url=server.url, timeout=30) as http,
    ):
        yield http


@pytest.fixture(scope="module")
def published():
    return []


@pytest.fixture(scope="module")
def wb(published):
    w = Workbench(S, publish=lambda key, msg: published.append((key, msg)))
    _feed(w)
    yield w
    w.close()


@pytest.fixture(scope="module")
def client(wb):
    with serve(wb) as c:
        yield c


def _project(T: np.ndarray, p) -> np.ndarray:
    px, _ = cam.project_points(INTR, cam.invert_rigid(T), np.atleast_2d(p))
    return px[0]


def _error(resp, status: int) -> str:
    assert resp.status_code == status, resp.text
    body = resp.json()
    assert set(body) == {"error"} and "Traceback" not in body["error"]
    return body["error"]


# ------------------------------------------------------------------------------------------- fixed contracts


def test_photos_contract(client) -> None:
    photos = client.get("/api/photos").json()
    assert [p["photo_id"] for p in photos] == ["p1", "p2", "p3", "p4", "p5", "p6"]
    for p in photos:
        assert {"photo_id", "filename", "camera_id", "capture_time", "status"} <= p.keys()
    status = {p["photo_id"]: p["status"] for p in photos}
    assert status == {"p1": "auto", "p2": "auto", "p3": "anchor", "p4": "failed", "p5": "needs_anchor", "p6": "pending"}
    p2 = next(p for p in photos if p["photo_id"] == "p2")
    assert p2["camera_id"] == "cam-a" and p2["capture_time"] == T0 + 10 * DAY and p2["filename"] == "p2.png"
    assert p2["overlays"] == ["photoreal"] and p2["masks"] == ["combined"]
    assert client.get("/api/anchor-queue").json()[0]["photo_id"] == "p5"
    assert client.get("/api/photos/p2/image").content == client.get("/api/photos/p2/image").content
    assert client.get("/api/photos/p2/thumb").headers["content-type"] == "image/jpeg"
    assert "no 'edges' overlay" in _error(client.get("/api/photos/p2/overlay/edges"), 404)
    assert "unknown photo" in _error(client.get("/api/photos/nope"), 404)


def test_pick_contract(client) -> None:
    wall_pt = np.array([0.5, -0.2, 1.0])  # on the wall's front face
    u, v = _project(CAM_A, wall_pt)
    r = client.get(f"/api/pick?photo_id=p1&u={u}&v={v}").json()
    assert r["global_id"] == "wall" and r["ifc_class"] == "IfcWall"
    assert np.linalg.norm(np.subtract(r["point_in_world_m"], wall_pt)) < 0.01
    # On p1's date the slab is not built: a pixel of the slab's front edge falls through to the wall or nothing.
    slab_pt = np.array([-2.8, -0.5, 3.1])
    u2, v2 = _project(CAM_A, slab_pt)
    assert client.get(f"/api/pick?photo_id=p1&u={u2}&v={v2}").json()["global_id"] != "slab"
    assert client.get(f"/api/pick?photo_id=p2&u={u2}&v={v2}").json()["global_id"] == "slab"
    assert client.get("/api/pick?photo_id=p1&u=2&v=2").json() == {"global_id": None}
    # Snapped to the wall's corner when asked, from a click 3 px off.
    corner = np.array([-3.0, -0.2, 3.0])
    cu, cv = _project(CAM_A, corner) + 3.0
    snapped = client.get(f"/api/pick?photo_id=p1&u={cu}&v={cv}&snap_px=8").json()
    assert snapped["snapped"] == "vertex" and np.allclose(snapped["point_in_world_m"], corner, atol=1e-4)
    assert "'u' is required" in _error(client.get("/api/pick?photo_id=p1&v=3"), 400)
    assert "not a valid finite number" in _error(client.get("/api/pick?photo_id=p1&u=abc&v=3"), 400)
    assert "outside" in _error(client.get("/api/pick?photo_id=p1&u=9000&v=3"), 400)
    assert "not registered" in _error(client.get("/api/pick?photo_id=p6&u=3&v=3"), 409)
    assert "unknown photo" in _error(client.get("/api/pick?photo_id=zz&u=3&v=3"), 404)


def test_model_view_pick(client) -> None:
    T = cam.look_at([0.0, -10.0, 1.5], [0.0, 0.0, 1.5])
    body = {
        "world_from_camera": cam.pose_to_tuple(T),
        "intrinsics": {"width_px": 400, "height_px": 300, "f_px": 300.0, "cx_px": 199.5, "cy_px": 149.5},
        "u": 199.5,
        "v": 149.5,
        "snap_px": 0,
    }
    r = client.post("/api/pick", json=body).json()
    assert r["global_id"] == "wall" and np.allclose(r["point_in_world_m"], [0.0, -0.2, 1.5], atol=1e-6)
    assert "world_from_camera" in _error(client.post("/api/pick", json={"u": 1}), 400)
    assert "valid JSON" in _error(client.post("/api/pick", content=b"{nope"), 400)


def _corners() -> np.ndarray:
    out = []
    for _, _, _, _, c, ext in BOXES.values():
        for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            out.append(np.asarray(c) + s * np.asarray(ext) / 2)
    return np.array(out)


def test_anchors_contract_solves_and_publishes(client, published) -> None:
    rng = np.random.default_rng(3)
    pts = _corners()[[0, 3, 5, 6, 9, 12, 17, 18, 21]]
    px = np.array([_project(CAM_B, p) for p in pts]) + rng.normal(0, 0.3, (len(pts), 2))
    body = {"points": [{"pixel": list(q), "world": list(p)} for q, p in zip(px, pts, strict=True)]}
    n0 = len(published)
    r = client.post("/api/photos/p5/anchors", json=body)
    assert r.status_code == 200, r.text
    out = r.json()
    assert len(out["residuals_px"]) == len(pts) and max(out["residuals_px"]) < 2.0
    T = np.asarray(out["world_from_camera"]).reshape(4, 4)
    dist = np.linalg.norm(CAM_B[:3, 3] - [1.0, 0.0, 1.5])
    assert np.linalg.norm(T[:3, 3] - CAM_B[:3, 3]) < 0.03 * dist and out["published"] is True
    assert cam.rotation_angle_deg(T[:3, :3], CAM_B[:3, :3]) < 1.0
    ((key, msg),) = published[n0:]
    assert key == keys.key(keys.ANCHORS, site=S, photo="p5") and isinstance(msg, AnchorClicks)
    assert len(msg.points) == len(pts) and msg.photo_id == "p5"
    # The live solve: same answer, nothing published; a 30 px mis-click is flagged.
    bad = json.loads(json.dumps(body))
    bad["points"][4]["pixel"][0] += 30
    s = client.post("/api/photos/p5/solve", json=bad).json()
    assert s["misclick"] == [False] * 4 + [True] + [False] * 4 and len(published) == n0 + 1
    # Bad input: clear reasons.
    assert "at least 4" in _error(client.post("/api/photos/p5/anchors", json={"points": body["points"][:3]}), 422)
    assert "body must be" in _error(client.post("/api/photos/p5/anchors", json={"points": [{"pixel": [1]}]}), 400)
    assert "body must be" in _error(client.post("/api/photos/p5/anchors", content=b"not json"), 400)
    outside = {"points": [{**q, "pixel": [5000.0, 1.0]} for q in body["points"]]}
    assert "outside" in _error(client.post("/api/photos/p5/anchors", json=outside), 400)
    assert "unknown photo" in _error(client.post("/api/photos/zz/anchors", json=body), 404)
    assert len(published) == n0 + 1


def test_live_solve_says_when_the_clicks_also_fit_another_camera(client) -> None:
    """Three distinct corners (a fourth on one of them) fit the true camera and, for most triples, a mirrored one: the
    live solve says so and asks for spread clicks; nine spread corners do not."""
    c = _corners()
    notes = []
    for i, j, k in [(0, 3, 5), (0, 9, 17), (3, 12, 21), (5, 6, 18), (9, 17, 21), (0, 12, 18)]:
        pts = np.array([c[i], c[j], c[k], c[j] + [0.0, 0.0, 0.01]])
        body = {"points": [{"pixel": list(_project(CAM_B, p)), "world": list(p)} for p in pts]}
        r = client.post("/api/photos/p5/solve", json=body)
        if r.status_code == 200:
            notes.append(r.json()["note"])
    assert any("also fit a camera" in n and "add clicks" in n for n in notes), notes
    pts = c[[0, 3, 5, 6, 9, 12, 17, 18, 21]]
    body = {"points": [{"pixel": list(_project(CAM_B, p)), "world": list(p)} for p in pts]}
    assert "also fit" not in client.post("/api/photos/p5/solve", json=body).json()["note"]


def test_review_mode_publishes_nothing() -> None:
    w = Workbench(S, publish=None)
    _feed(w)
    try:
        with serve(w) as c:
            pts = _corners()[:8]
            body = {"points": [{"pixel": list(_project(CAM_B, p)), "world": list(p)} for p in pts]}
            out = c.post("/api/photos/p5/anchors", json=body).json()
            assert out["published"] is False and len(out["residuals_px"]) == 8
            assert c.get("/api/site").json()["live"] is False
    finally:
        w.close()


# ---------------------------------------------------------------------------------- selection, annotations


def test_select_and_grow(client) -> None:
    u, v = _project(CAM_A, [0.5, -0.2, 1.0])
    sel = client.post("/api/photos/p2/select", json={"mode": "click", "u": u, "v": v}).json()
    assert sel["element_ids"] == ["wall"] and sel["elements"][0]["material"] == "brick" and sel["polygons"]
    grown = client.post("/api/photos/p2/select", json={"mode": "grow", "element_ids": ["col"], "by": "material"})
    assert set(grown.json()["element_ids"]) == {"col", "slab"}
    c = _project(CAM_A, [5.0, 0.0, 1.5])
    poly = [[c[0] - 25, c[1] - 60], [c[0] + 25, c[1] - 60], [c[0] + 25, c[1] + 60], [c[0] - 25, c[1] + 60]]
    assert client.post("/api/photos/p2/select", json={"mode": "region", "polygon": poly}).json()["element_ids"] == [
        "col"
    ]
    brush = client.post("/api/photos/p2/select", json={"mode": "region", "brush": [list(c)], "radius_px": 40}).json()
    assert brush["element_ids"] == ["col"]
    occ = client.post("/api/photos/p2/select", json={"mode": "occlusion", "u": 100, "v": 430, "kind": "combined"})
    (ring,) = occ.json()["region_polygons"]
    xs, ys = np.asarray(ring).T
    assert abs(xs.min() - 20) < 2 and abs(xs.max() - 199) < 2 and abs(ys.min() - 400) < 2
    assert "grow by" in _error(
        client.post("/api/photos/p2/select", json={"mode": "grow", "element_ids": [], "by": "colour"}), 400
    )
    assert "mode must be" in _error(client.post("/api/photos/p2/select", json={"mode": "zap"}), 400)
    assert "occlusion region under" in _error(
        client.post("/api/photos/p2/select", json={"mode": "occlusion", "u": 5, "v": 5}), 404
    )


def _mask(polys) -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    for p in polys:
        cv2.fillPoly(m, [np.round(np.asarray(p)).astype(np.int32)], 1)
    return m.astype(bool)


def test_annotations_transfer_edit_delete(client, wb, published) -> None:
    n0 = len(published)
    r = client.post(
        "/api/annotations", json={"photo_id": "p2", "element_ids": ["wall"], "status": "behind", "text": "late"}
    )
    assert r.status_code == 201
    aid = r.json()["annotation_id"]
    assert published[-1][0] == keys.key(keys.ANNOTATION, site=S, annotation=aid)
    # Transferred: on the other camera's photo (p3, other camera) it covers the wall's visible pixels there.
    (on_p3,) = [a for a in client.get("/api/annotations?photo_id=p3").json() if a["annotation_id"] == aid]
    drawn = _mask(on_p3["polygons"])
    u, v = _project(CAM_B, [0.0, -0.2, 1.5])
    assert drawn[round(v), round(u)] and on_p3["rgba"] == [230, 40, 40, 160]
    # Not on a photo that is not registered.
    assert all(a["annotation_id"] != aid for a in client.get("/api/annotations?photo_id=p6").json())
    # A region drawn on p2 over the column travels to p3 through the model surface.
    c = _project(CAM_A, [5.0, -0.25, 1.5])
    square = [[c[0] - 6, c[1] - 6], [c[0] + 6, c[1] - 6], [c[0] + 6, c[1] + 6], [c[0] - 6, c[1] + 6]]
    reg = client.post("/api/annotations", json={"photo_id": "p2", "polygon_px": square, "text": "crack"}).json()
    assert reg["kind"] == "note" and len(reg["polygon_in_world_m"]) == 4
    (rp3,) = [
        a for a in client.get("/api/annotations?photo_id=p3").json() if a["annotation_id"] == reg["annotation_id"]
    ]
    cu, cv = _project(CAM_B, [5.0, -0.25, 1.5])
    xs, ys = np.concatenate([np.asarray(p) for p in rp3["polygons"]]).T
    assert abs(xs.mean() - cu) < 8 and abs(ys.mean() - cv) < 8
    # Edit, history, delete.
    assert client.put(f"/api/annotations/{aid}", json={"text": "very late"}).json()["revision"] == 1
    hist = client.get(f"/api/annotations/{aid}/history").json()
    assert [(h["revision"], h["text"]) for h in hist] == [(0, "late"), (1, "very late")]
    assert client.delete(f"/api/annotations/{aid}").json()["deleted"] is True
    assert all(a["annotation_id"] != aid for a in client.get("/api/annotations").json())
    assert len(client.get(f"/api/annotations/{aid}/history").json()) == 3
    assert len(published) == n0 + 4  # two created, one edit, one deletion
    assert "unknown annotation" in _error(client.delete(f"/api/annotations/{aid}"), 404)
    assert "needs element_ids or a polygon" in _error(client.post("/api/annotations", json={"photo_id": "p2"}), 400)
    assert "bad annotation" in _error(
        client.post("/api/annotations", json={"photo_id": "p2", "element_ids": ["wall"], "status": "great"}), 400
    )
    assert "JSON object" in _error(client.post("/api/annotations", json=[1, 2]), 400)


def test_progress_readings_confirmed_and_corrected(client, wb, published) -> None:
    """What the progress node read in a photo, listed with the fused progress; a person confirms one reading and
    corrects another: each becomes a published status annotation on the element, listed as its review."""
    assert "no progress evidence" in _error(client.get("/api/photos/p2/progress"), 404)
    t2 = T0 + 10 * DAY
    wb.apply(
        PhotoEvidence(
            site=S,
            photo_id="p2",
            camera_id="cam-a",
            capture_time_ns=t2,
            elements=(
                ElementEvidence(global_id="col", state="occluded", confidence=0.9, visible_px=9, occluded_fraction=0.9),
                ElementEvidence(global_id="slab", state="not_built", confidence=0.8, visible_px=400),
                ElementEvidence(global_id="wall", state="built", confidence=0.93, visible_px=900, llr_appearance=1.0),
            ),
        )
    )
    wb.apply(
        ProgressUpdate(
            site=S,
            as_of_ns=t2,
            photo_id="p2",
            tz="Europe/Berlin",
            elements=(
                ElementProgress(global_id="wall", state="built", present_probability=0.97, deviation="on_time"),
                ElementProgress(
                    global_id="slab",
                    state="not_built",
                    present_probability=0.1,
                    deviation="not_built",
                    planned_start_ns=T0,
                    planned_finish_ns=T0 + DAY,
                ),
            ),
        )
    )
    doc = client.get("/api/photos/p2/progress").json()
    assert (doc["as_of_ns"], doc["tz"], doc["capture_time_ns"]) == (t2, "Europe/Berlin", t2)
    assert [e["global_id"] for e in doc["elements"]] == ["wall", "slab", "col"]  # reviewable first, by pixels
    wall, slab, col = doc["elements"]
    assert wall["ifc_class"] == "IfcWall" and wall["photo"]["llr_appearance"] == 1.0
    assert wall["fused"]["deviation"] == "on_time" and slab["fused"]["present_probability"] == 0.1
    assert col["fused"] is None and all(e["review"] is None for e in doc["elements"])
    # The review queue: the slab read not built 9 days after its planned finish (the wall's reading agrees with its
    # plan, the column was not read).
    (q,) = client.get("/api/progress/review-queue").json()
    assert (q["photo_id"], q["global_id"], q["reading"], q["days_off"]) == ("p2", "slab", "not_built", 9.0)
    assert client.get("/api/progress/review-queue?limit=0").json() == []
    n0 = len(published)
    r = client.post("/api/photos/p2/progress/review", json={"global_id": "wall", "verdict": "confirm", "author": "pm"})
    assert r.status_code == 201, r.text
    ok = r.json()
    assert (ok["kind"], ok["status"], ok["element_ids"], ok["photo_id"]) == ("status", "built", ["wall"], "p2")
    assert ok["text"] == "confirms the detection: built (93%)" and ok["author"] == "pm"
    key, msg = published[-1]
    assert isinstance(msg, Annotation) and msg.status == "built" and msg.element_ids == ("wall",)
    assert key == keys.key(keys.ANNOTATION, site=S, annotation=ok["annotation_id"])
    fix = client.post(
        "/api/photos/p2/progress/review", json={"global_id": "slab", "verdict": "built", "text": "poured 9:00"}
    ).json()
    assert fix["status"] == "built" and fix["text"] == "corrects the detection not built (80%): built; poured 9:00"
    reviews = {e["global_id"]: e["review"] for e in client.get("/api/photos/p2/progress").json()["elements"]}
    assert reviews["wall"]["status"] == "built" and reviews["wall"]["author"] == "pm"
    assert reviews["slab"]["annotation_id"] == fix["annotation_id"] and reviews["col"] is None
    assert len(published) == n0 + 2
    assert client.get("/api/progress/review-queue").json() == []  # reviewed elements leave the queue
    review = "/api/photos/p2/progress/review"
    assert "nothing to confirm" in _error(client.post(review, json={"global_id": "col", "verdict": "confirm"}), 400)
    assert "verdict must be" in _error(client.post(review, json={"global_id": "wall", "verdict": "maybe"}), 400)
    assert "global_id" in _error(client.post(review, json={"verdict": "built"}), 400)
    assert "not read in photo" in _error(client.post(review, json={"global_id": "nope", "verdict": "built"}), 404)
    other = "/api/photos/p3/progress/review"
    assert "no progress evidence" in _error(client.post(other, json={"global_id": "wall", "verdict": "built"}), 404)
    assert "unknown photo" in _error(client.get("/api/photos/zzz/progress"), 404)
    assert len(published) == n0 + 2
    for a in (ok, fix):  # leave the annotations as the other tests expect them
        client.delete(f"/api/annotations/{a['annotation_id']}")


# ---------------------------------------------------------------------------------------------- time, preview


def test_peek_backward_forward_and_preview(client, wb) -> None:
    poly = [[100, 100], [300, 100], [300, 300], [100, 300]]
    r = client.post("/api/photos/p2/peek", json={"at_ns": T0 + DAY, "polygon": poly})
    assert r.status_code == 200 and json.loads(r.headers["X-Peek"])["source_photo_id"] == "p1"
    rgba = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    p1 = cv2.imdecode(np.frombuffer(wb.photo("p1").data, np.uint8), cv2.IMREAD_COLOR)
    assert (rgba[150:250, 150:250, 3] == 255).all() and (rgba[:90, :, 3] == 0).all()
    assert np.abs(rgba[150:250, 150:250, :3].astype(int) - p1[150:250, 150:250]).max() <= 1
    # Forward from p1 (slab not built yet) to p2's date: the slab drawn where it will stand.
    f = client.post("/api/photos/p1/peek", json={"at_ns": T0 + 10 * DAY})
    assert json.loads(f.headers["X-Peek"])["direction"] == "forward"
    layer = cv2.imdecode(np.frombuffer(f.content, np.uint8), cv2.IMREAD_UNCHANGED)
    su, sv = _project(CAM_A, [1.0, -0.5, 3.1]).round().astype(int)
    assert tuple(layer[sv, su, :3][::-1]) == (255, 170, 0)
    assert "no photo from this viewpoint" in _error(client.post("/api/photos/p1/peek", json={"at_ns": T0 - DAY}), 404)
    assert "peek needs" in _error(client.post("/api/photos/p1/peek", json={"polygon": poly}), 400)
    prev = client.get("/api/photos/p2/preview?element_ids=col")
    assert prev.status_code == 200
    out = cv2.imdecode(np.frombuffer(prev.content, np.uint8), cv2.IMREAD_COLOR)
    cu, cv = _project(CAM_A, [5.0, -0.25, 1.5]).round().astype(int)
    real = cv2.imdecode(np.frombuffer(wb.state.overlays[("p2", "photoreal")].image_png, np.uint8), cv2.IMREAD_COLOR)
    photo = cv2.imdecode(np.frombuffer(wb.photo("p2").data, np.uint8), cv2.IMREAD_COLOR)
    assert (out[cv, cu] == real[cv, cu]).all() and (out[10, 10] == photo[10, 10]).all()
    assert "no photoreal overlay" in _error(client.get("/api/photos/p1/preview?element_ids=col"), 409)


# ---------------------------------------------------------------------------------------- access and errors


def test_token_and_errors_without_traceback(wb, monkeypatch) -> None:
    assert access_token(Config(host="127.0.0.1")) == "" and access_token(Config(host="::1")) == ""
    assert len(access_token(Config(host="0.0.0.0"))) >= 16
    assert access_token(Config(host="10.1.2.3", token="abc")) == "abc"
    with serve(wb, token="s3cret") as c:
        assert "token required" in _error(c.get("/api/photos"), 401)
        assert "wrong access token" in _error(c.get("/api/photos", headers={"Authorization": "Bearer nope"}), 401)
        assert c.get("/api/photos", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        page = c.get("/?token=s3cret")
        assert page.status_code == 200 and "workbench_token" in page.headers["set-cookie"]
        assert c.get("/api/site").status_code == 200  # the cookie the page got
        assert "Not Found" in _error(c.get("/api/nothing-here"), 404)
        monkeypatch.setattr(wb, "anchor_queue", lambda: 1 / 0)
        msg = _error(c.get("/api/anchor-queue"), 500)
        assert msg.startswith("internal error: ZeroDivisionError")
        assert c.get("/api/photos").status_code == 200  # still up


def test_openapi_documents_the_contracts(client) -> None:
    doc = client.get("/api/openapi.json").json()
    assert doc == openapi_document()
    assert {"get"} <= doc["paths"]["/api/photos"].keys() and "post" in doc["paths"]["/api/photos/{photo_id}/anchors"]
    assert {p["name"] for p in doc["paths"]["/api/pick"]["get"]["parameters"]} >= {"photo_id", "u", "v"}
    page = client.get("/")
    assert page.status_code == 200 and "main.js" in page.text
    assert client.get("/static/main.js").headers["content-type"].startswith("text/javascript")


# ------------------------------------------------------------------------------------------- node and CLI


def test_node_serves_over_http_with_live_events() -> None:
    assert "workbench" in SPEC.describe() and "AnchorClicks" in SPEC.describe()
    with LocalBus() as bus, start_node(SPEC, Config(site=S, port=0), bus) as node:
        url = node.obj.url
        with httpx.Client(base_url=url, timeout=10) as http:
            assert http.get("/api/photos").json() == []
            with http.stream("GET", "/api/events") as events:
                lines = events.iter_lines()
                first = next(line for line in lines if line.startswith("data: "))
                assert json.loads(first[6:])["kind"] == "hello"
                bus.publish(keys.key(keys.PHOTO, site=S, camera="cam-a"), _photo("p1", "cam-a", T0, 1))
                ev = next(json.loads(line[6:]) for line in lines if line.startswith("data: "))
                assert ev["kind"] == "photo" and ev["photo_id"] == "p1"
            assert http.get("/api/photos").json()[0]["status"] == "pending"


def test_cli_opens_a_recording_for_review(tmp_path) -> None:
    from nodes.recorder.mcapio import RecordingWriter
    from schemas import codec

    rec = tmp_path / "site.mcap"
    with RecordingWriter(rec) as w:
        w.write(keys.key(keys.BIM_MODEL, site=S), codec.encode(_model()))
        w.write(keys.key(keys.PHOTO, site=S, camera="cam-a"), codec.encode(_photo("p1", "cam-a", T0, 1)))
        w.write(keys.key(keys.REGISTRATION, site=S, camera="cam-a", photo="p1"), codec.encode(_reg("p1", CAM_A)))
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "constructaide.app.cli", "workbench", "--recording", str(rec), "--port", "0"]
    with subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        try:
            line = proc.stdout.readline()
            assert "review, nothing is published" in line, line
            url = line.split(": ", 1)[1].split()[0]
            photos = httpx.get(url + "api/photos", timeout=10).json()
            assert [(p["photo_id"], p["status"]) for p in photos] == [("p1", "auto")]
        finally:
            proc.send_signal(signal.SIGINT)
            assert proc.wait(30) == 0
    bad = subprocess.run(
        [*cmd[:4], "--recording", str(tmp_path / "none.mcap")], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "recording not found" in bad.stderr and "Traceback" not in bad.stderr
