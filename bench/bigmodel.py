"""Big-model scale: a synthetic IFC4 model of N elements (default 50,000; towers of a multi-storey frame, one task
per storey, :mod:`constructaide.synth.bigmodel`) through the shipping code.

* ingest: ``load_site_model`` + ``to_bim_model`` + message encoding in a fresh subprocess (seconds; peak RSS =
  ``VmHWM`` of the child, as ``ru_maxrss`` would carry the parent's peak over the fork); baseline in the same run:
  ifcopenshell's bare geometry iterator over the file (same threads, no metadata, no GLB), as bench/ingest.py;
* the BimModel message: bytes on the bus (one payload);
* overlay: the render node's ``RenderEngine`` (model load = GLB decode + scene build; then ``render`` of a
  1920x1080 photo, ``state4d`` mode, composite + PNG) for a camera that sees the whole model and one that sees
  one tower's corner; median of ``--runs`` after one warm-up;
* late joiner: a zenoh hub session publishes the encoded model latched (``ZenohBus.publish(latched=True)``, what
  the ingest node's ``NodeContext.publish`` does for ``BIM_MODEL``); a new process joins later, subscribes with
  ``fetch_latched=True`` (what a node's latched input does) and reports the time from opening its session until
  it holds the decoded model, and the largest zenoh payload it got (the samples the bus reassembles); once with
  the model as one payload (``chunk_bytes=0``, the baseline: how it went before chunking) and once in parts of
  the default ``chunk_bytes`` (:mod:`constructaide.runtime.chunks`).

    python bench/bigmodel.py [--elements 50000] [--out DIR] [--runs 3] [--no-write]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from bench._report import code_version, median, table, write_section  # noqa: E402
from bench.ingest import run_child as ingest_child  # noqa: E402

JOINER = r"""
import json, sys, threading, time
from constructaide.runtime import BusConfig, open_bus, chunks
sizes = []
_unpack = chunks.Receiver.unpack
def _spy(self, key, payload, attachment):
    sizes.append(len(payload))  # every zenoh sample the subscription gets, before reassembly
    return _unpack(self, key, payload, attachment)
chunks.Receiver.unpack = _spy
from schemas import codec, keys
from schemas.messages import BimModel
port, site = int(sys.argv[1]), sys.argv[2]
got = threading.Event()
box = {}
t0 = time.perf_counter()
with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])) as bus:
    t_open = time.perf_counter()
    def on_model(key, payload):
        box["recv"] = time.perf_counter()
        box["model"] = codec.decode(payload, BimModel)
        box["decoded"] = time.perf_counter()
        got.set()
    sub = bus.subscribe(keys.pattern(keys.BIM_MODEL, site=site), on_model, fetch_latched=True)
    ok = got.wait(120)
    sub.close()
out = {"ok": ok, "open_s": t_open - t0, "samples": len(sizes), "largest_mib": max(sizes, default=0) / 2**20}
if ok:
    out.update(received_s=box["recv"] - t_open, decoded_s=box["decoded"] - t_open, elements=len(box["model"].elements))
out["maxrss_mib"] = [int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")][0] / 1024
print(json.dumps(out))
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "PYOPENGL_PLATFORM": "egl"}


