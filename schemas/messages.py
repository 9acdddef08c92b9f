"""Every message that crosses the ConstructAide bus.

Conventions (see ``schemas/README.md`` for the evolution rules):

* All structs are frozen msgspec Structs; bus messages are members of the tagged union
  :data:`Message` (tag field ``"type"``, tag value = class name).
* Times are integer nanoseconds since the Unix epoch, UTC (``*_ns``); the site's IANA zone
  travels beside them (``tz``) so local dates can be shown.
* Camera frame is OpenCV's: x right, y down, z forward. ``world_from_camera`` is a row-major
  4x4 rigid transform (16 floats) mapping a point in camera coordinates to model/world
  coordinates in metres. Pixels use the OpenCV convention: (0, 0) is the centre of the
  top-left pixel; ``u`` to the right, ``v`` down.
* Large arrays travel as raw little-endian bytes with their dtype and shape in the field name
  or docstring (``points_xyz_f32``: float32, shape (N, 3)).
"""

from __future__ import annotations

from typing import Literal

import msgspec


class _Base(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=False):
    """Base for embedded (non-bus) structs."""


class Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type", tag=True):
    """Base for bus messages; every message names its site."""

    site: str


# ---------------------------------------------------------------------------
# Embedded structs
# ---------------------------------------------------------------------------


class GeoPoint(_Base, frozen=True, kw_only=True):
    """WGS84 position: degrees and metres above the ellipsoid (or sea level when unknown)."""

    lat_deg: float
    lon_deg: float
    alt_m: float | None = None


class Intrinsics(_Base, frozen=True, kw_only=True):
    """Pinhole camera with two radial distortion terms (Brown model, normalised coordinates).

    ``x_d = x (1 + k1 r^2 + k2 r^4)`` with ``x = X/Z`` and ``r^2 = x^2 + y^2``; pixel
    ``u = f_px * x_d + cx_px``, ``v = f_px * fy_over_fx * y_d + cy_px``. ``f_px`` is the horizontal focal
    ``fx``; ``fy_over_fx`` the pixel aspect ratio ``fy / fx`` (1.0 = square pixels, the default and what
    older messages mean).
    """

    width_px: int
    height_px: int
    f_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    fy_over_fx: float = 1.0


class AnchorPoint(_Base, frozen=True, kw_only=True):
    """One user click: a pixel in the photo and the model point it shows (model units, metres)."""

    pixel_px: tuple[float, float]
    point_in_world_m: tuple[float, float, float]


class BimElement(_Base, frozen=True, kw_only=True):
    """One building element with geometry.

    ``geometry_ref`` names the mesh node carrying this element in the model's GLB
    (by default the GlobalId itself).
    """

    global_id: str
    ifc_class: str
    name: str = ""
    storey: str = ""
    type_name: str = ""
    material: str = ""
    geometry_ref: str = ""
    bbox_min_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bbox_max_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


class ScheduleTask(_Base, frozen=True, kw_only=True):
    """A construction task and the elements it builds. Times in UTC ns; actuals optional."""

    task_id: str
    name: str
    planned_start_ns: int
    planned_finish_ns: int
    actual_start_ns: int | None = None
    actual_finish_ns: int | None = None
    element_ids: tuple[str, ...] = ()
    predecessor_ids: tuple[str, ...] = ()
    # "construction" builds its elements, "demolition" removes them, "temporary" both.
    task_type: Literal["construction", "demolition", "temporary", "other"] = "construction"
    # The summary task this one is nested in (IfcRelNests); a summary's progress rolls up its sub-tasks'.
    parent_id: str | None = None


class ViewpointNeighbour(_Base, frozen=True, kw_only=True):
    """A photo taken from nearly the same viewpoint.

    ``this_from_neighbour`` is a row-major 3x3 homography mapping pixels of the neighbour
    photo to pixels of this photo.
    """

    photo_id: str
    this_from_neighbour: tuple[float, ...]
    inlier_ratio: float
    num_matches: int


class LegendEntry(_Base, frozen=True, kw_only=True):
    label: str
    rgba: tuple[int, int, int, int]


class ElementFilter(_Base, frozen=True, kw_only=True):
    """Selection of elements; empty tuples mean "no restriction" on that attribute."""

    ifc_classes: tuple[str, ...] = ()
    storeys: tuple[str, ...] = ()
    materials: tuple[str, ...] = ()
    task_ids: tuple[str, ...] = ()
    element_ids: tuple[str, ...] = ()


