"""Partitioned workers: which worker of a node kind handles which camera and which phone photo.

Pure (no bus). ``N`` instances of a node kind (register, occlude, render) share a site's work by key space:
a fixed camera belongs to one worker (its frames arrive on ``constructaide/{site}/photo/<camera>``, so a worker
subscribes to its own cameras' keys only when the site's camera list is known), phone photos
(``photo/phone``) form a shared pool in which each photo belongs to one worker by its id. Ownership is
rendezvous (highest random weight) hashing: stable for a fixed worker set, and adding or removing a worker
moves only the cameras that the new worker wins or the removed one held.

:class:`Router` decides per incoming message (from its key, and the photo id where the key has none): take
it, skip it (another worker's), or park it until its photo turns out to be this worker's (a message keyed by
photo only, e.g. anchor clicks or an occlusion mask, can arrive before the photo itself).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from schemas import keys

TAKE, SKIP, PARK = "take", "skip", "park"


def weight(item: str, worker: str) -> int:
    """The rendezvous weight of ``item`` for ``worker`` (64 bits of blake2b; the same on every host)."""
    return int.from_bytes(hashlib.blake2b(f"{worker}\x00{item}".encode(), digest_size=8).digest(), "big")


def owner(item: str, workers: Iterable[str]) -> str:
    """The worker that owns ``item``: the highest weight (ties broken by the worker name)."""
    ws = list(workers)
    if not ws:
        raise ValueError("no workers")
    return max(ws, key=lambda w: (weight(item, w), w))


def assign(items: Iterable[str], workers: Iterable[str]) -> dict[str, tuple[str, ...]]:
    """``{worker: sorted items it owns}`` (every worker present, possibly with none)."""
    ws = list(workers)
    out: dict[str, list[str]] = {w: [] for w in ws}
    for it in items:
        out[owner(it, ws)].append(it)
    return {w: tuple(sorted(v)) for w, v in out.items()}


def worker_names(count: int) -> tuple[str, ...]:
    """Names of ``count`` workers of a kind: ``"w0"`` .. ``"w<count-1>"``."""
    if count < 1:
        raise ValueError(f"worker count must be >= 1, got {count}")
    return tuple(f"w{i}" for i in range(count))


@dataclass(frozen=True)
class Partition:
    """One worker's share: ``worker`` among ``workers``; ``cameras``: the site's fixed camera ids when known
    (then the worker subscribes to its own cameras' photo keys only), else ``None`` (it subscribes to every
    camera and skips the others' frames)."""

    worker: str
    workers: tuple[str, ...]
    cameras: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.worker not in self.workers:
            raise ValueError(f"worker {self.worker!r} is not one of {self.workers}")
        for c in self.cameras or ():
            keys.check_chunk(c, "camera")
            if c == keys.PHONE:
                raise ValueError(f"{keys.PHONE!r} is the phone pool, not a fixed camera")

    @classmethod
    def parse(cls, spec: str, cameras: Iterable[str] | None = None) -> Partition:
        """From ``"I/N"`` (worker I of N, 0-based) and the site's camera ids."""
        try:
            i_s, n_s = spec.split("/")
            i, n = int(i_s), int(n_s)
        except ValueError:
            raise ValueError(f"partition must be I/N (e.g. 0/2), got {spec!r}") from None
        if not 0 <= i < n:
            raise ValueError(f"partition {spec!r}: I must be in 0..N-1")
        cams = tuple(c for c in (cameras or ()) if c) or None
        names = worker_names(n)
        return cls(names[i], names, cams)

    def spec(self) -> str:
        return f"{self.workers.index(self.worker)}/{len(self.workers)}"

    def owns_camera(self, camera: str) -> bool:
        return owner(camera, self.workers) == self.worker

    def owns_phone_photo(self, photo_id: str) -> bool:
        return owner(photo_id, self.workers) == self.worker

    def my_cameras(self) -> tuple[str, ...] | None:
        return None if self.cameras is None else assign(self.cameras, self.workers)[self.worker]

    def camera_keyexprs(self, template: str, **fields: str) -> list[str]:
        """Key expressions for a template with a ``{camera}`` field: this worker's cameras and the phone pool,
        or every camera (``*``) when the camera list is not known."""
        mine = self.my_cameras()
        if mine is None:
            return [keys.pattern(template, **fields)]
        return [keys.pattern(template, **fields, camera=c) for c in (*mine, keys.PHONE)]


@dataclass
class Router:
    """Per-message decisions for one worker; remembers the photos it took (at most ``max_owned``) and holds
    photo-keyed messages of photos not seen yet (at most ``max_parked``, the oldest dropped first and counted in
    ``parked_dropped``: they were, nearly always, another worker's)."""

    partition: Partition
    max_owned: int = 65536
    max_parked: int = 256
    owned: OrderedDict[str, None] = field(default_factory=OrderedDict)
    parked: OrderedDict[tuple[str, int], tuple[str, Any]] = field(default_factory=OrderedDict)
    parked_dropped: int = 0
    skipped: int = 0
    _seq: int = 0

    def route(self, template: str, key: str, photo_id_of: Callable[[], str | None]) -> str:
        """TAKE, SKIP or PARK for a message on ``key`` (subscribed with ``template``); ``photo_id_of`` reads the
        photo id from the payload (called only when the key does not carry it)."""
        fields = keys.parse(template, key)
        if fields is None or ("camera" not in fields and "photo" not in fields):
            return TAKE  # site-wide (model, updates, annotations, progress)
        camera = fields.get("camera")
        if camera is not None:
            photo = fields.get("photo") or photo_id_of()
            if camera == keys.PHONE:
                mine = photo is not None and self.partition.owns_phone_photo(photo)
            else:
                mine = self.partition.owns_camera(camera)
            if not mine:
                self.skipped += 1
                return SKIP
            if photo is not None:
                self._own(photo)
            return TAKE
        return TAKE if fields["photo"] in self.owned else PARK

    def _own(self, photo_id: str) -> None:
        self.owned[photo_id] = None
        self.owned.move_to_end(photo_id)
        while len(self.owned) > self.max_owned:
            self.owned.popitem(last=False)

    def owns_any(self, photo_ids: Iterable[str]) -> bool:
        return any(p in self.owned for p in photo_ids)

    def park(self, photo_id: str, item: Any) -> None:
        self._seq += 1
        self.parked[(photo_id, self._seq)] = (photo_id, item)
        while len(self.parked) > self.max_parked:
            self.parked.popitem(last=False)
            self.parked_dropped += 1

    def release(self) -> list[Any]:
        """Parked items whose photo is now owned, oldest first (removed from the park)."""
        ready = [k for k, (pid, _) in self.parked.items() if pid in self.owned]
        return [self.parked.pop(k)[1] for k in ready]

    def photo_of_key(self, template: str, key: str) -> str | None:
        fields = keys.parse(template, key)
        return None if fields is None else fields.get("photo")
