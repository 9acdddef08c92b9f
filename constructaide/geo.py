"""Shared pure geodesy for photo positions: EXIF GPS and horizontal distances between WGS84 points.

Distances use the local equirectangular approximation at the pair's mean latitude on the WGS84 mean radius;
over a construction site (< 10 km) it is within 0.1 % of the geodesic. No site frame is needed: distances between
photos are independent of where the site's origin is and of how its axes turn from north.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from PIL import Image

from schemas.messages import GeoPoint

EARTH_RADIUS_M = 6_371_008.8
_GPS_IFD = 0x8825


def rational(value: object) -> float | None:
    """An EXIF rational (or number) as a finite float, None when it is not one."""
    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f if math.isfinite(f) else None


def exif_gps(exif: Image.Exif) -> GeoPoint | None:
    """WGS84 position from the EXIF GPS IFD, ``None`` when absent or out of range."""
    try:
        gps: dict[int, Any] = dict(exif.get_ifd(_GPS_IFD))
    except (KeyError, ValueError, TypeError, OSError):
        return None
    if 2 not in gps or 4 not in gps:
        return None

    def deg(dms: Any) -> float | None:
        try:
            d, m, s = (rational(x) for x in dms)
        except (TypeError, ValueError):
            return None
        if d is None or m is None or s is None:
            return None
        return d + m / 60.0 + s / 3600.0

    lat, lon = deg(gps[2]), deg(gps[4])
    if lat is None or lon is None:
        return None
    if str(gps.get(1, "N")).upper().startswith("S"):
        lat = -lat
    if str(gps.get(3, "E")).upper().startswith("W"):
        lon = -lon
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return None
    alt = rational(gps.get(6)) if 6 in gps else None
    if alt is not None and gps.get(5) in (1, b"\x01"):
        alt = -alt
    return GeoPoint(lat_deg=lat, lon_deg=lon, alt_m=alt)


def enu_m(g: GeoPoint, origin: GeoPoint) -> tuple[float, float]:
    """East / north metres of ``g`` from ``origin`` (local equirectangular, like :func:`horizontal_distance_m`)."""
    lat = math.radians(0.5 * (g.lat_deg + origin.lat_deg))
    return (
        EARTH_RADIUS_M * math.radians(g.lon_deg - origin.lon_deg) * math.cos(lat),
        EARTH_RADIUS_M * math.radians(g.lat_deg - origin.lat_deg),
    )


def horizontal_distance_m(a: GeoPoint, b: GeoPoint) -> float:
    """Horizontal distance (m) between two WGS84 points (local equirectangular approximation)."""
    lat_m = math.radians(0.5 * (a.lat_deg + b.lat_deg))
    dx = math.radians(b.lon_deg - a.lon_deg) * math.cos(lat_m) * EARTH_RADIUS_M
    dy = math.radians(b.lat_deg - a.lat_deg) * EARTH_RADIUS_M
    return math.hypot(dx, dy)


def gps_distance_residuals_m(
    centre_in_world_m: np.ndarray, gps: GeoPoint, others_in_world_m: np.ndarray, others_gps: list[GeoPoint]
) -> np.ndarray:
    """|horizontal distance between registered camera centres - distance between their GPS positions| (K,) m,
    from one camera (centre (3,) in a z-up metric world frame, its GPS) to K others. Invariant to the world
    frame's origin and heading, so it needs no georeference of the model."""
    d_reg = np.linalg.norm(np.asarray(others_in_world_m, np.float64)[:, :2] - np.asarray(centre_in_world_m)[:2], axis=1)
    d_gps = np.array([horizontal_distance_m(gps, o) for o in others_gps])
    return np.abs(d_reg - d_gps)