def run_child(code: str, *args: str, timeout: float = 1800) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=timeout
    )
    if proc.returncode != 0:
        raise RuntimeError(f"child {args[:1]} failed: {proc.stderr.strip().splitlines()[-3:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def cameras(model):  # noqa: ANN001, ANN201
    """(name, intrinsics, world_from_camera) for a camera that sees the whole model and one that sees a part."""
    from constructaide.camera import centered_intrinsics, look_at

    lo = np.min([e.bbox_min_m for e in model.elements], axis=0)
    hi = np.max([e.bbox_max_m for e in model.elements], axis=0)
    c = 0.5 * (lo + hi)
    r = float(np.linalg.norm(hi - lo))
    intr = centered_intrinsics(1920, 1080, 1400.0, -0.08, 0.015)
    whole = look_at(c + np.array([0.35, -1.0, 0.45]) * r, c)
    corner = np.array([lo[0], lo[1], lo[2] + 10.0])
    part = look_at(corner + np.array([-12.0, -25.0, 6.0]), corner + np.array([15.0, 15.0, 5.0]))
    return [("whole model", intr, whole), ("part (one tower corner)", intr, part)]


def bench_render(payload: bytes, runs: int) -> tuple[dict[str, float], list[list[object]]]:
    import cv2

    from nodes.render.engine import RenderEngine
    from schemas import codec
    from schemas.messages import BimModel, Photo, Registration

    t0 = time.perf_counter()
    model = codec.decode(payload, BimModel)
    t1 = time.perf_counter()
    engine = RenderEngine()
    engine.set_model(model)
    t2 = time.perf_counter()
    assert engine.scene is not None
    info = {"decode_s": t1 - t0, "set_model_s": t2 - t1, "triangles": float(engine.scene.num_triangles)}
    img = np.random.default_rng(0).integers(80, 160, (1080, 1920, 3), dtype=np.uint8)
    jpeg = bytes(cv2.imencode(".jpg", img)[1])
    at = max((t.planned_finish_ns for t in model.tasks), default=0) + 1
    photo = Photo(site="bench", photo_id="p", capture_time_ns=at, data=jpeg, width_px=1920, height_px=1080)
    rows: list[list[object]] = []
    try:
        for name, intr, wfc in cameras(model):
            reg = Registration(
                site="bench",
                photo_id="p",
                intrinsics=intr,
                world_from_camera=tuple(float(x) for x in np.asarray(wfc).ravel()),
                status="anchor",
            )
            engine.render(photo, reg, "state4d")  # warm-up: uploads the mesh
            ras = engine.rasterizer
            vis = np.ones(engine.scene.num_elements + 1, bool)
            shown = len(np.unique(ras.render(engine.scene, intr, wfc, vis).ids))
            total, raster = [], []
            for _ in range(runs):
                t = time.perf_counter()
                engine.render(photo, reg, "state4d")
                total.append(time.perf_counter() - t)
                t = time.perf_counter()
                ras.render(engine.scene, intr, wfc, vis)
                raster.append(time.perf_counter() - t)
            rows.append([name, shown - 1, median(raster) * 1e3, median(total) * 1e3])
            print(f"render {name}: {rows[-1]}", file=sys.stderr, flush=True)
    finally:
        engine.close()
    return info, rows


def bench_late_join(payload: bytes, runs: int, chunk_bytes: int) -> list[dict]:
    """Late joiners of a hub session that publishes ``payload`` latched with ``chunk_bytes`` (0: one payload)."""
    from constructaide.runtime import BusConfig, open_bus
    from schemas import keys

    out = []
    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], chunk_bytes=chunk_bytes)) as bus:
        port = bus.listen_port()
        bus.publish(keys.key(keys.BIM_MODEL, site="bench"), payload, latched=True)
        for _ in range(runs):
            out.append(run_child(JOINER, str(port), "bench", timeout=300))
            print(f"late join (chunk_bytes {chunk_bytes}): {out[-1]}", file=sys.stderr, flush=True)
    return out


