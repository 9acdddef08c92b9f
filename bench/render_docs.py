"""Render every overlay mode (and the photoreal composite) on two synthetic-site frames into docs/.

Development/scoring script: it reads the synthetic site's TRUE cameras (no registration needed) and
its as-built log (truth/element_states.json) to give the schedule actual dates, standing in for the
actuals a site manager would enter. System code never does this.

    python bench/render_docs.py [--size small] [--out docs]
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import constructaide  # noqa: E402,F401  (sets PYOPENGL_PLATFORM)
from constructaide.bim.ifc import load_site_model  # noqa: E402
from constructaide.modelscene import scene_from_model  # noqa: E402
from constructaide.modelview import GLRasterizer  # noqa: E402
from constructaide.synth import ensure_site, truth  # noqa: E402
from nodes.ingest.revisions import to_bim_model  # noqa: E402
from nodes.render.overlays import MODES, ScheduleView, composite, render_overlay  # noqa: E402
from nodes.render.photoreal import PhotorealRenderer  # noqa: E402
from nodes.render.sun import sun_direction_in_site, sun_position  # noqa: E402
from schemas.messages import BimModel, ScheduleTask  # noqa: E402


def _ns(iso: str | None) -> int | None:
    return None if iso is None else int(dt.datetime.fromisoformat(iso).timestamp() * 1e9)


def site_model_with_actuals(site: Path) -> BimModel:
    """BimModel of the site IFC, with one task per element carrying the as-built dates of the site log."""
    sm = load_site_model([site / "model/building.ifc"], tz="Europe/Amsterdam")
    model = to_bim_model(sm, "synth", "r1")
    states = truth.element_states(site)["elements"]
    tasks = []
    for t in model.tasks:
        for gid in t.element_ids:
            s = states.get(gid, {})
            tasks.append(
                ScheduleTask(
                    task_id=f"{t.task_id}:{gid}",
                    name=t.name,
                    planned_start_ns=_ns(s.get("planned_start")) or t.planned_start_ns,
                    planned_finish_ns=_ns(s.get("planned_finish")) or t.planned_finish_ns,
                    actual_start_ns=_ns(s.get("actual_start")),
                    actual_finish_ns=_ns(s.get("actual_finish")),
                    element_ids=(gid,),
                )
            )
    import msgspec

    return msgspec.structs.replace(model, tasks=tuple(tasks))


def save_png(img: np.ndarray, path: Path, width: int = 960) -> int:
    im = Image.fromarray(img)
    if im.width > width:
        im = im.resize((width, round(im.height * width / im.width)), Image.LANCZOS)
    im.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)
    return path.stat().st_size


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="small")
    ap.add_argument("--out", default=str(ROOT / "docs"))
    args = ap.parse_args(argv)
    site = ensure_site(args.size, 0, ROOT / ".cache" / "synth")
    model = site_model_with_actuals(site)
    scene = scene_from_model(model)
    schedule = ScheduleView.from_model(model, scene)
    cams = truth.load_cameras(site)
    rels = sorted(cams)
    fixed = [r for r in rels if r.startswith("cam-north")]
    phone = [r for r in rels if r.startswith("phone")]
    # Fixed camera mid-period, and the phone photo taken farthest from the building (whole facade in view).
    far = max(phone, key=lambda r: float(np.linalg.norm(np.asarray(cams[r]["world_from_camera"])[:2, 3])))
    frames = {"a": fixed[len(fixed) // 2], "b": far}
    ras = GLRasterizer()
    photoreal = PhotorealRenderer(ras)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for tag, rel in frames.items():
        intr, wfc = truth.true_camera(site, rel, cams)
        at = int(cams[rel]["capture_time_utc_ns"])
        photo = np.asarray(Image.open(site / "photos" / rel).convert("RGB"))
        occ = truth.load_mask(site, rel, "static") | truth.load_mask(site, rel, "dynamic")
        for mode in MODES:
            res = render_overlay(ras, scene, schedule, intr, wfc, mode, at, occlusion=occ)
            size = save_png(composite(photo, res.layer_rgba), out / f"overlay_{mode}_{tag}.png")
            print(f"overlay_{mode}_{tag}.png  {rel}  {size / 1024:.0f} KB")
        sun = sun_position(51.8583, 5.8647, at)
        built = schedule.built(at, basis="actual")
        img = photoreal.render(
            scene, built | schedule.future(at), intr, wfc, photo, sun_direction_in_site(sun), occlusion=occ
        )
        size = save_png(img, out / f"overlay_photoreal_{tag}.png")
        sun_txt = f"sun az {sun.azimuth_deg:.1f} el {sun.elevation_deg:.1f}"
        print(f"overlay_photoreal_{tag}.png  {rel}  {size / 1024:.0f} KB  {sun_txt}")
    ras.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
