"""Deterministic writers: JPEG with EXIF, 8/16-bit PNG, npz without zip timestamps."""

from __future__ import annotations

import datetime as dt
import io
import math
import zipfile
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from PIL import Image

from .config import ALT_M, LAT_DEG, LON_DEG

_M_PER_DEG_LAT = 111_320.0


def enu_to_latlon(x_east_m: float, y_north_m: float) -> tuple[float, float]:
    """Latitude/longitude (degrees) of a site-frame point (small-area approximation)."""
    lat = LAT_DEG + y_north_m / _M_PER_DEG_LAT
    lon = LON_DEG + x_east_m / (_M_PER_DEG_LAT * math.cos(math.radians(LAT_DEG)))
    return lat, lon


def _dms(deg: float) -> tuple[float, float, float]:
    a = abs(deg)
    d = math.floor(a)
    m = math.floor((a - d) * 60)
    s = round(((a - d) * 60 - m) * 60, 4)
    return float(d), float(m), s


def write_jpeg(
    path: Path,
    rgb: NDArray[np.uint8],
    when_local: dt.datetime,
    f_mm: float,
    f35_mm: float,
    position_m: NDArray[np.float64],
    model: str,
    quality: int = 92,
) -> None:
    """JPEG with EXIF DateTimeOriginal/OffsetTimeOriginal, FocalLength(+35 mm), GPS of ``position_m``."""
    exif = Image.Exif()
    exif[0x010F] = "ConstructAide Synth"  # Make
    exif[0x0110] = model  # Model
    exif[0x0132] = when_local.strftime("%Y:%m:%d %H:%M:%S")  # DateTime
    sub = exif.get_ifd(0x8769)
    sub[0x9003] = when_local.strftime("%Y:%m:%d %H:%M:%S")  # DateTimeOriginal
    off = when_local.utcoffset() or dt.timedelta(0)
    minutes = int(off.total_seconds() // 60)
    sign = "+" if minutes >= 0 else "-"
    sub[0x9011] = f"{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"  # OffsetTimeOriginal
    sub[0x920A] = round(float(f_mm), 3)  # FocalLength
    sub[0xA405] = int(round(f35_mm))  # FocalLengthIn35mmFilm
    lat, lon = enu_to_latlon(float(position_m[0]), float(position_m[1]))
    gps = exif.get_ifd(0x8825)
    gps[0x0000] = b"\x02\x03\x00\x00"  # GPSVersionID
    gps[0x0001] = "N" if lat >= 0 else "S"
    gps[0x0002] = _dms(lat)
    gps[0x0003] = "E" if lon >= 0 else "W"
    gps[0x0004] = _dms(lon)
    gps[0x0005] = 0  # above sea level
    gps[0x0006] = round(ALT_M + float(position_m[2]), 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, "JPEG", quality=quality, exif=exif.tobytes())
    path.write_bytes(buf.getvalue())


def write_png(path: Path, image: NDArray) -> None:
    """8-bit or 16-bit single-channel PNG (OpenCV encoder, deterministic)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 2])
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    path.write_bytes(data.tobytes())


def write_npz(path: Path, **arrays: NDArray) -> None:
    """Compressed .npz readable by ``np.load`` with fixed zip timestamps (byte-identical across runs)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(2026, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            a = io.BytesIO()
            np.lib.format.write_array(a, np.asarray(arr), allow_pickle=False)
            zf.writestr(info, a.getvalue(), compresslevel=1)
    path.write_bytes(buf.getvalue())
