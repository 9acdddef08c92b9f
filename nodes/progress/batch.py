"""``constructaide progress --recording FILE --out DIR``: the progress engine over a recorded pipeline run.

Reads the recording's BIM model (and updates), photos, final registrations, occlusion masks, sparse cloud and
status annotations, runs :class:`~nodes.progress.engine.ProgressEngine` (the node's code) over the registered
photos in capture order and writes the batch contract:

* ``DIR/observations.csv``: ``photo_id, filename, camera_id, capture_time, global_id, state, confidence``, one row
  per (photo, element the photo should see); ``state`` in ``built, not_built, occluded, unknown`` (the fused
  estimate at the photo's capture time given every photo);
* ``DIR/elements.csv``: ``global_id, task_id, planned_start, planned_finish, detected_start, detected_finish,
  deviation`` (``ahead, on_time, behind, not_built, unknown``, at the last capture time);

times ISO 8601 with the site's offset, empty when unknown; ``camera_id`` empty for phone photos. Also
``DIR/summary.json`` (counts, as-of time, evidence time per photo, the schedule slip scale learnt from the photos).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime as dt
import json
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar
from zoneinfo import ZoneInfo

from constructaide.errors import UserError
from constructaide.recording import RecordingError, decoded_messages
from nodes.progress.engine import ProgressEngine
from nodes.progress.evidence import EvidenceParams
from nodes.progress.fusion import FusionParams
from nodes.progress.params import EngineParams
from nodes.progress.registrations import ignores_polish
from schemas.messages import (
    Annotation,
    BimModel,
    BimUpdate,
    Message,
    OcclusionMask,
    Photo,
    PhotoEvidence,
    Registration,
    SparseCloud,
)

T = TypeVar("T")

OBSERVATION_COLUMNS = ("photo_id", "filename", "camera_id", "capture_time", "global_id", "state", "confidence")
ELEMENT_COLUMNS = (
    "global_id",
    "task_id",
    "planned_start",
    "planned_finish",
    "detected_start",
    "detected_finish",
    "deviation",
)
STATES = ("built", "not_built", "occluded", "unknown")
DEVIATIONS = ("ahead", "on_time", "behind", "not_built", "unknown")


def iter_recording(path: Path) -> Iterator[Message]:
    """Decoded ConstructAide messages of an MCAP recording in file (= receive, log-time) order (undecodable
    payloads skipped)."""
    if not path.is_file():
        raise UserError(f"no such recording: {path}")
    try:
        for _key, msg in decoded_messages(path):
            yield msg
    except RecordingError as e:
        raise UserError(str(e)) from e


@dataclass
class RecordedInputs:
    """What the progress engine needs from a recording (latest registration / mask per photo and kind)."""

    model: BimModel | None = None
    updates: list[BimUpdate] = field(default_factory=list)
    photos: dict[str, Photo] = field(default_factory=dict)
    registrations: dict[str, Registration] = field(default_factory=dict)
    masks: dict[tuple[str, str], OcclusionMask] = field(default_factory=dict)
    sparse: SparseCloud | None = None
    annotations: list[Annotation] = field(default_factory=list)


def read_inputs(path: Path) -> RecordedInputs:
    out = RecordedInputs()
    for msg in iter_recording(path):
        if isinstance(msg, BimModel):
            out.model, out.updates = msg, []
        elif isinstance(msg, BimUpdate):
            out.updates.append(msg)
        elif isinstance(msg, Photo):
            out.photos[msg.photo_id] = msg
        elif isinstance(msg, Registration):
            if not ignores_polish(out.registrations.get(msg.photo_id), msg):
                out.registrations[msg.photo_id] = msg
        elif isinstance(msg, OcclusionMask):
            out.masks[(msg.photo_id, msg.kind)] = msg
        elif isinstance(msg, SparseCloud):
            out.sparse = msg
        elif isinstance(msg, Annotation):
            out.annotations.append(msg)
    if out.model is None:
        raise UserError(f"{path}: the recording holds no BimModel (was the ingest node running?)")
    return out


def run_engine(
    inputs: RecordedInputs,
    params: EngineParams | None = None,
    progress: bool = True,
    evidence: dict[str, PhotoEvidence] | None = None,
) -> ProgressEngine:
    """Feed a recording's inputs to a fresh engine and process every registered photo in capture order;
    ``evidence``, when given, receives each photo's PhotoEvidence as the streaming node would publish it."""
    engine = ProgressEngine(params)
    assert inputs.model is not None
    engine.set_model(inputs.model)
    for u in inputs.updates:
        engine.apply_update(u)
    for p in inputs.photos.values():
        engine.add_photo(p)
    for r in inputs.registrations.values():
        engine.add_registration(r)
    for m in inputs.masks.values():
        engine.add_mask(m)
    if inputs.sparse is not None:
        engine.set_sparse(inputs.sparse)
    todo = sorted(
        (p for p in inputs.photos.values() if engine.ready(p.photo_id)), key=lambda p: (p.capture_time_ns, p.photo_id)
    )
    for k, p in enumerate(todo, start=1):
        ev, _update = engine.process(p.photo_id)
        if evidence is not None:
            evidence[p.photo_id] = ev
        if progress:
            print(f"\rprogress: evidence {k}/{len(todo)} photos", end="", file=sys.stderr, flush=True)
    if progress and todo:
        print(file=sys.stderr)
    for a in inputs.annotations:
        engine.add_annotation(a)
    return engine