def late_join_rows(payload: bytes, runs: int) -> tuple[list[list[object]], bool]:
    """One row per setting (one payload, then parts of the default chunk_bytes); False when a join failed."""
    from constructaide.runtime.bus import default_chunk_bytes

    rows: list[list[object]] = []
    base: float | None = None
    all_ok = True
    for label, chunk in [("one payload (chunk_bytes 0, as before)", 0), ("parts", default_chunk_bytes())]:
        joins = bench_late_join(payload, runs, chunk)
        ok = [j for j in joins if j.get("ok")]
        all_ok &= len(ok) == len(joins)
        if chunk:
            label = f"parts of {chunk / 2**20:g} MiB (default chunk_bytes)"
        if not ok:
            rows.append([label, f"FAILED 0/{len(joins)}", "", "", "", "", "", ""])
            continue
        decoded = median([j["decoded_s"] for j in ok])
        base = decoded if base is None else base
        rows.append(
            [
                label,
                median([j["received_s"] for j in ok]),
                decoded,
                decoded / base,
                median([j["largest_mib"] for j in ok]),
                int(median([j["samples"] for j in ok])),
                median([j["maxrss_mib"] for j in ok]),
                f"{len(ok)}/{len(joins)}",
            ]
        )
    return rows, all_ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--elements", type=int, default=50_000)
    ap.add_argument("--out", type=Path, default=None, help="folder for the IFC (default: a temp folder)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=3, help="render / late-join repeats (median)")
    ap.add_argument("--ingest-runs", type=int, default=1, help="ingest and baseline repeats (median)")
    ap.add_argument("--no-write", action="store_true", help="print only, do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    from constructaide.synth.bigmodel import write_big_ifc

    code = code_version()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.out or Path(tmp)
        ifc = folder / f"bigmodel-{args.elements}-s{args.seed}.ifc"
        t = time.perf_counter()
        counts = write_big_ifc(ifc, args.elements, args.seed)
        gen_s = time.perf_counter() - t
        ifc_mib = ifc.stat().st_size / 2**20
        print(f"generated {counts} in {gen_s:.1f} s, {ifc_mib:.1f} MiB", file=sys.stderr, flush=True)
        payload_path = Path(tmp) / "bim_model.bin"
        ours = [ingest_child("ingest", [str(ifc)], str(payload_path), timeout=1800) for _ in range(args.ingest_runs)]
        print(f"ingest: {ours}", file=sys.stderr, flush=True)
        bare = [ingest_child("iterator", [str(ifc)], timeout=1800) for _ in range(args.ingest_runs)]
        print(f"bare iterator: {bare}", file=sys.stderr, flush=True)
        payload = payload_path.read_bytes()
    info, render_rows = bench_render(payload, args.runs)
    join_rows, joins_ok = late_join_rows(payload, args.runs)

    ingest_s = median([r["load_s"] + r["glb_s"] + r["encode_s"] for r in ours])
    bare_s = median([r["load_s"] for r in bare])
    ing = ours[0]
    ingest_rows: list[list[object]] = [
        [
            counts["elements"],
            int(ing["elements"]),
            int(ing["tasks"]),
            int(ing["triangles"]),
            round(ifc_mib, 1),
            median([r["load_s"] for r in ours]),
            median([r["glb_s"] for r in ours]),
            median([r["encode_s"] for r in ours]),
            bare_s,
            ingest_s / bare_s,
            median([r["maxrss_mib"] for r in ours]),
            median([r["maxrss_mib"] for r in bare]),
            ing["payload_mib"],
        ]
    ]
    ingest_headers = [
        "elements written",
        "elements ingested",
        "tasks",
        "triangles",
        "IFC MiB",
        "load s",
        "GLB s",
        "encode s",
        "baseline: bare iterator s",
        "ratio (load+GLB+encode)/bare",
        "peak RSS MiB",
        "bare peak RSS MiB",
        "BimModel message MiB",
    ]
    render_headers = ["camera", "elements in view", "ID+depth+shade raster ms", "state4d overlay ms (composite + PNG)"]
    join_headers = [
        "BimModel on the bus",
        "receive s",
        "hold decoded model s",
        "ratio vs one payload",
        "largest zenoh payload MiB",
        "zenoh samples",
        "joiner peak RSS MiB",
        "joins that got it",
    ]
    body = (
        f"Code: {code}. Synthetic IFC4 model (`constructaide.synth.bigmodel`, seed {args.seed}): {counts['towers']} "
        f"tower(s), {counts['storeys']} storeys of a 10x10-bay frame (columns, beams, slabs, walls, windows as "
        f"extruded rectangles), one task per storey; written in {gen_s:.0f} s.\n\n"
        f"Ingest (`load_site_model` + `to_bim_model` + `codec.encode`, fresh subprocess, median of "
        f"{args.ingest_runs}); baseline: ifcopenshell's bare geometry iterator (same threads):\n\n"
        + table(ingest_headers, ingest_rows)
        + f"\n\nRender node (`nodes.render.engine.RenderEngine`): BimModel decode {info['decode_s']:.2f} s, "
        f"`set_model` (GLB decode + scene build) {info['set_model_s']:.2f} s, {int(info['triangles'])} triangles; "
        f"1920x1080 photo with lens distortion, median of {args.runs} after a warm-up:\n\n"
        + table(render_headers, render_rows)
        + f"\n\nLate joiner (zenoh, loopback, model published latched by the hub session, a new process subscribes "
        f"with `fetch_latched=True`; seconds from its session open), median of {args.runs}"
        + ("" if joins_ok else " (SOME JOINS FAILED)")
        + ":\n\n"
        + table(join_headers, join_rows)
        + "\n\n"
        f"Machine load average (1 min) at start / end: {load_before:.1f} / {os.getloadavg()[0]:.1f} (shared "
        f"machine; seconds scale with its load)."
    )
    print(body)
    if not args.no_write:
        name = "bigmodel" if args.elements == 50_000 else f"bigmodel {args.elements} elements"  # one section per size
        write_section(name, body, f"python bench/bigmodel.py --elements {args.elements} --runs {args.runs}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