class ElementEvidence(_Base, frozen=True, kw_only=True):
    """What one photo shows of one element (``PhotoEvidence``).

    ``state``: ``built`` / ``not_built`` (the fused estimate at the photo's capture time, given every photo so far),
    ``occluded`` (the occlusion masks cover the element's region), ``unknown`` (too few pixels or evidence).
    ``confidence``: probability of ``state`` (occluded: the covered fraction). Cue log-likelihood ratios (natural
    log, present vs absent; 0 = no evidence): ``llr_change`` for the element having appeared between
    ``reference_ns`` and the capture (change against the same camera's earlier frames), ``llr_points`` (sparse
    points on / behind its surface), ``llr_appearance`` (colours against its material and what stands behind it).
    Pixel counts are at the working resolution of ``PhotoEvidence``.
    """

    global_id: str
    state: Literal["built", "not_built", "occluded", "unknown"]
    confidence: float = 0.0
    visible_px: int = 0
    occluded_fraction: float = 0.0
    llr_change: float = 0.0
    llr_points: float = 0.0
    llr_appearance: float = 0.0
    reference_ns: int = 0
    changed_fraction: float | None = None


class ElementProgress(_Base, frozen=True, kw_only=True):
    """Fused progress of one element at ``ProgressUpdate.as_of_ns``.

    ``present_probability``: P(the element stands). ``last_absent_ns`` / ``first_present_ns``: the most probable
    interval in which it was finished (``None``: unbounded; both ``None`` when never seen), with probability
    ``finish_probability``; ``detected_finish_ns`` its middle in working time (``None`` when a bound is unknown);
    ``detected_start_ns``: the latest time it was still absent (construction happened after). Planned dates are the
    union of the tasks that build it. ``deviation``: ``ahead`` (finished before its planned start), ``on_time``,
    ``behind`` (finished after its planned finish), ``not_built`` (still absent after its planned finish),
    ``unknown`` (no evidence).
    """

    global_id: str
    state: Literal["built", "not_built", "unknown"]
    present_probability: float = 0.0
    detected_start_ns: int | None = None
    detected_finish_ns: int | None = None
    last_absent_ns: int | None = None
    first_present_ns: int | None = None
    finish_probability: float = 0.0
    planned_start_ns: int | None = None
    planned_finish_ns: int | None = None
    deviation: Literal["ahead", "on_time", "behind", "not_built", "unknown"] = "unknown"
    task_ids: tuple[str, ...] = ()
    num_observations: int = 0
    evidence_photo_ids: tuple[str, ...] = ()


class TaskProgress(_Base, frozen=True, kw_only=True):
    """Fused progress of one schedule task: actual dates from its elements' detected dates (start: the earliest
    element's ``detected_start_ns``; finish: the latest ``detected_finish_ns`` once all stand), percent complete
    (expected share of its elements standing) against the planned percent (linear over the planned window)."""

    task_id: str
    name: str = ""
    planned_start_ns: int = 0
    planned_finish_ns: int = 0
    actual_start_ns: int | None = None
    actual_finish_ns: int | None = None
    percent_complete: float = 0.0
    planned_percent: float = 0.0
    deviation: Literal["ahead", "on_time", "behind", "not_built", "unknown"] = "unknown"
    num_elements: int = 0
    num_built: int = 0
    num_observed: int = 0


class StoreyProgress(_Base, frozen=True, kw_only=True):
    """Planned vs detected share of a storey's elements standing at ``ProgressUpdate.as_of_ns`` (one S-curve
    point; planned counts each element's share of its task's window linearly)."""

    storey: str
    planned_fraction: float = 0.0
    detected_fraction: float = 0.0
    num_elements: int = 0


# ---------------------------------------------------------------------------
# Bus messages
# ---------------------------------------------------------------------------


class Photo(Message, frozen=True, kw_only=True):
    """A photo as pushed by a camera or a person.

    ``photo_id`` is a content hash of ``data`` (sha256, first 16 hex characters), so the same
    photo pushed twice is the same photo. ``camera_id`` is ``None`` for phone photos.
    ``focal_px`` is the focal length in pixels of the stored image when EXIF allows it.
    """

    photo_id: str
    camera_id: str | None = None
    capture_time_ns: int
    tz: str = "UTC"
    media_type: Literal["image/jpeg", "image/png"] = "image/jpeg"
    data: bytes
    width_px: int = 0
    height_px: int = 0
    focal_px: float | None = None
    focal_35mm_mm: float | None = None
    gps: GeoPoint | None = None
    filename: str = ""
    source: str = ""