def engine_params_from_json(text: str, **fields: object) -> EngineParams:
    """EngineParams from a JSON object of overrides (its fields; ``evidence`` / ``fusion`` objects for the nested
    parameters) on top of ``fields``. Raises UserError naming an unknown or mistyped field."""
    try:
        over = json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f"--set is not JSON: {e}") from e
    if not isinstance(over, dict):
        raise UserError("--set must be a JSON object")
    over = {**fields, **over}
    nested = {}
    for key, cls in (("evidence", EvidenceParams), ("fusion", FusionParams)):
        sub = over.pop(key, {})
        if not isinstance(sub, dict):
            raise UserError(f"--set: {key} must be an object")
        nested[key] = _make(cls, sub, f"{key}.")
    return _make(EngineParams, {**over, **nested}, "")


def _make(cls: type[T], kwargs: dict, prefix: str) -> T:
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(kwargs) - names)
    if unknown:
        raise UserError(f"--set: unknown parameter {prefix}{unknown[0]} (known: {', '.join(sorted(names))})")
    base = cls()
    out = {k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()}
    for k, v in out.items():
        default = getattr(base, k)
        if not _compatible(default, v):
            like = "a number or null" if default is None else f"like {default!r}"
            raise UserError(f"--set: {prefix}{k} must be {like}, got {v!r}")
    return cls(**out)


def _compatible(default: object, v: object) -> bool:
    """Whether override ``v`` (decoded JSON) fits a parameter whose default is ``default`` (None: optional number)."""
    number = isinstance(v, int | float) and not isinstance(v, bool)
    if isinstance(default, bool):
        return isinstance(v, bool)
    if isinstance(default, int):
        return isinstance(v, int) and not isinstance(v, bool)
    if isinstance(default, float):
        return number
    if default is None:
        return v is None or number
    return isinstance(v, type(default))


def iso(t_ns: int | None, tz: str) -> str:
    """ISO 8601 with the zone's offset (seconds), empty for None."""
    if t_ns is None:
        return ""
    return dt.datetime.fromtimestamp(t_ns / 1e9, ZoneInfo(tz)).isoformat(timespec="seconds")


def observation_rows(engine: ProgressEngine) -> list[dict[str, str]]:
    rows = []
    for rec in sorted(engine.records.values(), key=lambda r: (r.capture_time_ns, r.photo_id)):
        for idx, (status, _px, occ) in sorted(engine.photo_cues(rec).items()):
            gid = engine.global_ids[idx - 1]
            state, conf = engine.photo_state(gid, status, rec.capture_time_ns, occ)
            rows.append(
                {
                    "photo_id": rec.photo_id,
                    "filename": rec.filename,
                    "camera_id": rec.camera_id or "",
                    "capture_time": iso(rec.capture_time_ns, engine.tz),
                    "global_id": gid,
                    "state": state,
                    "confidence": f"{conf:.3f}",
                }
            )
    return rows


def element_rows(engine: ProgressEngine) -> list[dict[str, str]]:
    rows = []
    for gid in engine.global_ids:
        ep = engine.element_progress(gid)
        rows.append(
            {
                "global_id": gid,
                "task_id": ";".join(ep.task_ids),
                "planned_start": iso(ep.planned_start_ns, engine.tz),
                "planned_finish": iso(ep.planned_finish_ns, engine.tz),
                "detected_start": iso(ep.detected_start_ns, engine.tz),
                "detected_finish": iso(ep.detected_finish_ns, engine.tz),
                "deviation": ep.deviation,
            }
        )
    return rows


def write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, str]]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="constructaide progress", description=__doc__.split("\n\n")[0])
    ap.add_argument("--recording", type=Path, required=True, help="MCAP recording of a pipeline run")
    ap.add_argument("--out", type=Path, required=True, help="folder for observations.csv and elements.csv")
    ap.add_argument(
        "--working-width", type=int, default=EngineParams().working_width_px, help="least width photos are read at (px)"
    )
    ap.add_argument(
        "--working-scale", type=float, default=EngineParams().working_scale, help="share of a photo's width read"
    )
    ap.add_argument(
        "--set",
        default="{}",
        metavar="JSON",
        help='engine parameter overrides for experiments, e.g. \'{"support_floor": 0.05, "fusion": '
        '{"built_probability": 0.8}}\' (EngineParams fields; "evidence" / "fusion" hold their own)',
    )
    ap.add_argument("-q", "--quiet", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    inputs = read_inputs(args.recording)
    params = engine_params_from_json(args.set, working_width_px=args.working_width, working_scale=args.working_scale)
    engine = run_engine(inputs, params, progress=not args.quiet)
    args.out.mkdir(parents=True, exist_ok=True)
    obs = observation_rows(engine)
    els = element_rows(engine)
    write_csv(args.out / "observations.csv", OBSERVATION_COLUMNS, obs)
    write_csv(args.out / "elements.csv", ELEMENT_COLUMNS, els)
    times = {r.photo_id: round(r.processing_ms, 1) for r in engine.records.values()}
    summary = {
        "recording": str(args.recording),
        "as_of": iso(engine.as_of_ns, engine.tz),
        "photos": len(inputs.photos),
        "photos_processed": len(engine.records),
        "observations": len(obs),
        "elements": len(els),
        "deviation_counts": {d: sum(r["deviation"] == d for r in els) for d in DEVIATIONS},
        "evidence_ms_per_photo": times,
        "working_width_px": args.working_width,
        "working_scale": args.working_scale,
        "engine_overrides": json.loads(args.set),
        "schedule_slip_days": round(engine.fusion.schedule_width_days, 3),
        "wall_secs": round(time.perf_counter() - t0, 1),
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    if not args.quiet:
        print(f"{len(engine.records)} photos, {len(obs)} observations, {len(els)} elements -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
