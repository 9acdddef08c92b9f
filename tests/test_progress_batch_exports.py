"""Progress batch contract and exports on a recording of the tiny synthetic site.

The recording is written with the recorder's writer from what upstream nodes would publish: the ingest node's
BimModel of the site's IFC, the photos, registrations and occlusion masks (simulated from the site's true
cameras and masks: the upstream nodes are not under test here). The progress engine and the exports are.
"""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from constructaide.bim.ifc import load_site_model
from constructaide.bim.schedule import tasks_from_ifc, zone
from constructaide.camera import pose_to_tuple
from nodes.ingest.photos import photo_from_file
from nodes.ingest.revisions import to_bim_model
from nodes.progress import batch, exports
from nodes.recorder.mcapio import RecordingWriter
from schemas import codec, keys
from schemas.messages import OcclusionMask, Registration

CACHE = Path(__file__).resolve().parents[1] / ".cache"
TZ = "Europe/Amsterdam"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(site folder, recording path)."""
    from constructaide.synth import ensure_site
    from constructaide.synth.truth import load_cameras, load_mask, true_camera

    site = ensure_site("tiny", 0, CACHE / "synth")
    model = to_bim_model(load_site_model([site / "model" / "building.ifc"], tz=TZ), "t", "r1", 0.0)
    rec = tmp_path_factory.mktemp("rec") / "tiny.mcap"
    cams = load_cameras(site)
    with RecordingWriter(rec) as w:
        w.write(keys.key(keys.BIM_MODEL, site="t"), codec.encode(model))
        for rel in sorted(cams, key=lambda r: cams[r]["capture_time_utc_ns"]):
            cam = cams[rel]["camera_id"]
            photo = photo_from_file(site / "photos" / rel, camera_id=cam, site="t", tz=TZ)
            intr, T = true_camera(site, rel, cams)
            reg = Registration(
                site="t",
                photo_id=photo.photo_id,
                camera_id=cam,
                capture_time_ns=photo.capture_time_ns,
                intrinsics=intr,
                world_from_camera=pose_to_tuple(T),
                status="anchor",
            )
            occ = (load_mask(site, rel, "static") | load_mask(site, rel, "dynamic")).astype(np.uint8) * 255
            mask = OcclusionMask(
                site="t", photo_id=photo.photo_id, kind="combined", mask_png=cv2.imencode(".png", occ)[1].tobytes()
            )
            w.write(keys.key(keys.PHOTO, site="t", camera=cam), codec.encode(photo))
            w.write(keys.key(keys.REGISTRATION, site="t", camera=cam, photo=photo.photo_id), codec.encode(reg))
            w.write(keys.key(keys.OCCLUSION, site="t", kind="combined", photo=photo.photo_id), codec.encode(mask))
    return site, rec


def test_batch_contract_columns_and_values(tiny: tuple[Path, Path], tmp_path: Path) -> None:
    site, rec = tiny
    assert batch.main(["--recording", str(rec), "--out", str(tmp_path), "--quiet"]) == 0
    with (tmp_path / "observations.csv").open() as f:
        obs = list(csv.DictReader(f))
    with (tmp_path / "elements.csv").open() as f:
        els = list(csv.DictReader(f))
    assert list(obs[0]) == list(batch.OBSERVATION_COLUMNS)
    assert list(els[0]) == list(batch.ELEMENT_COLUMNS)
    assert {r["state"] for r in obs} <= set(batch.STATES) and "built" in {r["state"] for r in obs}
    assert {r["deviation"] for r in els} <= set(batch.DEVIATIONS)
    photos = {hashlib.sha256(p.read_bytes()).hexdigest()[:16]: p for p in (site / "photos").rglob("*.jpg")}
    assert {r["photo_id"] for r in obs} == set(photos)  # every photo was read
    for r in obs[:50]:
        assert r["filename"] == photos[r["photo_id"]].name
        assert r["capture_time"].endswith("+01:00") or r["capture_time"].endswith("+02:00")
        assert 0.0 <= float(r["confidence"]) <= 1.0
    for r in els:
        for k in ("planned_start", "planned_finish", "detected_start", "detected_finish"):
            assert r[k] == "" or r[k][-6] in "+-"  # ISO 8601 with offset, or empty
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["photos_processed"] == len(photos)


def test_ifc_export_reread_by_our_ingest(tiny: tuple[Path, Path], tmp_path: Path) -> None:
    import ifcopenshell

    site, rec = tiny
    inputs = batch.read_inputs(rec)
    engine = batch.run_engine(inputs, progress=False)
    out = tmp_path / "asbuilt.ifc"
    n = exports.export_ifc(engine, site / "model" / "building.ifc", out)
    assert n == len(engine.tasks) > 0
    f = ifcopenshell.open(str(out))
    reread = {t.task_id: t for t in tasks_from_ifc(f, set(engine.global_ids), zone(TZ))}
    written = 0
    for tid, task in engine.tasks.items():
        tp = engine.task_progress(task)
        got = reread[tid]
        for want, have in ((tp.actual_start_ns, got.actual_start_ns), (tp.actual_finish_ns, got.actual_finish_ns)):
            if want is None:
                assert have is None
            else:  # written to the second, local time
                assert have is not None and abs(have - want) < 1_000_000_000
                written += 1
        tt = next(t for t in f.by_type("IfcTask") if t.GlobalId == tid).TaskTime
        assert tt.Completion == pytest.approx(tp.percent_complete / 100.0, abs=1e-6)
    assert written > 0


def test_summary_tasks_roll_up_their_element_sub_tasks(tiny: tuple[Path, Path]) -> None:
    """The synthetic IFC nests one sub-task per element in each trade task: a trade task's progress counts its
    sub-tasks' elements, and BCF topics group behind elements by trade task."""
    _, rec = tiny
    engine = batch.run_engine(batch.read_inputs(rec), progress=False)
    summaries = [t for t in engine.tasks.values() if t.parent_id is None]
    subs = [t for t in engine.tasks.values() if t.parent_id is not None]
    assert summaries and len(subs) == len(engine.global_ids)
    for s in summaries:
        kids = [engine.task_progress(t) for t in subs if t.parent_id == s.task_id]
        tp = engine.task_progress(s)
        assert not s.element_ids and kids and tp.num_elements == sum(k.num_elements for k in kids)
        assert tp.num_built == sum(k.num_built for k in kids) and tp.num_observed == sum(k.num_observed for k in kids)
    names = {s.name for s in summaries}
    groups = exports.issue_groups(engine)
    assert groups and all(title.split(":")[0] in names for title, _, _ in groups if not title.startswith("Needs"))
    # a photo's update carries the trade task of each element it touched, beside the element's sub-task
    upd = engine.update_message([subs[0].element_ids[0]])
    assert {t.task_id for t in upd.tasks} == {subs[0].task_id, subs[0].parent_id}


