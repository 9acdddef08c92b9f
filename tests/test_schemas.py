"""Every message round-trips through msgpack and JSON; keys and schema evolution rules hold."""

from __future__ import annotations

import msgspec
import pytest

from schemas import codec, keys
from schemas.messages import (
    MESSAGE_TYPES,
    AnchorClicks,
    AnchorPoint,
    Annotation,
    BimElement,
    BimModel,
    BimUpdate,
    ElementEvidence,
    ElementFilter,
    ElementProgress,
    GeoPoint,
    Intrinsics,
    LegendEntry,
    NeedsAnchor,
    NodeError,
    OcclusionMask,
    Overlay,
    Photo,
    PhotoEvidence,
    ProgressUpdate,
    Registration,
    ScheduleTask,
    SparseCloud,
    StoreyProgress,
    TaskProgress,
    ViewpointGroup,
    ViewpointNeighbour,
)

S = "site-1"
T0 = 1_767_225_600_000_000_000
ELEMENT = BimElement(
    global_id="2O2Fr$t4X7Zf8NOew3FLOH",
    ifc_class="IfcWall",
    name="W1",
    storey="Level 1",
    type_name="Brick 300",
    material="Brick",
    geometry_ref="2O2Fr$t4X7Zf8NOew3FLOH",
    bbox_min_m=(0.0, 0.0, 0.0),
    bbox_max_m=(5.0, 0.3, 3.0),
)
TASK = ScheduleTask(
    task_id="T1",
    name="Walls L1",
    planned_start_ns=T0,
    planned_finish_ns=T0 + 10**15,
    actual_start_ns=T0 + 5,
    element_ids=(ELEMENT.global_id,),
    predecessor_ids=("T0",),
)
INTR = Intrinsics(width_px=1920, height_px=1080, f_px=1500.0, cx_px=959.5, cy_px=539.5, k1=-0.05, k2=0.01)

SAMPLES = [
    Photo(
        site=S,
        photo_id="0123456789abcdef",
        camera_id="cam-north",
        capture_time_ns=T0,
        tz="Europe/Amsterdam",
        data=b"\xff\xd8\xff\xe0jpeg",
        width_px=1920,
        height_px=1080,
        focal_px=1500.0,
        focal_35mm_mm=28.0,
        gps=GeoPoint(lat_deg=51.84, lon_deg=5.86, alt_m=12.0),
        filename="a.jpg",
        source="push",
    ),
    BimModel(
        site=S,
        revision="r1",
        elements=(ELEMENT,),
        tasks=(TASK,),
        geometry_glb=b"glTF",
        origin_offset_m=(1.0, 2.0, 3.0),
        gps=GeoPoint(lat_deg=1.0, lon_deg=2.0),
        tz="Europe/Amsterdam",
        source_files=("a.ifc",),
        terrain_height_m=0.0,
    ),
    BimUpdate(site=S, base_revision="r1", revision="r2", added=(ELEMENT,), removed=("x",), changed=(), tasks=(TASK,)),
    AnchorClicks(
        site=S,
        photo_id="p",
        image_name="IMG_1.jpg",
        points=tuple(AnchorPoint(pixel_px=(float(i), 2.0), point_in_world_m=(1.0, 2.0, float(i))) for i in range(6)),
        focal_px=1520.0,
    ),
    Registration(
        site=S,
        photo_id="p",
        camera_id="cam",
        capture_time_ns=T0,
        intrinsics=INTR,
        world_from_camera=tuple(float(v) for v in range(16)),
        status="auto",
        method="pnp",
        num_inliers=120,
        reprojection_rms_px=0.7,
        anchor_residuals_px=(0.5, 0.4),
    ),
    SparseCloud(site=S, revision=3, photo_ids=("p",), points_xyz_f32=b"\x00" * 12, colors_rgb_u8=b"\x01\x02\x03"),
    ViewpointGroup(
        site=S,
        photo_id="p",
        neighbours=(
            ViewpointNeighbour(photo_id="q", this_from_neighbour=(1.0,) * 9, inlier_ratio=0.9, num_matches=300),
        ),
    ),
    NeedsAnchor(site=S, photo_id="p", reason="no tracks", num_matched_tracks=3),
    OcclusionMask(
        site=S, photo_id="p", kind="dynamic", status="ok", mask_png=b"png", background_jpeg=b"jpg", num_views=4
    ),
    Overlay(
        site=S,
        photo_id="p",
        mode="progress",
        at_ns=T0,
        image_png=b"png",
        legend=(LegendEntry(label="behind", rgba=(255, 0, 0, 200)),),
        filter=ElementFilter(ifc_classes=("IfcWall",), storeys=("L1",)),
    ),
    Annotation(
        site=S,
        annotation_id="a1",
        kind="occluder",
        photo_id="p",
        camera_id="cam",
        polygon_px=((0.0, 0.0), (10.0, 0.0), (10.0, 10.0)),
        status="occluded",
        created_ns=T0,
    ),
    Annotation(
        site=S,
        annotation_id="a2",
        kind="status",
        photo_id="p",
        element_ids=("g1", "g2"),
        status="behind",
        text="slab late",
        created_ns=T0,
        rgba=(230, 40, 40, 160),
        polygon_in_world_m=((0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 1.0)),
        revision=2,
        deleted=True,
        modified_ns=T0 + 5,
    ),
    NodeError(site=S, node="register", topic="constructaide/site-1/photo/*", reason="bad", key="k", time_ns=T0),
    PhotoEvidence(
        site=S,
        photo_id="p",
        camera_id="cam",
        capture_time_ns=T0,
        filename="cam/a.jpg",
        elements=(
            ElementEvidence(
                global_id=ELEMENT.global_id,
                state="built",
                confidence=0.97,
                visible_px=812,
                occluded_fraction=0.1,
                llr_change=4.2,
                llr_points=-0.7,
                llr_appearance=1.1,
                reference_ns=T0 - 86_400 * 10**9,
                changed_fraction=0.91,
            ),
            ElementEvidence(global_id="x", state="occluded", confidence=0.8, occluded_fraction=0.8),
        ),
        working_width_px=640,
        working_height_px=360,
        processing_ms=210.0,
    ),
    ProgressUpdate(
        site=S,
        as_of_ns=T0,
        photo_id="p",
        elements=(
            ElementProgress(
                global_id=ELEMENT.global_id,
                state="built",
                present_probability=0.99,
                detected_start_ns=T0 - 10**12,
                detected_finish_ns=T0 - 5 * 10**11,
                last_absent_ns=T0 - 10**12,
                first_present_ns=T0,
                finish_probability=0.9,
                planned_start_ns=T0,
                planned_finish_ns=T0 + 10**15,
                deviation="ahead",
                task_ids=("T1",),
                num_observations=3,
                evidence_photo_ids=("p",),
            ),
        ),
        tasks=(
            TaskProgress(
                task_id="T1",
                name="Walls L1",
                planned_start_ns=T0,
                planned_finish_ns=T0 + 10**15,
                actual_start_ns=T0 - 10**12,
                percent_complete=100.0,
                planned_percent=0.0,
                deviation="ahead",
                num_elements=1,
                num_built=1,
                num_observed=1,
            ),
        ),
        storeys=(StoreyProgress(storey="Level 1", planned_fraction=0.0, detected_fraction=1.0, num_elements=1),),
        tz="Europe/Amsterdam",
    ),
]


