"""What the progress node detected in a photo, and a person's review of it (pure: site state in, JSON out).

:func:`detections` lists the elements a photo's :class:`~schemas.messages.PhotoEvidence` covers: the photo's own
reading (state, confidence, cue log-likelihood ratios), the fused progress of the element
(:class:`~schemas.messages.ElementProgress`: P(stands), deviation, detected and planned dates) and the latest review
a person gave (a ``status`` annotation ``built`` / ``not_built`` on the element). :func:`review_annotation` turns a
review (``confirm`` the detection, or say ``built`` / ``not_built``) into the body of such an annotation; published,
the progress node reads it as strong evidence at the photo's capture time (``ProgressEngine.add_annotation``), so a
confirmed or corrected element's estimate follows the person.

:func:`review_queue` lists the readings worth a person's look first: those that disagree with the schedule (an
element read built before its planned start, or not built after its planned finish: the evidence of an ``ahead`` or
``behind``), one per element, the farthest off schedule first.

Errors: ``LookupError`` (unknown photo evidence or element: the API's 404), ``ValueError`` (a bad review: 400).
"""

from __future__ import annotations

from typing import Any

from nodes.workbench.state import SiteState
from schemas.messages import Annotation, BimElement, ElementEvidence, ElementProgress

VERDICTS = ("confirm", "built", "not_built")
"""``confirm``: the photo's reading is right; ``built`` / ``not_built``: what the element truly is in the photo."""
REVIEWABLE = ("built", "not_built")


def _reviews(state: SiteState) -> dict[str, Annotation]:
    """The latest built / not built status annotation of each element (by its modification time)."""
    out: dict[str, Annotation] = {}
    for ann in state.current_annotations():
        if ann.kind != "status" or ann.status not in REVIEWABLE:
            continue
        for gid in ann.element_ids:
            old = out.get(gid)
            if old is None or (ann.modified_ns, ann.created_ns) >= (old.modified_ns, old.created_ns):
                out[gid] = ann
    return out


def _fused(p: ElementProgress | None) -> dict[str, Any] | None:
    if p is None:
        return None
    return {
        "state": p.state,
        "present_probability": p.present_probability,
        "deviation": p.deviation,
        "detected_finish_ns": p.detected_finish_ns,
        "planned_start_ns": p.planned_start_ns,
        "planned_finish_ns": p.planned_finish_ns,
        "num_observations": p.num_observations,
    }


def _reading(e: ElementEvidence) -> dict[str, Any]:
    return {
        "state": e.state,
        "confidence": e.confidence,
        "visible_px": e.visible_px,
        "occluded_fraction": e.occluded_fraction,
        "llr_change": e.llr_change,
        "llr_appearance": e.llr_appearance,
        "llr_points": e.llr_points,
    }


def detections(state: SiteState, photo_id: str, elements: dict[str, BimElement]) -> dict[str, Any]:
    """The ``GET /api/photos/{photo_id}/progress`` document: ``{"photo_id", "as_of_ns", "tz", "elements": [...]}``,
    each element ``{"global_id", "name", "ifc_class", "photo": reading, "fused": progress or null, "review":
    {"annotation_id", "status", "author", "photo_id"} or null}``; readings a person can confirm (built / not built)
    first, then the rest (unknown, occluded), each by visible pixels. ``elements``: the model's elements by id (names
    and classes)."""
    ev = state.evidence.get(photo_id)
    if ev is None:
        raise LookupError(f"no progress evidence for photo {photo_id!r} (is the progress node running?)")
    reviews = _reviews(state)
    rows: list[dict[str, Any]] = []
    order: dict[str, tuple[bool, int, str]] = {}
    for e in ev.elements:
        order[e.global_id] = (e.state not in REVIEWABLE, -e.visible_px, e.global_id)
        el = elements.get(e.global_id)
        ann = reviews.get(e.global_id)
        rows.append(
            {
                "global_id": e.global_id,
                "name": el.name if el is not None else "",
                "ifc_class": el.ifc_class if el is not None else "",
                "photo": _reading(e),
                "fused": _fused(state.progress.get(e.global_id)),
                "review": None
                if ann is None
                else {
                    "annotation_id": ann.annotation_id,
                    "status": ann.status,
                    "author": ann.author,
                    "photo_id": ann.photo_id,
                },
            }
        )
    rows.sort(key=lambda r: order[r["global_id"]])
    return {
        "photo_id": photo_id,
        "capture_time_ns": ev.capture_time_ns,
        "as_of_ns": state.progress_as_of_ns,
        "tz": state.progress_tz,
        "elements": rows,
    }


