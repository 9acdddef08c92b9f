"""``constructaide render``: one overlay of a recorded photo, on demand.

    constructaide render --photo ID --mode MODE [--at DATETIME] --out FILE.png [--recording FILE.mcap]
        [--filter-class IfcWall ...] [--presets FILE.toml]

Reads the BimModel (and updates), the Photo, its Registration and its OcclusionMask (combined
kind preferred) and status Annotations from an MCAP recording (default: the newest
``recordings/*.mcap``), renders with the same engine as the render node and writes a PNG.
"""

from __future__ import annotations

import argparse
import datetime as dt
from pathlib import Path

from constructaide.errors import UserError
from constructaide.recording import RecordingError, decoded_messages
from nodes.render.engine import ALL_MODES, RenderEngine
from schemas.messages import Annotation, BimModel, BimUpdate, ElementFilter, OcclusionMask, Photo, Registration


def parse_datetime_ns(text: str) -> int:
    """UTC ns of an ISO 8601 date/time (no offset = UTC)."""
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError as exc:
        raise UserError(f"--at {text!r} is not an ISO 8601 date/time (e.g. 2026-03-12T11:30+01:00)") from exc
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return int(t.timestamp()) * 10**9 + t.microsecond * 1000


def _newest_recording() -> Path:
    found = sorted(Path("recordings").glob("*.mcap"), key=lambda p: p.stat().st_mtime)
    if not found:
        raise UserError("no --recording given and no recordings/*.mcap here")
    return found[-1]


def _read(path: Path, photo_id: str):
    """The model (and its updates since), photos, registrations, best masks and annotations for ``photo_id``."""
    model = None
    updates: list[BimUpdate] = []
    photos: dict[str, Photo] = {}
    regs: dict[str, Registration] = {}
    masks: dict[str, OcclusionMask] = {}
    anns: list[Annotation] = []
    types = (BimModel, BimUpdate, Photo, Registration, OcclusionMask, Annotation)
    try:
        for _key, msg in decoded_messages(path, types):
            if isinstance(msg, BimModel):
                model, updates = msg, []
            elif isinstance(msg, BimUpdate):
                updates.append(msg)
            elif isinstance(msg, Photo) and msg.photo_id.startswith(photo_id):
                photos[msg.photo_id] = msg
            elif isinstance(msg, Registration) and msg.photo_id.startswith(photo_id) and msg.status != "failed":
                regs[msg.photo_id] = msg
            elif isinstance(msg, OcclusionMask) and msg.photo_id.startswith(photo_id) and msg.status == "ok":
                old = masks.get(msg.photo_id)
                if old is None or msg.kind == "combined" or old.kind != "combined":
                    masks[msg.photo_id] = msg
            elif isinstance(msg, Annotation):
                anns.append(msg)
    except RecordingError as exc:
        raise UserError(f"{exc}") from exc
    except OSError as exc:
        raise UserError(f"cannot read recording {path}: {exc}") from exc
    except ValueError as exc:  # not an MCAP file at all
        raise UserError(
            f"{path} is not a readable MCAP recording ({exc}); try `constructaide recording repair`"
        ) from exc
    return model, updates, photos, regs, masks, anns


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="constructaide render", description=__doc__.splitlines()[0])
    ap.add_argument("--photo", required=True, help="photo id (or a unique prefix)")
    ap.add_argument("--mode", required=True, choices=ALL_MODES)
    ap.add_argument("--at", default=None, help="ISO 8601 date/time of the 4D state (default: capture time)")
    ap.add_argument("--out", required=True, help="output PNG")
    ap.add_argument("--recording", default=None, help="MCAP file (default: newest recordings/*.mcap)")
    ap.add_argument("--filter-class", nargs="*", default=[], help="only these IFC classes")
    ap.add_argument("--filter-storey", nargs="*", default=[], help="only these storeys")
    ap.add_argument("--filter-material", nargs="*", default=[], help="only these material names")
    ap.add_argument("--filter-task", nargs="*", default=[], help="only elements of these task ids")
    ap.add_argument("--filter-element", nargs="*", default=[], help="only these GlobalIds")
    ap.add_argument("--presets", default="", help="material/lighting presets TOML for photoreal")
    ap.add_argument("--layer-only", action="store_true", help="write the RGBA overlay layer, not the composite")
    args = ap.parse_args(argv)

    path = Path(args.recording) if args.recording else _newest_recording()
    if not path.is_file():
        raise UserError(f"recording {path} does not exist")
    if args.presets and not Path(args.presets).is_file():
        raise UserError(f"presets file {args.presets} does not exist")
    at_ns = parse_datetime_ns(args.at) if args.at else None
    model, updates, photos, regs, masks, anns = _read(path, args.photo)
    if model is None:
        raise UserError(f"{path} holds no BimModel")
    if not photos:
        raise UserError(f"{path} holds no photo with id starting {args.photo!r}")
    if len(photos) > 1:
        raise UserError(f"photo id prefix {args.photo!r} is ambiguous: {', '.join(sorted(photos)[:5])}")
    ((pid, photo),) = photos.items()
    reg = regs.get(pid)
    if reg is None:
        raise UserError(f"photo {pid} has no successful registration in {path}")
    flt = ElementFilter(
        ifc_classes=tuple(args.filter_class),
        storeys=tuple(args.filter_storey),
        materials=tuple(args.filter_material),
        task_ids=tuple(args.filter_task),
        element_ids=tuple(args.filter_element),
    )
    engine = RenderEngine(presets_file=args.presets)
    try:
        engine.set_model(model)
        for up in updates:
            engine.apply_update(up)
        for ann in anns:
            engine.add_annotation(ann)
        ov = engine.render(photo, reg, args.mode, at_ns, flt, masks.get(pid), composite_photo=not args.layer_only)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    finally:
        engine.close()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(ov.image_png)
    legend = "; ".join(e.label for e in ov.legend)
    print(f"wrote {out} ({args.mode}, {ov.processing_ms:.0f} ms){': ' + legend if legend else ''}")
    return 0