def test_every_message_type_has_a_sample() -> None:
    assert {type(m) for m in SAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip_msgpack_and_json(msg: msgspec.Struct) -> None:
    assert codec.decode(codec.encode(msg)) == msg  # via the tagged union
    assert codec.decode(codec.encode(msg), type(msg)) == msg  # via the concrete type
    assert codec.from_json(codec.to_json(msg)) == msg
    assert codec.from_json(codec.to_json(msg), type(msg)) == msg
    schema = codec.json_schema(type(msg))
    assert type(msg).__name__.encode() in schema


def test_messages_are_frozen() -> None:
    with pytest.raises(AttributeError):
        SAMPLES[0].photo_id = "x"  # type: ignore[misc]


def test_wrong_type_payload_is_rejected() -> None:
    with pytest.raises(msgspec.ValidationError):
        codec.decode(codec.encode(SAMPLES[0]), Registration)
    with pytest.raises(msgspec.DecodeError):
        codec.decode(b"\xc1garbage")


def test_old_reader_accepts_new_fields_and_new_reader_old_messages() -> None:
    """Evolution rule: adding a field with a default keeps both directions compatible."""

    class PhotoV2(Photo, frozen=True, kw_only=True, tag="Photo"):
        exposure_ev: float = 0.0

    new = PhotoV2(site=S, photo_id="x", capture_time_ns=T0, data=b"", exposure_ev=1.5)
    old = codec.decode(codec.encode(new), Photo)
    assert old.photo_id == "x"
    back = msgspec.msgpack.decode(codec.encode(Photo(site=S, photo_id="y", capture_time_ns=T0, data=b"")), type=PhotoV2)
    assert back.exposure_ev == 0.0


def test_keys_fill_parse_and_reject_bad_ids() -> None:
    k = keys.key(keys.REGISTRATION, site="s1", camera=None, photo="abc")
    assert k == "constructaide/s1/registration/phone/abc"
    assert keys.parse(keys.REGISTRATION, k) == {"site": "s1", "camera": "phone", "photo": "abc"}
    assert keys.parse(keys.PHOTO, k) is None
    assert keys.pattern(keys.OVERLAY, site="s1") == "constructaide/s1/overlay/*/*"
    for bad in ("a/b", "a*", "", "x y", "$z"):
        with pytest.raises(ValueError):
            keys.key(keys.PHOTO, site="s", camera=bad)
    with pytest.raises(KeyError):
        keys.key(keys.REGISTRATION, site="s", camera="c")  # photo missing
    assert keys.key(keys.PHOTO, site="s") == "constructaide/s/photo/phone"  # no camera: a phone photo