class BimModel(Message, frozen=True, kw_only=True):
    """A whole site model revision.

    ``geometry_glb`` is a binary glTF with one mesh node per element named by
    ``BimElement.geometry_ref``, in site-local metres (z up). ``origin_offset_m`` is the
    offset that was subtracted from map coordinates to make them site-local.
    """

    revision: str
    elements: tuple[BimElement, ...] = ()
    tasks: tuple[ScheduleTask, ...] = ()
    geometry_glb: bytes = b""
    origin_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    crs_name: str = ""
    gps: GeoPoint | None = None
    tz: str = "UTC"
    source_files: tuple[str, ...] = ()
    terrain_height_m: float | None = None


class BimUpdate(Message, frozen=True, kw_only=True):
    """Difference between two model revisions, by GlobalId.

    ``geometry_glb`` carries the meshes of ``added`` and ``changed`` elements only; ``tasks``
    replaces the whole schedule when not ``None``.
    """

    base_revision: str
    revision: str
    added: tuple[BimElement, ...] = ()
    removed: tuple[str, ...] = ()
    changed: tuple[BimElement, ...] = ()
    geometry_glb: bytes = b""
    tasks: tuple[ScheduleTask, ...] | None = None


class AnchorClicks(Message, frozen=True, kw_only=True):
    """2D-3D correspondences clicked by a user for one photo (>= 4 needed)."""

    photo_id: str
    image_name: str = ""
    points: tuple[AnchorPoint, ...]
    focal_px: float | None = None
    author: str = ""


class Registration(Message, frozen=True, kw_only=True):
    """A photo's camera in the model frame.

    ``status``: ``anchor`` (solved from clicks), ``auto`` (solved from image matches),
    ``failed``. ``method`` says which path solved it (``anchor``, ``homography``,
    ``pnp``, ``fastpath``, ``batch``). ``anchor_residuals_px`` has one entry per click for anchors.
    """

    photo_id: str
    camera_id: str | None = None
    capture_time_ns: int = 0
    intrinsics: Intrinsics | None = None
    world_from_camera: tuple[float, ...] = ()
    status: Literal["anchor", "auto", "failed"]
    method: str = ""
    num_inliers: int = 0
    reprojection_rms_px: float = 0.0
    anchor_residuals_px: tuple[float, ...] = ()
    message: str = ""
    processing_ms: float = 0.0


SPARSE_POINT_FROM_MODEL = 1
"""SparseCloud point flag: the point's 3D position was looked up on the BIM (depth of the model) and no two-view
triangulation has reproduced it (something unmodelled may stand in front of the model there)."""
SPARSE_POINT_VERIFIED = 2
"""SparseCloud point flag: triangulated from epipolar-guided matches (densification), free of the repeated-texture
mismatches that blind matching keeps; the static-occlusion test uses only such points when flags are given."""


class SparseCloud(Message, frozen=True, kw_only=True):
    """Triangulated points with their observations.

    ``points_xyz_f32``: float32 (N, 3) in world metres; ``colors_rgb_u8``: uint8 (N, 3);
    observation arrays share one length M: ``obs_point_i32`` (index into points),
    ``obs_photo_i32`` (index into ``photo_ids``), ``obs_pixel_f32`` float32 (M, 2).
    ``point_flags_u8``: uint8 (N,) bit set of ``SPARSE_POINT_FROM_MODEL`` / ``SPARSE_POINT_VERIFIED`` per point,
    or empty (older publishers: no flags known).
    """

    revision: int = 0
    photo_ids: tuple[str, ...] = ()
    points_xyz_f32: bytes = b""
    colors_rgb_u8: bytes = b""
    obs_point_i32: bytes = b""
    obs_photo_i32: bytes = b""
    obs_pixel_f32: bytes = b""
    point_flags_u8: bytes = b""


class ViewpointGroup(Message, frozen=True, kw_only=True):
    """Photos taken from nearly the same viewpoint as ``photo_id`` (paper Sec. 4.1.1)."""

    photo_id: str
    neighbours: tuple[ViewpointNeighbour, ...] = ()


class NeedsAnchor(Message, frozen=True, kw_only=True):
    """Registration asks a user for anchor clicks on this photo."""

    photo_id: str
    reason: str
    num_matched_tracks: int = 0


class OcclusionMask(Message, frozen=True, kw_only=True):
    """Pixels of ``photo_id`` where something stands in front of the building.

    ``mask_png``: 8-bit single-channel PNG at photo resolution, 255 = occluded.
    ``background_jpeg``: the clean background plate (dynamic kind only).
    ``status``: ``ok`` or ``not_enough_views`` (then the mask is empty and must not be used).
    """

    photo_id: str
    kind: Literal["dynamic", "static", "user", "combined"]
    status: Literal["ok", "not_enough_views", "failed"] = "ok"
    mask_png: bytes = b""
    background_jpeg: bytes = b""
    num_views: int = 0
    processing_ms: float = 0.0


