"""BIM ingest cost: seconds and peak memory to load each IFC model into a SiteModel and encode
its BimModel (GLB), per model in ../shared/data/ifc/ and the Schependomlaan design parts together.

Each measurement runs in a fresh subprocess (peak RSS = ``ru_maxrss`` of that child, which
includes the Python + ifcopenshell baseline, reported separately as "import only"). Baseline
for the ratio: ifcopenshell's bare geometry iterator over the same files (same threads, no
metadata, no GLB). Median of several runs.

    python bench/ingest.py [--quick]
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _report import median, table, write_section  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

CHILD = r"""
import json, resource, sys, time
mode, out_path, paths = sys.argv[1], sys.argv[2], sys.argv[3:]
out = {}
if mode == "ingest":
    from constructaide.bim.ifc import load_site_model
    from nodes.ingest.revisions import to_bim_model
    from schemas import codec
    t0 = time.perf_counter()
    site = load_site_model(paths, tz="UTC")
    t1 = time.perf_counter()
    bim = to_bim_model(site, "bench", "r1")
    t2 = time.perf_counter()
    payload = codec.encode(bim)
    t3 = time.perf_counter()
    if out_path != "-":
        open(out_path, "wb").write(payload)
    out = {"load_s": t1 - t0, "glb_s": t2 - t1, "encode_s": t3 - t2, "elements": len(site.elements),
           "tasks": len(site.tasks), "triangles": int(sum(len(m.faces) for m in site.meshes.values())),
           "glb_mib": len(bim.geometry_glb) / 2**20, "payload_mib": len(payload) / 2**20}
elif mode == "iterator":
    import os
    import ifcopenshell, ifcopenshell.geom
    t0 = time.perf_counter()
    n = 0
    for p in paths:
        f = ifcopenshell.open(p)
        s = ifcopenshell.geom.settings(); s.set("use-world-coords", True)
        it = ifcopenshell.geom.iterator(s, f, min(os.cpu_count() or 1, 8))
        if it.initialize():
            while True:
                n += 1
                if not it.next():
                    break
    out = {"load_s": time.perf_counter() - t0, "shapes": n}
else:
    import ifcopenshell, ifcopenshell.geom, trimesh, constructaide.bim.ifc  # noqa: F401
out["maxrss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""
"""One fresh process per measurement: ``mode`` ingest (load + GLB + encode; the BimModel payload written to
``out_path`` unless "-"), iterator (ifcopenshell's bare geometry iterator, the baseline) or import (start-up
only); prints one JSON line (seconds, sizes, peak RSS)."""


def run_child(mode: str, paths: list[str], out_path: str = "-", timeout: float | None = None) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, mode, out_path, *paths],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=timeout,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{mode} {paths}: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="1 run per model instead of 3")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args(argv)
    runs = 1 if args.quick else 3
    cases: list[tuple[str, list[str]]] = [(Path(p).name, [p]) for p in sorted(glob.glob(str(DATA / "ifc" / "*.ifc")))]
    parts = sorted(glob.glob(str(DATA / "schependomlaan" / "design-parts" / "*.ifc")))
    if parts:
        cases.append((f"Schependomlaan {len(parts)} parts together", parts))
    if not cases:
        print(f"no IFC data under {DATA}", file=sys.stderr)
        return 1
    load_before = os.getloadavg()[0]
    base_rss = median([run_child("import", [])["maxrss_mib"] for _ in range(runs)])
    rows = []
    for name, paths in cases:
        ours = [run_child("ingest", paths) for _ in range(runs)]
        bare = [run_child("iterator", paths) for _ in range(runs)]
        load_s = median([r["load_s"] for r in ours])
        glb_s = median([r["glb_s"] for r in ours])
        bare_s = median([r["load_s"] for r in bare])
        size_mib = sum(Path(p).stat().st_size for p in paths) / 2**20
        rows.append(
            [
                name,
                round(size_mib, 2),
                int(ours[0]["elements"]),
                int(ours[0]["triangles"]),
                load_s,
                glb_s,
                bare_s,
                (load_s + glb_s) / bare_s,
                median([r["maxrss_mib"] for r in ours]),
                median([r["maxrss_mib"] for r in bare]),
                ours[0]["glb_mib"],
            ]
        )
        print(f"{name}: load {load_s:.2f} s, glb {glb_s:.2f} s, bare iterator {bare_s:.2f} s", file=sys.stderr)
    headers = [
        "model",
        "IFC MiB",
        "elements",
        "triangles",
        "load s",
        "GLB s",
        "bare iterator s",
        "ratio (load+GLB)/bare",
        "peak RSS MiB",
        "bare peak RSS MiB",
        "GLB MiB",
    ]
    body = (
        f"IFC -> SiteModel (`load_site_model`: geometry iterator with 2 threads, metadata, IFC schedule) and "
        f"SiteModel -> BimModel GLB (`to_bim_model`), each in a fresh subprocess, median of {runs} run(s). "
        f"Baseline: ifcopenshell's bare geometry iterator (open + iterate, no metadata). Peak RSS includes "
        f"the interpreter with ifcopenshell/trimesh imported: {base_rss:.0f} MiB for imports alone. "
        f"Machine load average (1 min) at start / end: {load_before:.1f} / {os.getloadavg()[0]:.1f} "
        f"(the machine is shared; seconds scale with it).\n\n" + table(headers, rows)
    )
    print(body)
    if not args.no_write:
        write_section("ingest", body, "python bench/ingest.py" + (" --quick" if args.quick else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
