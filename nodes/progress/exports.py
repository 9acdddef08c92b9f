"""``constructaide export ifc|bcf|csv|mp4|gltf --recording FILE --out PATH``: detected progress for other tools.

* ``ifc``: the model's IFC with the detected dates written back to each ``IfcTask``'s ``IfcTaskTime``
  (``ActualStart``, ``ActualFinish``, ``Completion``; local time of the site), through ifcopenshell;
* ``bcf``: BCF 3.0 (``--bcf-version 2.1`` for 2.1), through bcf-client: one topic per task whose elements are
  behind or not built (and per needs-review annotation), its viewpoint the registered camera of the photo that
  shows them best (position, direction, up, field of view in the IFC's coordinates), the elements as selected
  components, the progress overlay of that photo as the snapshot;
* ``csv``: a report, one row per element (element, task, planned, detected, deviation, evidence photos);
* ``mp4``: a time-lapse per fixed camera (``OUT/<camera>.mp4``), optionally with an overlay mode blended in
  (``--overlay progress``), through PyAV;
* ``gltf``: the model as binary glTF (y up, as glTF wants) with one perspective camera node per registered photo.

The progress comes from :mod:`nodes.progress.batch` (the progress engine run over the recording).
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import struct
from pathlib import Path
from zoneinfo import ZoneInfo

import cv2
import numpy as np

from constructaide.camera import focal_xy, pose_from_tuple, registered_camera
from constructaide.errors import UserError
from constructaide.imagecodec import decode_bgr, decode_unchanged, encode_png
from nodes.progress.batch import RecordedInputs, iso, iter_recording, read_inputs, run_engine
from nodes.progress.engine import ProgressEngine
from schemas.messages import Overlay, Registration

REPORT_COLUMNS = (
    "global_id",
    "name",
    "ifc_class",
    "storey",
    "task_id",
    "task_name",
    "planned_start",
    "planned_finish",
    "detected_start",
    "detected_finish",
    "deviation",
    "state",
    "present_probability",
    "evidence_photos",
)


def _local(t_ns: int, tz: str) -> str:
    """IfcDateTime: local time without offset, seconds."""
    return dt.datetime.fromtimestamp(t_ns / 1e9, ZoneInfo(tz)).replace(tzinfo=None).isoformat(timespec="seconds")


def export_ifc(engine: ProgressEngine, ifc_in: Path, ifc_out: Path) -> int:
    """Write detected actual dates into a copy of the IFC; returns the number of tasks written."""
    import ifcopenshell
    import ifcopenshell.api.sequence

    f = ifcopenshell.open(str(ifc_in))
    n = 0
    for task in f.by_type("IfcTask"):
        st = engine.tasks.get(task.GlobalId)
        if st is None:
            continue
        tp = engine.task_progress(st)
        tt = task.TaskTime or ifcopenshell.api.sequence.add_task_time(f, task=task)  # type: ignore[arg-type]
        tt.ActualStart = _local(tp.actual_start_ns, engine.tz) if tp.actual_start_ns is not None else None
        tt.ActualFinish = _local(tp.actual_finish_ns, engine.tz) if tp.actual_finish_ns is not None else None
        tt.Completion = float(np.clip(tp.percent_complete / 100.0, 0.0, 1.0))
        n += 1
    ifc_out.parent.mkdir(parents=True, exist_ok=True)
    f.write(str(ifc_out))
    return n


def report_rows(engine: ProgressEngine) -> list[dict[str, str]]:
    names = {e.global_id: e for e in engine.model.elements} if engine.model is not None else {}
    files = {r.photo_id: (f"{r.camera_id}/" if r.camera_id else "") + r.filename for r in engine.records.values()}
    rows = []
    for gid in engine.global_ids:
        ep = engine.element_progress(gid)
        el = names.get(gid)
        tasks = [engine.tasks[t] for t in ep.task_ids if t in engine.tasks]
        rows.append(
            {
                "global_id": gid,
                "name": el.name if el else "",
                "ifc_class": el.ifc_class if el else "",
                "storey": el.storey if el else "",
                "task_id": ";".join(t.task_id for t in tasks),
                "task_name": ";".join(t.name for t in tasks),
                "planned_start": iso(ep.planned_start_ns, engine.tz),
                "planned_finish": iso(ep.planned_finish_ns, engine.tz),
                "detected_start": iso(ep.detected_start_ns, engine.tz),
                "detected_finish": iso(ep.detected_finish_ns, engine.tz),
                "deviation": ep.deviation,
                "state": ep.state,
                "present_probability": f"{ep.present_probability:.3f}",
                "evidence_photos": ";".join(files.get(p, p) for p in ep.evidence_photo_ids),
            }
        )
    return rows


def _overlays(path: Path, mode: str) -> dict[str, Overlay]:
    """Last overlay of ``mode`` per photo in a recording."""
    return {m.photo_id: m for m in iter_recording(path) if isinstance(m, Overlay) and m.mode == mode}


def overlaid(photo_jpeg: bytes, overlay: Overlay | None) -> np.ndarray:
    """(H, W, 3) BGR: the photo with an overlay (RGBA layer or RGB composite) blended in."""
    img = decode_bgr(photo_jpeg, "photo")
    if overlay is None or not overlay.image_png:
        return img
    ov: np.ndarray = decode_unchanged(overlay.image_png, "overlay")
    if ov.shape[:2] != img.shape[:2]:
        ov = cv2.resize(ov, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
    if ov.ndim == 3 and ov.shape[2] == 4:
        a = ov[..., 3:4].astype(np.float32) / 255.0
        return (img * (1.0 - a) + ov[..., :3] * a).astype(np.uint8)
    return ov[..., :3] if ov.ndim == 3 else img


def bcf_camera(reg: Registration, offset_m: tuple[float, float, float]) -> dict[str, object]:
    """BCF perspective camera of a registration: view point, direction, up (IFC coordinates = site-local +
    ``offset_m``), vertical field of view (deg), aspect ratio."""
    T = pose_from_tuple(reg.world_from_camera)
    assert reg.intrinsics is not None
    _, fy = focal_xy(reg.intrinsics)
    fov = math.degrees(2.0 * math.atan(reg.intrinsics.height_px / 2.0 / fy))
    return {
        "position": tuple(float(v) for v in T[:3, 3] + np.asarray(offset_m)),
        "direction": tuple(float(v) for v in T[:3, 2]),
        "up": tuple(float(v) for v in -T[:3, 1]),
        "fov_deg": fov,
        "aspect": reg.intrinsics.width_px / reg.intrinsics.height_px,
    }


def issue_groups(engine: ProgressEngine) -> list[tuple[str, str, list[str]]]:
    """(title, description, element GlobalIds): per task (the outermost summary of an element's sub-task), its
    behind / not-built elements; per needs-review annotation, its elements."""
    groups: dict[str, list[str]] = {}
    for gid in engine.global_ids:
        ep = engine.element_progress(gid)
        if ep.deviation in ("behind", "not_built"):
            tid = ep.task_ids[0] if ep.task_ids else "(no task)"
            key = (tid, *engine.task_ancestors.get(tid, ()))[-1]  # the outermost summary task
            groups.setdefault(key, []).append(gid)
    out = []
    for tid, gids in groups.items():
        name = engine.tasks[tid].name if tid in engine.tasks else tid
        devs = sorted({engine.element_progress(g).deviation for g in gids})
        out.append(
            (
                f"{name}: {len(gids)} element(s) {' / '.join(d.replace('_', ' ') for d in devs)}",
                f"Detected from the photos as of {iso(engine.as_of_ns, engine.tz)} (task {tid}).",
                gids,
            )
        )
    for ann in engine.annotations:
        if ann.kind == "status" and ann.status == "needs_review" and ann.element_ids:
            out.append(
                (
                    f"Needs review: {ann.text or ann.annotation_id}",
                    f"Annotation by {ann.author or 'unknown'}.",
                    list(ann.element_ids),
                )
            )
    return out


def export_bcf(engine: ProgressEngine, inputs: RecordedInputs, recording: Path, out: Path, version: str = "3.0") -> int:
    """Write a BCF file of the issue groups; returns the number of topics."""
    if version == "3.0":
        import bcf.v3.bcfxml as bx
        import bcf.v3.model as mdl
        import bcf.v3.visinfo as vi
    elif version == "2.1":
        import bcf.v2.bcfxml as bx  # type: ignore[no-redef]
        import bcf.v2.model as mdl  # type: ignore[no-redef]
        import bcf.v2.visinfo as vi  # type: ignore[no-redef]
    else:
        raise UserError(f"BCF version must be 3.0 or 2.1, got {version!r}")
    assert engine.model is not None
    overlays = _overlays(recording, "progress")
    doc = bx.BcfXml.create_new(project_name=engine.model.site)
    n = 0
    for title, text, gids in issue_groups(engine):
        topic = doc.add_topic(title, text, "constructaide progress", "Issue", "Open")
        best = _best_photo(engine, gids)
        comps = mdl.Components(
            selection=mdl.ComponentSelection(component=[mdl.Component(ifc_guid=g) for g in gids]),
            visibility=mdl.ComponentVisibility(default_visibility=True),
        )
        cam = None
        snapshot = None
        if best is not None and best in inputs.registrations and best in inputs.photos:
            c = bcf_camera(inputs.registrations[best], engine.model.origin_offset_m)
            xyz = lambda v: dict(zip("xyz", v, strict=True))  # noqa: E731
            kw = dict(
                camera_view_point=mdl.Point(**xyz(c["position"])),
                camera_direction=mdl.Direction(**xyz(c["direction"])),
                camera_up_vector=mdl.Direction(**xyz(c["up"])),
                field_of_view=c["fov_deg"],
            )
            if version == "3.0":
                kw["aspect_ratio"] = c["aspect"]
            cam = mdl.PerspectiveCamera(**kw)  # type: ignore[arg-type]
            snapshot = encode_png(overlaid(inputs.photos[best].data, overlays.get(best)))
        info = mdl.VisualizationInfo(components=comps, perspective_camera=cam, guid=topic.guid)
        handler = vi.VisualizationInfoHandler(info, snapshot=snapshot)
        topic.add_visinfo_handler(handler, "snapshot.png" if snapshot else None)
        n += 1
    out.parent.mkdir(parents=True, exist_ok=True)
    doc.save(out)
    return n


def _best_photo(engine: ProgressEngine, gids: list[str]) -> str | None:
    """The processed photo showing most pixels of the elements (ties: latest)."""
    idx = {engine.index_of[g] for g in gids if g in engine.index_of}
    best, score = None, 0
    for rec in sorted(engine.records.values(), key=lambda r: r.capture_time_ns):
        s = sum(px for i, (status, px, _) in rec.cues.items() if i in idx and status == "seen")
        if s >= score and s > 0:
            best, score = rec.photo_id, s
    return best


def export_mp4(inputs: RecordedInputs, recording: Path, out_dir: Path, overlay: str = "", fps: float = 4.0) -> dict:
    """One MP4 per fixed camera of its photos in capture order; returns {camera: frames}."""
    import av

    overlays = _overlays(recording, overlay) if overlay else {}
    by_cam: dict[str, list] = {}
    for p in inputs.photos.values():
        if p.camera_id:
            by_cam.setdefault(p.camera_id, []).append(p)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames: dict[str, int] = {}
    for cam, photos in sorted(by_cam.items()):
        photos.sort(key=lambda p: p.capture_time_ns)
        first = decode_bgr(photos[0].data, "photo")
        h, w = first.shape[:2]
        scale = min(1.0, 1280.0 / w)
        W, H = int(w * scale) // 2 * 2, int(h * scale) // 2 * 2
        with av.open(str(out_dir / f"{cam}.mp4"), "w") as container:
            stream = container.add_stream("libx264", rate=int(round(fps)))
            stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
            for p in photos:
                img = overlaid(p.data, overlays.get(p.photo_id)) if overlay else decode_bgr(p.data, "photo")
                img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
                rgb = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8)
                frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
        frames[cam] = len(photos)
    return frames


def export_gltf(inputs: RecordedInputs, out: Path) -> int:
    """The model GLB re-rooted y-up with a perspective camera node per registered photo; returns the cameras."""
    assert inputs.model is not None
    glb = inputs.model.geometry_glb
    if glb[:4] != b"glTF":
        raise UserError("the recorded model carries no binary glTF geometry")
    json_len = struct.unpack_from("<I", glb, 12)[0]
    doc = json.loads(glb[20 : 20 + json_len])
    rest = glb[20 + json_len :]
    scene = doc["scenes"][doc.get("scene", 0)]
    nodes = doc.setdefault("nodes", [])
    cams = doc.setdefault("cameras", [])
    children = list(scene["nodes"])
    s = math.sqrt(0.5)
    for reg in sorted(inputs.registrations.values(), key=lambda r: (r.capture_time_ns, r.photo_id)):
        camera = registered_camera(reg)
        if camera is None:
            continue
        intr = camera.intrinsics
        _, fy = focal_xy(intr)
        cams.append(
            {
                "type": "perspective",
                "name": reg.photo_id,
                "perspective": {
                    "yfov": 2.0 * math.atan(intr.height_px / 2.0 / fy),
                    "aspectRatio": intr.width_px / intr.height_px,
                    "znear": 0.05,
                },
            }
        )
        # glTF cameras look down -z with +y up; OpenCV cameras down +z with y down
        M = camera.world_from_camera @ np.diag([1.0, -1.0, -1.0, 1.0])
        nodes.append(
            {
                "name": f"camera {reg.camera_id or 'phone'} {reg.photo_id}",
                "camera": len(cams) - 1,
                "matrix": [float(v) for v in M.T.ravel()],
            }
        )
        children.append(len(nodes) - 1)
    # the site frame is z up: one root node turns it y up (-90 deg about x)
    nodes.append({"name": "site (z up)", "rotation": [-s, 0.0, 0.0, s], "children": children})
    scene["nodes"] = [len(nodes) - 1]
    body = json.dumps(doc, separators=(",", ":")).encode()
    body += b" " * (-len(body) % 4)
    out_bytes = b"glTF" + struct.pack("<II", 2, 12 + 8 + len(body) + len(rest)) + struct.pack("<I", len(body))
    out_bytes += b"JSON" + body + rest
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(out_bytes)
    return len(cams)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="constructaide export", description=__doc__.split("\n\n")[0])
    ap.add_argument("format", choices=["ifc", "bcf", "csv", "mp4", "gltf"])
    ap.add_argument("--recording", type=Path, required=True, help="MCAP recording of a pipeline run")
    ap.add_argument("--out", type=Path, required=True, help="output file (mp4: a folder)")
    ap.add_argument("--ifc", type=Path, help="IFC to write the dates into (default: the model's source file)")
    ap.add_argument("--bcf-version", default="3.0", choices=["3.0", "2.1"])
    ap.add_argument("--overlay", default="", help="mp4: overlay mode to blend in (e.g. progress)")
    ap.add_argument("--fps", type=float, default=4.0)
    args = ap.parse_args(argv)
    inputs = read_inputs(args.recording)
    if args.format == "mp4":
        frames = export_mp4(inputs, args.recording, args.out, args.overlay, args.fps)
        print(", ".join(f"{c}: {n} frames" for c, n in frames.items()) + f" -> {args.out}")
        return 0
    if args.format == "gltf":
        print(f"{export_gltf(inputs, args.out)} cameras -> {args.out}")
        return 0
    engine = run_engine(inputs, progress=False)
    if args.format == "ifc":
        src = args.ifc or next((Path(p) for p in inputs.model.source_files if p.lower().endswith(".ifc")), None)  # type: ignore[union-attr]
        if src is None or not src.is_file():
            raise UserError(f"no IFC to write into ({src}); pass --ifc FILE")
        print(f"{export_ifc(engine, src, args.out)} tasks with actual dates -> {args.out}")
    elif args.format == "bcf":
        print(f"{export_bcf(engine, inputs, args.recording, args.out, args.bcf_version)} topics -> {args.out}")
    else:
        rows = report_rows(engine)
        with args.out.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(REPORT_COLUMNS), lineterminator="\n")
            w.writeheader()
            w.writerows(rows)
        print(f"{len(rows)} elements -> {args.out}")
    return 0
