"""What the register node holds between messages (pure): photos waiting for anchors, clicks waiting for their
photo, recently registered photos (late clicks can still re-anchor them), and the message conversions at the shell.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from nodes.register.photo import FrameImage, PhotoInput
from schemas.messages import AnchorClicks, Photo, Registration

if TYPE_CHECKING:
    from nodes.register.streaming import Outcome


def photo_input(msg: Photo) -> PhotoInput:
    """The registrar's view of a Photo message (pixels decoded lazily)."""
    if not msg.data:
        raise ValueError(f"photo {msg.photo_id} has no image data")
    return PhotoInput(
        photo_id=msg.photo_id,
        image=FrameImage(data=msg.data),
        camera_id=msg.camera_id,
        capture_time_ns=msg.capture_time_ns,
        focal_px=msg.focal_px,
        width_px=msg.width_px,
        height_px=msg.height_px,
        gps=msg.gps,
    )


def click_arrays(clicks: AnchorClicks) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) px and model points (N, 3) m of anchor clicks."""
    px = np.array([p.pixel_px for p in clicks.points], np.float64)
    pts = np.array([p.point_in_world_m for p in clicks.points], np.float64)
    return px, pts


def dropped_registration(site: str, photo: Photo, max_pending: int) -> Registration:
    """The failed Registration of a photo pushed out of the full waiting queue."""
    return Registration(
        site=site,
        photo_id=photo.photo_id,
        camera_id=photo.camera_id,
        capture_time_ns=photo.capture_time_ns,
        status="failed",
        message=f"dropped from the waiting queue ({max_pending} photos wait for anchors)",
    )


def late_clicks_note(
    photo_id: str, off_px: float, width_px: int, max_frac: float, kept_photos: int
) -> tuple[bool, str]:
    """Clicks for a photo registered meanwhile whose pixels are no longer kept (a request answered after the photo
    registered on its own), ``off_px`` (median) from its registration: whether they confirm it (within ``max_frac``
    of the width) and what to say (logged when they do, the error when they do not: they are kept for the photo's
    next push, which re-anchors it)."""
    if off_px <= max_frac * width_px:
        return True, f"clicks for {photo_id} confirm its registration (median {off_px:.1f} px off); it registered first"
    return False, (
        f"clicks for {photo_id} disagree with its registration (median {off_px:.1f} px off) and its pixels are no "
        f"longer kept (only the last {kept_photos} photos are): the clicks are kept; push the photo again to "
        "re-anchor it with them"
    )


class Inbox:
    """Bounded holding areas, oldest out first: ``pending`` photos (not registrable yet), ``pending_anchors``
    (clicks whose photo has not come), ``recent`` registered photos (0 kept when ``max_recent`` is 0)."""

    def __init__(self, max_pending: int, max_pending_anchors: int, max_recent: int) -> None:
        if max_pending < 1:
            raise ValueError("max_pending must be >= 1")
        self.max_pending = max_pending
        self.max_pending_anchors = max_pending_anchors
        self.max_recent = max_recent
        self.pending: OrderedDict[str, Photo] = OrderedDict()
        self.pending_anchors: OrderedDict[str, AnchorClicks] = OrderedDict()
        self.recent: OrderedDict[str, Photo] = OrderedDict()
        self.asked_groups: set[str] = set()
        self.unreported: set[str] = set()
        """Waiting photos no Registration has been published for (they came before any registration)."""

    def __setstate__(self, state: dict) -> None:
        state.setdefault("unreported", set())  # saved before the field existed
        self.__dict__.update(state)

    def enqueue(self, photo: Photo) -> list[Photo]:
        """Let a photo wait; returns the photos pushed out (oldest first)."""
        self.pending[photo.photo_id] = photo
        dropped = []
        while len(self.pending) > self.max_pending:
            dropped.append(self.pending.popitem(last=False)[1])
            self.unreported.discard(dropped[-1].photo_id)  # the caller publishes its (failed) Registration
        return dropped

    def keep_anchors(self, clicks: AnchorClicks) -> None:
        """Hold clicks until their photo is pushed."""
        self.pending_anchors[clicks.photo_id] = clicks
        while len(self.pending_anchors) > self.max_pending_anchors:
            self.pending_anchors.popitem(last=False)

    def remember(self, photo: Photo) -> None:
        """Keep a registered photo's bytes (the most recent ``max_recent``)."""
        if self.max_recent <= 0:
            return
        self.recent[photo.photo_id] = photo
        self.recent.move_to_end(photo.photo_id)
        while len(self.recent) > self.max_recent:
            self.recent.popitem(last=False)

    def check_clicks_on_image(self, clicks: AnchorClicks) -> None:
        """Raise ValueError naming the clicks that lie off their photo (when the photo is held here)."""
        known = self.pending.get(clicks.photo_id) or self.recent.get(clicks.photo_id)
        if known is None or known.width_px <= 0 or known.height_px <= 0:
            return
        w, h = known.width_px, known.height_px
        off = [i for i, p in enumerate(clicks.points) if not (0 <= p.pixel_px[0] <= w and 0 <= p.pixel_px[1] <= h)]
        if off:
            raise ValueError(f"anchor clicks for {clicks.photo_id}: point(s) {off} off the {w}x{h} image")

    def photo_for_clicks(self, photo_id: str) -> Photo | None:
        """The photo clicks arrived for: taken out of the waiting queue, else a recent one, else None."""
        return self.pending.pop(photo_id, None) or self.recent.get(photo_id)

    def first_ask(self, photo: Photo) -> bool:
        """True the first time a photo of its camera (or the phone photo itself) is to be asked for anchors."""
        group = photo.camera_id or f"phone:{photo.photo_id}"
        if group in self.asked_groups:
            return False
        self.asked_groups.add(group)
        return True

    def waiting_by_time(self) -> list[Photo]:
        """The waiting photos in capture-time order."""
        return sorted(self.pending.values(), key=lambda p: p.capture_time_ns)

    def retry_waiting(
        self, retry: Callable[[PhotoInput], Outcome | None], publish: Callable[[Outcome, bool], None]
    ) -> None:
        """Try the waiting photos again (``retry``, oldest first) while the map grows: each registration can
        connect others. A registered one leaves the queue, published without a request; a still-failed one is
        published only when it came before any registration and was never reported (now the map says why)."""
        grown = True
        while grown and self.pending:
            grown = False
            for msg in self.waiting_by_time():
                out = retry(photo_input(msg))
                if out is None or out.registration.status == "failed":
                    if out is not None and msg.photo_id in self.unreported:
                        publish(out, True)
                    continue
                del self.pending[msg.photo_id]
                publish(out, False)
                self.remember(msg)
                grown = grown or out.map_changed
