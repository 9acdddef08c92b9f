"""Sun position from latitude, longitude and UTC time (pure numpy; NOAA solar calculator equations).

Implements the equations of the NOAA Global Monitoring Laboratory solar calculator
(``calcdetails``: Meeus, *Astronomical Algorithms*, low-order series), stated accuracy about
0.01 deg for 1800-2100, including NOAA's atmospheric refraction approximation. Azimuth is degrees
clockwise from true north (0 N, 90 E, 180 S); elevation is the apparent (refracted) angle above
the horizon in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

_NS_PER_DAY = 86_400_000_000_000


@dataclass(frozen=True)
class SunPosition:
    azimuth_deg: float
    elevation_deg: float
    elevation_geometric_deg: float
    declination_deg: float
    equation_of_time_min: float


def _refraction_deg(elev_deg: float) -> float:
    """NOAA's approximate atmospheric refraction (degrees) for a geometric elevation."""
    e = elev_deg
    if e > 85.0:
        return 0.0
    te = np.tan(np.radians(e))
    if e > 5.0:
        arcsec = 58.1 / te - 0.07 / te**3 + 0.000086 / te**5
    elif e > -0.575:
        arcsec = 1735.0 + e * (-518.2 + e * (103.4 + e * (-12.79 + e * 0.711)))
    else:
        arcsec = -20.772 / te
    return float(arcsec / 3600.0)


def sun_position(lat_deg: float, lon_deg: float, time_utc_ns: int) -> SunPosition:
    """Apparent sun azimuth/elevation at WGS84 ``lat_deg``/``lon_deg`` (east positive) and UTC ns."""
    if not -90.0 <= lat_deg <= 90.0 or not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"latitude/longitude out of range: {lat_deg}, {lon_deg}")
    days = time_utc_ns / _NS_PER_DAY
    jd = days + 2440587.5
    jc = (jd - 2451545.0) / 36525.0
    minutes_of_day = (time_utc_ns % _NS_PER_DAY) / 60e9

    l0 = (280.46646 + jc * (36000.76983 + jc * 0.0003032)) % 360.0
    m = 357.52911 + jc * (35999.05029 - 0.0001537 * jc)
    ecc = 0.016708634 - jc * (0.000042037 + 0.0000001267 * jc)
    mr = np.radians(m)
    center = (
        np.sin(mr) * (1.914602 - jc * (0.004817 + 0.000014 * jc))
        + np.sin(2 * mr) * (0.019993 - 0.000101 * jc)
        + np.sin(3 * mr) * 0.000289
    )
    true_long = l0 + center
    omega = np.radians(125.04 - 1934.136 * jc)
    app_long = true_long - 0.00569 - 0.00478 * np.sin(omega)
    eps0 = 23.0 + (26.0 + (21.448 - jc * (46.815 + jc * (0.00059 - jc * 0.001813))) / 60.0) / 60.0
    eps = np.radians(eps0 + 0.00256 * np.cos(omega))
    decl = np.arcsin(np.sin(eps) * np.sin(np.radians(app_long)))
    y = np.tan(eps / 2.0) ** 2
    l0r = np.radians(l0)
    eot_min = 4.0 * np.degrees(
        y * np.sin(2 * l0r)
        - 2 * ecc * np.sin(mr)
        + 4 * ecc * y * np.sin(mr) * np.cos(2 * l0r)
        - 0.5 * y * y * np.sin(4 * l0r)
        - 1.25 * ecc * ecc * np.sin(2 * mr)
    )
    true_solar_min = (minutes_of_day + eot_min + 4.0 * lon_deg) % 1440.0
    hour_angle = true_solar_min / 4.0 - 180.0
    lat = np.radians(lat_deg)
    cos_zen = np.sin(lat) * np.sin(decl) + np.cos(lat) * np.cos(decl) * np.cos(np.radians(hour_angle))
    zen = np.arccos(np.clip(cos_zen, -1.0, 1.0))
    denom = np.cos(lat) * np.sin(zen)
    if abs(denom) < 1e-12:
        az = 180.0 if lat_deg > 0 else 0.0
    else:
        cos_az = np.clip((np.sin(lat) * np.cos(zen) - np.sin(decl)) / denom, -1.0, 1.0)
        a = np.degrees(np.arccos(cos_az))
        az = (a + 180.0) % 360.0 if hour_angle > 0 else (540.0 - a) % 360.0
    elev_geo = 90.0 - float(np.degrees(zen))
    return SunPosition(
        azimuth_deg=float(az),
        elevation_deg=elev_geo + _refraction_deg(elev_geo),
        elevation_geometric_deg=elev_geo,
        declination_deg=float(np.degrees(decl)),
        equation_of_time_min=float(eot_min),
    )


def sun_direction_in_site(sun: SunPosition, true_north_deg: float = 0.0) -> NDArray[np.float64]:
    """Unit vector (3,) from the site towards the sun in site coordinates (z up).

    ``true_north_deg``: angle of true north measured counter-clockwise from the site's +y axis
    about +z (IFC ``TrueNorth`` convention); 0 means +x east, +y north.
    """
    az = np.radians(sun.azimuth_deg)
    el = np.radians(sun.elevation_deg)
    enu = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
    a = np.radians(true_north_deg)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return rot @ enu
