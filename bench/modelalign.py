"""Model outline polish (nodes/register/modelalign.py, as the register node calls it) on the registrations of demo
recordings, scored against the synthetic site's truth.

    python bench/modelalign.py --run SIZE:SEED:RECORDING [--run ...] [--no-write]

For each registered photo of each recording: the pose the register node published as solved (its latest
registration of the photo that is not failed and not a polish update, ``...+outline``; recordings of code without
the polish have only those) and the pose :func:`nodes.register.modelalign.polish` makes of it with the node's
default parameters (``--ablation JSON``: also with those parameter overrides, rows labelled so), on the recording's BIM
(elements the schedule says stand, terrain plane). Error = mean reprojection error on the photo's truly visible BIM
pixels (every 16th pixel), % of the width: the true camera's pixel, back-projected with the true depth, projected
by the estimate. Only this scoring reads `truth/`. Fixed-camera frames (polished by default) and phone photos
(not polished by default) are reported apart.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import msgspec  # noqa: E402
from _report import code_version, table, write_section  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth, load_ids, true_camera  # noqa: E402
from nodes.progress.batch import iter_recording, read_inputs  # noqa: E402
from nodes.register.bimdepth import MeshDepthLookup  # noqa: E402
from nodes.register.bimsite import BimMeshes  # noqa: E402
from nodes.register.modelalign import AlignParams, polish  # noqa: E402
from schemas.messages import Registration  # noqa: E402


def bim_error_pct(intr_t, wfc_t, intr_e, wfc_e, depth_m: np.ndarray) -> float:  # noqa: ANN001
    """Mean reprojection error (% width) over every 16th pixel with BIM depth (> 0)."""
    h, w = depth_m.shape
    vv, uu = np.mgrid[0:h:16, 0:w:16]
    d = depth_m[vv, uu]
    ok = d > 0
    px = np.c_[uu[ok], vv[ok]].astype(np.float64)
    xy = cam.pixels_to_normalized(intr_t, px)
    p_cam = np.c_[xy, np.ones(len(xy))] * d[ok][:, None]
    p_world = p_cam @ wfc_t[:3, :3].T + wfc_t[:3, 3]
    pe, _ = cam.project_points(intr_e, cam.invert_rigid(wfc_e), p_world)
    return 100.0 * float(np.nanmean(np.linalg.norm(pe - px, axis=1))) / w


def run(
    size: str, seed: int, recording: Path, cache: Path, params: list[AlignParams]
) -> list[list[tuple[bool, float, float, bool, float]]]:
    """Per parameter set: (fixed camera?, error before, error after, accepted, seconds) per registered photo."""
    site = ensure_site(size, seed, cache)
    cams = load_cameras(site)
    inputs = read_inputs(recording)
    assert inputs.model is not None
    bim = BimMeshes()
    bim.set_model(inputs.model)
    lookup = MeshDepthLookup(bim.meshes, elements_at=bim.refs_at(), ground_height_m=bim.terrain_height_m)
    rel_of = {p.photo_id: p.filename for p in inputs.photos.values()}
    solved: dict[str, Registration] = {}
    for msg in iter_recording(recording):  # the latest solved registration of each photo
        if isinstance(msg, Registration) and msg.status != "failed" and not msg.method.endswith("+outline"):
            solved[msg.photo_id] = msg
    out: list[list[tuple[bool, float, float, bool, float]]] = [[] for _ in params]
    try:
        for pid, reg in sorted(solved.items(), key=lambda kv: kv[1].capture_time_ns):
            if reg.status == "failed" or reg.intrinsics is None or pid not in rel_of:
                continue
            rel = next((k for k in cams if k == rel_of[pid] or k.endswith("/" + rel_of[pid])), None)
            if rel is None:
                continue
            gray = cv2.imread(str(site / "photos" / rel), cv2.IMREAD_GRAYSCALE)
            wfc = np.asarray(reg.world_from_camera, np.float64).reshape(4, 4)
            intr_t, wfc_t = true_camera(site, rel, cams)
            depth = load_depth(site, rel) * (load_ids(site, rel) > 0)
            e0 = bim_error_pct(intr_t, wfc_t, reg.intrinsics, wfc, depth)
            for k, p in enumerate(params):
                t0 = time.perf_counter()
                res = polish(lookup, gray, reg.intrinsics, wfc, reg.capture_time_ns, p)
                secs = time.perf_counter() - t0
                e1 = bim_error_pct(intr_t, wfc_t, res.intrinsics, res.world_from_camera, depth)
                out[k].append((reg.camera_id is not None, e0, e1, res.accepted, secs))
    finally:
        lookup.close()
    return out


def summary(rows: list[tuple[bool, float, float, bool, float]], label: str) -> list[object]:
    e0 = np.array([r[1] for r in rows])
    e1 = np.array([r[2] for r in rows])
    if not len(e0):
        return [label, 0, "-", "-", "-", "-", "-", "-", "-"]
    return [
        label,
        len(rows),
        f"{e0.mean():.3f} -> {e1.mean():.3f}",
        f"{np.median(e0):.3f} -> {np.median(e1):.3f}",
        f"{e0.max():.3f} -> {e1.max():.3f}",
        int(sum(r[3] for r in rows)),
        int(np.sum(e1 < e0 - 0.05)),
        int(np.sum(e1 > e0 + 0.05)),
        f"{statistics.median(r[4] for r in rows):.2f}",
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, help="SIZE:SEED:RECORDING (repeatable)")
    ap.add_argument("--cache", type=Path, default=ROOT / ".cache" / "synth")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument(
        "--set", default="{}", help="AlignParams fields to override, JSON (e.g. '{\"max_rotation_deg\": 3}')"
    )
    ap.add_argument(
        "--ablation", default=None, help="also polish with these AlignParams overrides (JSON), rows labelled so"
    )
    ap.add_argument("--section", default="model outline polish", help="BENCHMARKS.md section to write")
    args = ap.parse_args()
    params = [msgspec.convert(msgspec.json.decode(args.set), AlignParams)]
    tags = [""]
    if args.ablation:
        over = msgspec.json.decode(args.ablation)
        params.append(msgspec.convert({**msgspec.json.decode(args.set), **over}, AlignParams))
        tags.append(f" (ablation: {args.ablation})")
    rows: list[list[object]] = []
    pooled: dict[tuple[int, bool], list] = {(k, f): [] for k in range(len(params)) for f in (True, False)}
    names = []
    for spec in args.run:
        size, seed, rec = spec.split(":", 2)
        per_params = run(size, int(seed), Path(rec), args.cache, params)
        names.append(f"{size} seed {seed}: `{Path(rec).name}`")
        for fixed in (True, False):
            for k, res in enumerate(per_params):
                part = [r for r in res if r[0] == fixed]
                pooled[(k, fixed)] += part
                rows.append(summary(part, f"{size} seed {seed}, {'fixed cameras' if fixed else 'phones'}{tags[k]}"))
    for k, tag in enumerate(tags):
        rows.append(summary(pooled[(k, True)], f"all, fixed cameras (polished by default){tag}"))
        rows.append(summary(pooled[(k, False)], f"all, phones (not polished without clicks){tag}"))
    headers = [
        "run",
        "photos",
        "mean error % width (before -> after)",
        "median",
        "worst",
        "polish accepted",
        "better by > 0.05",
        "worse by > 0.05",
        "s per photo (median)",
    ]
    body = (
        f"Code: {code_version()}. Recordings: {'; '.join(names)}. Error: mean reprojection on the photo's truly"
        " visible BIM pixels, % of the width (see the script's docstring); before = the registration the register"
        " node published as solved, after = `modelalign.polish` of it"
        f" ({'the node default parameters' if args.set == '{}' else 'parameters ' + args.set}).\n\n"
        + table(headers, rows)
    )
    print(body)
    if not args.no_write:
        write_section(args.section, body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
