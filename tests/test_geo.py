"""Shared geodesy: EXIF GPS parsing and frame-free distance checks between photo positions."""

from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image

from constructaide.geo import exif_gps, gps_distance_residuals_m, horizontal_distance_m
from schemas.messages import GeoPoint


def test_horizontal_distance_against_known_values() -> None:
    a = GeoPoint(lat_deg=51.8583, lon_deg=5.8647)
    north = GeoPoint(lat_deg=51.8583 + 0.001, lon_deg=5.8647)
    east = GeoPoint(lat_deg=51.8583, lon_deg=5.8647 + 0.001)
    assert abs(horizontal_distance_m(a, north) - 111.19) < 0.05  # 1e-3 deg of latitude
    assert abs(horizontal_distance_m(a, east) - 111.19 * math.cos(math.radians(51.8583))) < 0.05
    assert horizontal_distance_m(a, a) == 0.0


def test_distance_residuals_ignore_the_model_frame() -> None:
    """Camera centres in any rotated / shifted z-up metric frame give the same residuals against GPS."""
    rng = np.random.default_rng(0)
    enu = rng.uniform(-40, 40, (6, 2))  # true horizontal positions, east/north metres
    lat0, lon0 = 51.8583, 5.8647
    r = 6_371_008.8
    gps = [
        GeoPoint(
            lat_deg=lat0 + math.degrees(n / r), lon_deg=lon0 + math.degrees(e / (r * math.cos(math.radians(lat0))))
        )
        for e, n in enumerate_pairs(enu)
    ]
    a = math.radians(37.0)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    centres = np.c_[enu @ R.T + [100.0, -20.0], rng.uniform(0, 10, 6)]  # model frame: turned, shifted, any height
    res = gps_distance_residuals_m(centres[0], gps[0], centres[1:], gps[1:])
    assert res.shape == (5,) and res.max() < 0.05
    wrong = centres[0] + [30.0, 0.0, 0.0]  # a registration 30 m off
    assert np.median(gps_distance_residuals_m(wrong, gps[0], centres[1:], gps[1:])) > 5.0


def enumerate_pairs(enu: np.ndarray):
    return [(float(e), float(n)) for e, n in enu]


def test_exif_gps_round_trip() -> None:
    exif = Image.Exif()
    exif.get_ifd(0x8825).update({1: "N", 2: (51.0, 51.0, 29.88), 3: "W", 4: (5.0, 51.0, 52.92), 5: 0, 6: 12.5})
    buf = io.BytesIO()
    Image.new("RGB", (8, 8)).save(buf, "JPEG", exif=exif.tobytes())
    with Image.open(io.BytesIO(buf.getvalue())) as img:
        g = exif_gps(img.getexif())
    assert g is not None
    assert abs(g.lat_deg - 51.8583) < 1e-6 and abs(g.lon_deg + 5.8647) < 1e-6 and g.alt_m == 12.5
    assert exif_gps(Image.Exif()) is None