@pytest.mark.parametrize("version", ["3.0", "2.1"])
def test_bcf_export_round_trip(tiny: tuple[Path, Path], tmp_path: Path, version: str) -> None:
    site, rec = tiny
    inputs = batch.read_inputs(rec)
    engine = batch.run_engine(inputs, progress=False)
    groups = exports.issue_groups(engine)
    assert groups, "the tiny site has a never-built wall and late elements: some group must be behind"
    out = tmp_path / f"issues-{version}.bcf"
    assert exports.export_bcf(engine, inputs, rec, out, version) == len(groups)
    if version == "3.0":
        import bcf.v3.bcfxml as bx
    else:
        import bcf.v2.bcfxml as bx  # type: ignore[no-redef]
    doc = bx.BcfXml.load(str(out))
    topics = list(doc.topics.values())
    assert sorted(t.topic.title for t in topics) == sorted(g[0] for g in groups)
    offset = np.asarray(inputs.model.origin_offset_m)  # type: ignore[union-attr]
    centres = {
        pid: np.asarray(r.world_from_camera).reshape(4, 4)[:3, 3] + offset for pid, r in inputs.registrations.items()
    }
    for topic, (_, _, gids) in zip(sorted(topics, key=lambda t: t.topic.title), sorted(groups), strict=True):
        vp = next(iter(topic.viewpoints.values()))
        info = vp.visualization_info
        assert {c.ifc_guid for c in info.components.selection.component} == set(gids)
        cam = info.perspective_camera
        pos = np.array([cam.camera_view_point.x, cam.camera_view_point.y, cam.camera_view_point.z])
        assert min(np.linalg.norm(pos - c) for c in centres.values()) < 1e-6  # a registered camera's centre
        assert 10.0 < cam.field_of_view < 120.0
        assert vp.snapshot and cv2.imdecode(np.frombuffer(vp.snapshot, np.uint8), cv2.IMREAD_COLOR) is not None


def test_mp4_time_lapse_decodes_to_the_photo_count(tiny: tuple[Path, Path], tmp_path: Path) -> None:
    site, rec = tiny
    inputs = batch.read_inputs(rec)
    frames = exports.export_mp4(inputs, rec, tmp_path, overlay="")
    per_cam: dict[str, int] = {}
    for p in inputs.photos.values():
        if p.camera_id:
            per_cam[p.camera_id] = per_cam.get(p.camera_id, 0) + 1
    assert frames == per_cam and per_cam
    for cam, n in per_cam.items():
        with av.open(str(tmp_path / f"{cam}.mp4")) as c:
            decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        assert len(decoded) == n
        assert decoded[0].shape[0] % 2 == 0 and decoded[0].std() > 5.0  # a picture, not a blank frame


def test_csv_report_and_gltf_with_cameras(tiny: tuple[Path, Path], tmp_path: Path) -> None:
    import trimesh

    site, rec = tiny
    inputs = batch.read_inputs(rec)
    engine = batch.run_engine(inputs, progress=False)
    rows = exports.report_rows(engine)
    assert len(rows) == len(engine.global_ids) and set(rows[0]) == set(exports.REPORT_COLUMNS)
    assert any(r["evidence_photos"] for r in rows)
    out = tmp_path / "site.glb"
    n = exports.export_gltf(inputs, out)
    assert n == len(inputs.registrations)
    scene = trimesh.load(str(out), force="scene")
    assert len(scene.geometry) >= len(engine.global_ids) - 1
    # y up: the building's height runs along y
    lo, hi = scene.bounds
    assert (hi - lo)[1] < (hi - lo)[0] + (hi - lo)[2]
    doc = json.loads(out.read_bytes()[20 : 20 + int.from_bytes(out.read_bytes()[12:16], "little")])
    assert len(doc["cameras"]) == n and all(c["type"] == "perspective" for c in doc["cameras"])
