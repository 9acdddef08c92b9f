"""Camera plans: fixed time-lapse cameras (daily jitter, one knocked mid-way) and handheld phone visits."""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from constructaide.camera import centered_intrinsics, look_at, rodrigues_to_matrix
from schemas.messages import Intrinsics

from .building import Building
from .scene import SiteLayout, camera_position_ok
from .schedule import local_datetime

F64 = NDArray[np.float64]

# id -> (azimuth of the camera seen from the building, degrees clockwise from north; mount height m;
#        k1; k2; capture time local "HH:MM")
CAMERA_LAYOUT: dict[str, tuple[float, float, float, float, str]] = {
    "cam-north": (18.0, 11.0, -0.08, 0.012, "11:30"),
    "cam-east": (104.0, 9.0, -0.10, 0.020, "12:15"),
    "cam-south": (205.0, 12.0, -0.06, 0.008, "13:00"),
    "cam-west": (282.0, 10.0, -0.09, 0.015, "14:10"),
}
KNOCKED_CAMERA = "cam-east"
FIXED_SENSOR_WIDTH_MM = 7.2  # 1/1.8" sensor
PHONE_SENSOR_WIDTH_MM = 6.17  # 1/2.3" sensor


@dataclass(frozen=True)
class PhotoPlan:
    """One photo to render. ``rel_path`` is relative to ``photos/``; ``pose_segment`` changes when a fixed
    camera is knocked (truth: the anchor file does not use it); ``visit`` is the phone visit number or None."""

    rel_path: str
    camera_id: str | None
    intrinsics: Intrinsics
    world_from_camera: F64
    local_time: dt.datetime
    sensor_width_mm: float
    day: int
    pose_segment: int
    visit: int | None


def _jitter(rng: np.random.Generator) -> tuple[F64, float]:
    """Small rotation (camera frame, pan < 0.25 deg, tilt < 0.15 deg, roll < 0.1 deg) and zoom factor (< 0.8 %)."""
    pan, tilt, roll = (math.radians(rng.uniform(-a, a)) for a in (0.25, 0.15, 0.1))
    R = (
        rodrigues_to_matrix([0.0, pan, 0.0])
        @ rodrigues_to_matrix([tilt, 0.0, 0.0])
        @ rodrigues_to_matrix([0.0, 0.0, roll])
    )
    return R, float(rng.uniform(-0.008, 0.008))


def fixed_camera_plans(
    building: Building, camera_ids: tuple[str, ...], days: int, resolution: tuple[int, int], rng: np.random.Generator
) -> list[PhotoPlan]:
    """One photo per camera per working day 0..days-1."""
    hx, hy = building.half_extent_m
    W, H = resolution
    dist = 2.0 * max(hx, hy) + 24.0
    target = np.array([0.0, 0.0, 0.35 * building.top_m])
    plans = []
    for cam in camera_ids:
        az, height, k1, k2, hhmm = CAMERA_LAYOUT[cam]
        a = math.radians(az)
        eye = np.array([dist * math.sin(a), dist * math.cos(a), height])
        base = look_at(eye, target)
        f0 = 0.5 * W / math.tan(math.radians(31.0))
        hh, mm = (int(p) for p in hhmm.split(":"))
        knock_day = days // 2 if cam == KNOCKED_CAMERA else None
        for day in range(days):
            pose = base.copy()
            segment = 0
            if knock_day is not None and day >= knock_day:
                R_knock = rodrigues_to_matrix([math.radians(-3.0), math.radians(7.0), math.radians(1.5)])
                pose[:3, :3] = base[:3, :3] @ R_knock
                pose[:3, 3] = eye + np.array([0.4, -0.3, -0.25])
                segment = 1
            R_j, zoom = _jitter(rng)
            pose[:3, :3] = pose[:3, :3] @ R_j
            intr = centered_intrinsics(W, H, f0 * (1 + zoom), k1, k2)
            minute = int(rng.integers(-4, 5))
            when = local_datetime(day, hh, mm) + dt.timedelta(minutes=minute)
            rel = f"{cam}/{when.strftime('%Y%m%dT%H%M')}.jpg"
            plans.append(PhotoPlan(rel, cam, intr, pose, when, FIXED_SENSOR_WIDTH_MM, day, segment, None))
    return plans


def phone_visit_plans(
    building: Building,
    layout: SiteLayout,
    visits: tuple[int, ...],
    days: int,
    resolution: tuple[int, int],
    rng: np.random.Generator,
) -> list[PhotoPlan]:
    """Handheld visits spread over the period; each walks around the site (wide baselines, 24-52 mm eq.)."""
    W, H = resolution
    plans = []
    counter = 1
    for vi, n_photos in enumerate(visits):
        day = int(round((vi + 1) * days / (len(visits) + 1)))
        day = min(max(day, 0), days - 1)
        start = local_datetime(day, 10, 0) + dt.timedelta(minutes=int(rng.integers(0, 180)))
        az0 = rng.uniform(0, 2 * math.pi)
        span = math.radians(rng.uniform(200, 320))
        k = 0
        while k < n_photos:
            az = az0 + span * (k + rng.uniform(-0.3, 0.3)) / max(n_photos - 1, 1)
            # about a third of the photos from inside the fence (between fence and facade), the rest outside
            offset = rng.uniform(2.2, 3.4) if rng.random() < 0.35 else rng.uniform(6.5, 22.0)
            r_x, r_y = layout.hx + offset, layout.hy + offset
            xy = np.array([r_x * math.sin(az), r_y * math.cos(az)])
            if not camera_position_ok(layout, building, xy):
                continue
            eye = np.array([xy[0], xy[1], rng.uniform(1.45, 1.8)])
            target = np.array(
                [
                    rng.uniform(-0.6, 0.6) * layout.hx,
                    rng.uniform(-0.6, 0.6) * layout.hy,
                    rng.uniform(2.0, max(3.0, 0.45 * building.top_m)),
                ]
            )
            pose = look_at(eye, target)
            pose[:3, :3] = pose[:3, :3] @ rodrigues_to_matrix([0.0, 0.0, math.radians(rng.uniform(-4, 4))])
            f35 = rng.uniform(24.0, 52.0) if offset > 8.0 else rng.uniform(20.0, 28.0)
            intr = centered_intrinsics(W, H, f35 / 36.0 * W, rng.uniform(-0.03, 0.02), rng.uniform(-0.005, 0.005))
            when = start + dt.timedelta(minutes=3 * k + int(rng.integers(0, 3)))
            rel = f"phone/{when.strftime('%Y%m%d')}/IMG_{counter:04d}.jpg"
            plans.append(PhotoPlan(rel, None, intr, pose, when, PHONE_SENSOR_WIDTH_MM, day, 0, vi))
            counter += 1
            k += 1
    return plans
