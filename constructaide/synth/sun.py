"""Sun position (NOAA general solar position equations; ~0.1 degree accuracy, plenty for lighting)."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np


def sun_azimuth_elevation_deg(when_utc: dt.datetime, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """Solar azimuth (degrees clockwise from north) and elevation (degrees above the horizon)."""
    t = when_utc.astimezone(dt.UTC)
    doy = t.timetuple().tm_yday
    hour = t.hour + t.minute / 60 + t.second / 3600
    g = 2 * math.pi / 365 * (doy - 1 + (hour - 12) / 24)
    eqtime = 229.18 * (
        0.000075
        + 0.001868 * math.cos(g)
        - 0.032077 * math.sin(g)
        - 0.014615 * math.cos(2 * g)
        - 0.040849 * math.sin(2 * g)
    )
    decl = (
        0.006918
        - 0.399912 * math.cos(g)
        + 0.070257 * math.sin(g)
        - 0.006758 * math.cos(2 * g)
        + 0.000907 * math.sin(2 * g)
        - 0.002697 * math.cos(3 * g)
        + 0.00148 * math.sin(3 * g)
    )
    true_solar_min = hour * 60 + eqtime + 4 * lon_deg
    ha = math.radians(true_solar_min / 4 - 180)
    lat = math.radians(lat_deg)
    cos_zen = math.sin(lat) * math.sin(decl) + math.cos(lat) * math.cos(decl) * math.cos(ha)
    zen = math.acos(max(-1.0, min(1.0, cos_zen)))
    az = math.degrees(math.atan2(math.sin(ha), math.cos(ha) * math.sin(lat) - math.tan(decl) * math.cos(lat))) + 180
    return az % 360.0, 90.0 - math.degrees(zen)


def sun_direction_world(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector towards the sun in the site frame (x east, y north, z up)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])
