"""Zenoh key expressions: the one place topic names are defined.

Every key starts ``constructaide/{site}/``. ``camera`` is a camera id, or ``phone`` for photos
without a fixed camera. Ids must be single key chunks: no ``/``, ``*``, ``$``, ``?``, ``#``.
Multi-machine partitioning subscribes to a subset of a key space, e.g. one register node per
``constructaide/{site}/photo/cam-a``.
"""

from __future__ import annotations

import re

ROOT = "constructaide"
PHONE = "phone"

PHOTO = "constructaide/{site}/photo/{camera}"
# Raw JPEG/PNG bytes from camera software; the ingest node turns them into Photo messages.
UPLOAD = "constructaide/{site}/upload/{camera}"
BIM_MODEL = "constructaide/{site}/bim/model"
BIM_UPDATE = "constructaide/{site}/bim/update"
ANCHORS = "constructaide/{site}/anchors/{photo}"
REGISTRATION = "constructaide/{site}/registration/{camera}/{photo}"
SPARSE = "constructaide/{site}/sparse"
VIEWPOINTS = "constructaide/{site}/viewpoints/{photo}"
NEEDS_ANCHOR = "constructaide/{site}/needs_anchor/{photo}"
OCCLUSION = "constructaide/{site}/occlusion/{kind}/{photo}"
OVERLAY = "constructaide/{site}/overlay/{mode}/{photo}"
ANNOTATION = "constructaide/{site}/annotation/{annotation}"
ERRORS = "constructaide/{site}/errors"
LIVELINESS = "constructaide/{site}/@live/{node}/{instance}"
PHOTO_EVIDENCE = "constructaide/{site}/progress/evidence/{photo}"
PROGRESS = "constructaide/{site}/progress/update"

ALL_TEMPLATES: dict[str, str] = {
    "photo": PHOTO,
    "upload": UPLOAD,
    "bim_model": BIM_MODEL,
    "bim_update": BIM_UPDATE,
    "anchors": ANCHORS,
    "registration": REGISTRATION,
    "sparse": SPARSE,
    "viewpoints": VIEWPOINTS,
    "needs_anchor": NEEDS_ANCHOR,
    "occlusion": OCCLUSION,
    "overlay": OVERLAY,
    "annotation": ANNOTATION,
    "errors": ERRORS,
    "photo_evidence": PHOTO_EVIDENCE,
    "progress": PROGRESS,
}

_BAD_CHUNK = re.compile(r"[/*$?#\s]")
_FIELD = re.compile(r"\{(\w+)\}")


def check_chunk(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a valid single key chunk, else raise ValueError."""
    if not value or _BAD_CHUNK.search(value):
        raise ValueError(f"{what} {value!r} is not usable in a key (no '/', '*', '$', '?', '#', spaces)")
    return value


def key(template: str, **fields: str | None) -> str:
    """Fill a template; ``None`` for ``camera`` becomes ``phone``."""
    filled: dict[str, str] = {}
    for name in _FIELD.findall(template):
        value = fields.get(name)
        if value is None and name == "camera":
            value = PHONE
        if value is None:
            raise KeyError(f"key template {template!r} needs {name!r}")
        filled[name] = check_chunk(str(value), name)
    return template.format(**filled)


def pattern(template: str, **fields: str) -> str:
    """Key expression matching a template: given fields filled, the others ``*``."""
    out = template
    for name in _FIELD.findall(template):
        out = out.replace("{" + name + "}", check_chunk(fields[name], name) if name in fields else "*")
    return out


def site_pattern(site: str) -> str:
    """Every data key of one site (liveliness tokens excluded: they start with '@')."""
    return f"{ROOT}/{check_chunk(site, 'site')}/**"


def parse(template: str, key_str: str) -> dict[str, str] | None:
    """Fields of ``key_str`` if it matches ``template`` exactly, else ``None``."""
    regex = (
        "^"
        + _FIELD.sub(lambda m: f"(?P<{m.group(1)}>[^/]+)", re.escape(template).replace(r"\{", "{").replace(r"\}", "}"))
        + "$"
    )
    m = re.match(regex, key_str)
    return m.groupdict() if m else None