def review_annotation(state: SiteState, photo_id: str, body: dict[str, Any]) -> dict[str, Any]:
    """The annotation body (for ``Workbench.create_annotation``) of a review ``{"global_id", "verdict": "confirm" |
    "built" | "not_built", "author"?, "text"?}`` of what the progress node read of one element in photo
    ``photo_id``: a ``status`` annotation on that element and photo, its text saying what was detected."""
    gid, verdict = body.get("global_id"), body.get("verdict")
    if not isinstance(gid, str) or not gid:
        raise ValueError("a review needs the element's global_id")
    if verdict not in VERDICTS:
        raise ValueError(f"verdict must be one of {', '.join(VERDICTS)} (got {verdict!r})")
    ev = state.evidence.get(photo_id)
    if ev is None:
        raise LookupError(f"no progress evidence for photo {photo_id!r}")
    seen = next((e for e in ev.elements if e.global_id == gid), None)
    if seen is None:
        raise LookupError(f"element {gid!r} was not read in photo {photo_id!r}")
    detected = f"{seen.state.replace('_', ' ')} ({seen.confidence:.0%})"
    if verdict == "confirm":
        if seen.state not in REVIEWABLE:
            raise ValueError(f"the photo's reading is {seen.state}: nothing to confirm, say built or not_built")
        status, text = seen.state, f"confirms the detection: {detected}"
    elif verdict == seen.state:
        status, text = verdict, f"confirms the detection: {detected}"
    else:
        status, text = verdict, f"corrects the detection {detected}: {verdict.replace('_', ' ')}"
    note = body.get("text")
    if isinstance(note, str) and note.strip():
        text = f"{text}; {note.strip()}"
    author = body.get("author")
    return {
        "photo_id": photo_id,
        "element_ids": [gid],
        "kind": "status",
        "status": status,
        "text": text,
        "author": author if isinstance(author, str) else "",
    }


def review_queue(
    state: SiteState, elements: dict[str, BimElement], limit: int = 50, min_days_off: float = 0.25
) -> list[dict[str, Any]]:
    """Readings that disagree with the plan, one per element not reviewed yet, the farthest off first: ``[{"photo_id",
    "camera_id", "capture_time_ns", "global_id", "name", "ifc_class", "reading", "confidence", "days_off",
    "planned_start_ns", "planned_finish_ns"}]``. An element read ``built`` before its planned start (a possible
    ``ahead``: its earliest such photo) or ``not_built`` after its planned finish (a possible ``behind``: its latest
    such photo); ``days_off`` how far the photo lies outside the planned window, at least ``min_days_off`` (a
    reading an hour after a planned finish is no news). Planned dates come from the progress node's
    ElementProgress."""
    reviewed = set(_reviews(state))
    best: dict[str, dict[str, Any]] = {}
    day = 86_400e9
    for ev in state.evidence.values():
        for e in ev.elements:
            p = state.progress.get(e.global_id)
            if p is None or e.global_id in reviewed or e.state not in REVIEWABLE:
                continue
            t = ev.capture_time_ns
            start = p.planned_start_ns if p.planned_start_ns is not None else p.planned_finish_ns
            if e.state == "built" and start is not None and t < start:
                off = (start - t) / day
            elif e.state == "not_built" and p.planned_finish_ns is not None and t > p.planned_finish_ns:
                off = (t - p.planned_finish_ns) / day
            else:
                continue
            if off < min_days_off:
                continue
            old = best.get(e.global_id)
            if old is not None and old["days_off"] >= off:
                continue
            el = elements.get(e.global_id)
            best[e.global_id] = {
                "photo_id": ev.photo_id,
                "camera_id": ev.camera_id,
                "capture_time_ns": t,
                "global_id": e.global_id,
                "name": el.name if el is not None else "",
                "ifc_class": el.ifc_class if el is not None else "",
                "reading": e.state,
                "confidence": e.confidence,
                "days_off": off,
                "planned_start_ns": p.planned_start_ns,
                "planned_finish_ns": p.planned_finish_ns,
            }
    return sorted(best.values(), key=lambda r: (-r["days_off"], r["global_id"]))[: max(0, limit)]