class Overlay(Message, frozen=True, kw_only=True):
    """The BIM drawn into a photo. ``image_png`` is RGBA (or RGB composite) at photo size.

    ``progress`` colours elements by the deviation detected from the photos (``ProgressUpdate``) where there is
    evidence, else by the schedule; ``progress_planned`` by the schedule (and annotations) alone.
    """

    photo_id: str
    mode: Literal["state4d", "progress", "xray", "future", "edges", "photoreal", "id", "progress_planned"]
    at_ns: int = 0
    image_png: bytes = b""
    legend: tuple[LegendEntry, ...] = ()
    filter: ElementFilter = ElementFilter()
    camera_id: str | None = None
    processing_ms: float = 0.0


class Annotation(Message, frozen=True, kw_only=True):
    """A user's statement about elements or pixels.

    ``kind``: ``status`` (elements built / not built ...), ``occluder`` (polygon that hides the
    model, sticks to the camera), ``note``. ``polygon_px`` is in the pixels of ``photo_id``.
    ``status`` ``ahead`` / ``on_time`` / ``behind`` is the user's schedule judgement (paper Sec. 4.2 colours).
    ``rgba``: the colour to draw it in, 0-255 (all 0: the status's default colour). ``polygon_in_world_m``: a
    region's outline lifted onto the model surface (world metres), when it was drawn on a registered photo.
    Edits and deletions are new messages with the same ``annotation_id`` and a higher ``revision``
    (``deleted=True`` ends it); ``modified_ns`` is when that revision was made (``created_ns`` stays).
    """

    annotation_id: str
    kind: Literal["status", "occluder", "note"]
    photo_id: str | None = None
    camera_id: str | None = None
    polygon_px: tuple[tuple[float, float], ...] = ()
    element_ids: tuple[str, ...] = ()
    status: Literal["", "built", "not_built", "occluded", "needs_review", "ahead", "on_time", "behind"] = ""
    text: str = ""
    author: str = ""
    created_ns: int = 0
    rgba: tuple[int, int, int, int] = (0, 0, 0, 0)
    polygon_in_world_m: tuple[tuple[float, float, float], ...] = ()
    revision: int = 0
    deleted: bool = False
    modified_ns: int = 0


class NodeError(Message, frozen=True, kw_only=True):
    """A node could not decode or handle a message; the node keeps running."""

    node: str
    topic: str
    reason: str
    key: str = ""
    time_ns: int = 0


class PhotoEvidence(Message, frozen=True, kw_only=True):
    """Per-photo evidence of which elements stand (the progress node), one entry per element the photo should see
    (the model rendered at its registered pose and date window, minus the occlusion masks).

    ``working_width_px`` / ``working_height_px``: resolution the evidence was computed at.
    """

    photo_id: str
    camera_id: str | None = None
    capture_time_ns: int = 0
    filename: str = ""
    elements: tuple[ElementEvidence, ...] = ()
    working_width_px: int = 0
    working_height_px: int = 0
    processing_ms: float = 0.0


class ProgressUpdate(Message, frozen=True, kw_only=True):
    """Fused progress after new evidence: the elements whose estimate changed, every task touched, and one
    planned-vs-detected point per storey, all at ``as_of_ns`` (the latest capture time seen). ``photo_id``: the
    photo that triggered the update (empty for schedule or annotation changes)."""

    as_of_ns: int
    photo_id: str = ""
    elements: tuple[ElementProgress, ...] = ()
    tasks: tuple[TaskProgress, ...] = ()
    storeys: tuple[StoreyProgress, ...] = ()
    tz: str = "UTC"


AnyMessage = (
    Photo
    | BimModel
    | BimUpdate
    | AnchorClicks
    | Registration
    | SparseCloud
    | ViewpointGroup
    | NeedsAnchor
    | OcclusionMask
    | Overlay
    | Annotation
    | NodeError
    | PhotoEvidence
    | ProgressUpdate
)

MESSAGE_TYPES: tuple[type[Message], ...] = (
    Photo,
    BimModel,
    BimUpdate,
    AnchorClicks,
    Registration,
    SparseCloud,
    ViewpointGroup,
    NeedsAnchor,
    OcclusionMask,
    Overlay,
    Annotation,
    NodeError,
    PhotoEvidence,
    ProgressUpdate,
)
