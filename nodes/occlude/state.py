"""The occlude node's durable state: its time-lapse stacks, masks, registrations, sparse cloud and colour model.

One pickle (protocol 5) of the pipeline's fields, without what cannot or need not be kept: the emit callback, the
node context and the GL model view (rebuilt from the kept meshes). Read back only from the node's own state file.
Pure: no bus, no SQLite (the runtime's :class:`~constructaide.runtime.history.Ledger` stores the blob).
"""

from __future__ import annotations

import pickle
from typing import Any

STATE_VERSION = 1
NOT_KEPT = frozenset({"emit", "ctx", "renderer", "config"})


def dump(pipeline: Any) -> bytes:
    fields = {k: v for k, v in vars(pipeline).items() if k not in NOT_KEPT}
    return pickle.dumps({"version": STATE_VERSION, "fields": fields}, protocol=5)


def load_into(pipeline: Any, blob: bytes) -> None:
    doc = pickle.loads(blob)  # noqa: S301 - the node's own state file
    if doc.get("version") != STATE_VERSION:
        raise ValueError(f"occlude state version {doc.get('version')} (this build reads {STATE_VERSION})")
    for k, v in doc["fields"].items():
        if k not in NOT_KEPT:
            setattr(pipeline, k, v)
