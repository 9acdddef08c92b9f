"""Site sizes: how big the building is and how many photos are rendered."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SizeConfig:
    """Parameters of one site size. Resolutions are (width_px, height_px)."""

    name: str
    storeys: int  # above-ground storeys (a basement is always added)
    bays_x: int  # 6 m structural bays along x (east)
    bays_y: int  # 6 m structural bays along y (north)
    cameras: tuple[str, ...]  # fixed time-lapse camera ids, from CAMERA_LAYOUT
    days: int  # working days with one frame per fixed camera
    fixed_resolution: tuple[int, int]
    phone_resolution: tuple[int, int]
    visits: tuple[int, ...]  # photos per handheld visit
    ground_texture_px: int  # side of the non-repeating site ground texture
    texture_px: int  # side of the repeating material textures


SIZES: dict[str, SizeConfig] = {
    "tiny": SizeConfig("tiny", 1, 2, 1, ("cam-north", "cam-east"), 3, (320, 180), (320, 240), (2,), 512, 256),
    "small": SizeConfig(
        "small", 2, 3, 2, ("cam-north", "cam-east", "cam-south"), 6, (960, 540), (800, 600), (5,), 2048, 512
    ),
    "default": SizeConfig(
        "default",
        4,
        4,
        2,
        ("cam-north", "cam-east", "cam-south", "cam-west"),
        20,
        (1920, 1080),
        (1600, 1200),
        (8, 10, 12),
        4096,
        1024,
    ),
    "large": SizeConfig(
        "large",
        4,
        5,
        3,
        ("cam-north", "cam-east", "cam-south", "cam-west"),
        45,
        (1920, 1080),
        (1600, 1200),
        (8, 10, 12, 10, 15),
        4096,
        1024,
    ),
}

STOREY_HEIGHT_M = 3.2
BAY_M = 6.0
GROUND_FLOOR_TOP_M = 0.15  # top of the ground-floor slab (ground plane is z = 0)
BASEMENT_DEPTH_M = 3.0

# Site: a plot on the edge of Nijmegen (NL). World frame: x east, y north, z up, metres, origin at the
# building centre on the ground.
SITE_NAME = "Nijmegen Lent, Plot 7"
LAT_DEG = 51.8583
LON_DEG = 5.8647
ALT_M = 12.0
TZ = "Europe/Amsterdam"
FIRST_PHOTO_DAY = (2026, 3, 9)  # a Monday: first working day with fixed-camera photos
