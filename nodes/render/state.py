"""The render node's durable state: cached photos, registrations, masks, what is drawn and what waits to be.

One pickle (protocol 5) of those fields; the engine (GL) is rebuilt from the latched BIM model, and a restart
does not redraw what was drawn with the same model revision. Annotations and detected progress are not kept (a
restart draws the progress mode without them until they come again). Read back only from the node's own file.
"""

from __future__ import annotations

import pickle
from typing import Any

STATE_VERSION = 1
FIELDS = ("photos", "registrations", "masks", "dirty", "rendered", "_photo_bytes", "drawn_revision")


def dump(node: Any) -> bytes:
    return pickle.dumps({"version": STATE_VERSION, **{f: getattr(node, f) for f in FIELDS}}, protocol=5)


def load_into(node: Any, blob: bytes) -> None:
    doc = pickle.loads(blob)  # noqa: S301 - the node's own state file
    if doc.get("version") != STATE_VERSION:
        raise ValueError(f"render state version {doc.get('version')} (this build reads {STATE_VERSION})")
    for f in FIELDS:
        setattr(node, f, doc[f])
