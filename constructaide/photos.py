"""Photo bytes (JPEG / PNG from cameras and phones) -> ``schemas.messages.Photo``.

Decoding is defensive: a pixel-count limit checked from the header before any pixel is
decoded (decompression bombs), a full decode to catch truncation, EXIF orientation applied (the
image is re-encoded upright), capture time from EXIF DateTimeOriginal + OffsetTimeOriginal
(else the site's IANA zone), GPS, focal length in pixels from the 35 mm equivalent or the focal
plane resolution. ``photo_id`` = sha256 of the stored bytes, first 16 hex characters.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import math
import struct
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from PIL import Image, ImageOps, UnidentifiedImageError

from constructaide import camera as cam
from constructaide.geo import exif_gps
from constructaide.geo import rational as _rational
from schemas.messages import Photo

MAX_PIXELS = 120_000_000
"""Default decompression-bomb limit (width * height)."""
FUTURE_TOLERANCE_S = 600.0
"""Capture times later than now + this are rejected."""
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0
"""Horizontal fields of view outside this range mean the EXIF focal length is wrong."""
JPEG_QUALITY = 95

# EXIF tags
_EXIF_IFD = 0x8769
_DATETIME, _ORIENTATION = 0x0132, 0x0112
_DATETIME_ORIGINAL, _OFFSET_TIME_ORIGINAL, _OFFSET_TIME = 0x9003, 0x9011, 0x9010
_SUBSEC_ORIGINAL = 0x9291
_FOCAL_LENGTH, _FOCAL_35MM = 0x920A, 0xA405
_FP_XRES, _FP_YRES, _FP_UNIT = 0xA20E, 0xA20F, 0xA210
_PIXEL_X_DIM, _PIXEL_Y_DIM = 0xA002, 0xA003
_FP_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


class PhotoError(ValueError):
    """A photo that cannot be accepted; the message says why."""


@dataclass(frozen=True, slots=True)
class DecodedImage:
    """An image checked and made upright: ``data`` are the bytes to store."""

    data: bytes
    media_type: str
    width_px: int
    height_px: int
    exif: Image.Exif
    rotated: bool


JPEG_MAGIC, PNG_MAGIC = b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"


def verify_image(data: bytes, max_pixels: int = MAX_PIXELS, reduced: bool = False) -> tuple[str, int, int]:
    """(Pillow format, width_px, height_px as stored) of JPEG/PNG bytes after a full decode.

    Checked in this order: format and magic (JPEG ``ff d8 ff``, PNG signature), header size against
    ``max_pixels`` (before any pixel is decoded: decompression bombs), PNG chunk CRCs, a decode of every byte
    (truncation), the JPEG end-of-image marker. ``reduced``: JPEGs decode at 1/8 scale (DCT scaling; every
    entropy-coded byte is still read, about 15x faster). Raises PhotoError.
    """
    if not data:
        raise PhotoError("empty photo data")
    with warnings.catch_warnings():
        warnings.simplefilter("error", Image.DecompressionBombWarning)
        try:
            with Image.open(io.BytesIO(data)) as im:
                fmt = im.format
                w, h = im.size
        except UnidentifiedImageError as exc:
            head = f"starts {data[:8].hex()}, {len(data)} bytes"
            raise PhotoError(f"not an image (unrecognised bytes: {head})") from exc
        except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
            raise PhotoError(f"image too large (decompression bomb guard): {exc}") from exc
        except (OSError, SyntaxError, ValueError) as exc:
            raise PhotoError(f"truncated or corrupt image header: {exc}") from exc
        if fmt not in ("JPEG", "PNG", "MPO") or not data.startswith(PNG_MAGIC if fmt == "PNG" else JPEG_MAGIC):
            raise PhotoError(f"unsupported image format {fmt} (JPEG or PNG only)")
        if w <= 0 or h <= 0:
            raise PhotoError(f"image has no pixels ({w}x{h})")
        if w * h > max_pixels:
            raise PhotoError(f"image too large: {w}x{h} px > limit {max_pixels} px (decompression bomb guard)")
        try:
            with Image.open(io.BytesIO(data)) as im:
                im.verify()
            with Image.open(io.BytesIO(data)) as im:
                if reduced and fmt != "PNG":
                    im.draft("L", (max(1, w // 8), max(1, h // 8)))
                im.load()  # full decode: raises on truncated data (LOAD_TRUNCATED_IMAGES stays False)
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombWarning) as exc:
            raise PhotoError(f"truncated or corrupt image: {exc}") from exc
    if fmt in ("JPEG", "MPO") and b"\xff\xd9" not in data[-65536:]:
        raise PhotoError("truncated JPEG (no end-of-image marker)")
    return str(fmt), int(w), int(h)


def photo_problem(photo: Photo, max_pixels: int = MAX_PIXELS) -> str | None:
    """Why ``photo.data`` is not the image the message declares (None when it is): see :func:`verify_image`
    (JPEGs decoded at 1/8 scale), plus the stored size must equal ``width_px`` x ``height_px`` when declared
    (non-zero). The runtime calls this before every handler that takes a Photo; the reason names the photo id."""
    try:
        _, w, h = verify_image(photo.data, max_pixels, reduced=True)
    except PhotoError as e:
        return f"photo {photo.photo_id}: {e}"
    if (photo.width_px or photo.height_px) and (w, h) != (photo.width_px, photo.height_px):
        return f"photo {photo.photo_id}: decodes to {w}x{h} px, declares {photo.width_px}x{photo.height_px}"
    return None


def check_image(data: bytes, max_pixels: int = MAX_PIXELS) -> DecodedImage:
    """Check JPEG/PNG bytes (:func:`verify_image`, full decode) and apply EXIF orientation.

    Raises PhotoError for non-image bytes, other formats, more than ``max_pixels`` pixels,
    truncated or corrupt data.
    """
    fmt, w, h = verify_image(data, max_pixels)
    im = Image.open(io.BytesIO(data))  # decoded again only when made upright
    with im:
        exif = im.getexif()
        media_type = "image/png" if fmt == "PNG" else "image/jpeg"
        try:
            orientation = int(exif.get(_ORIENTATION, 1) or 1)
        except (TypeError, ValueError):
            orientation = 1  # unreadable tag: leave the image as stored
        if not 2 <= orientation <= 8:
            return DecodedImage(data, media_type, w, h, exif, False)
        upright = ImageOps.exif_transpose(im)
        icc = im.info.get("icc_profile")
    # Re-encode upright with the original EXIF (orientation reset) and colour profile.
    extra: dict[str, Any] = {"icc_profile": icc} if icc else {}
    try:
        exif_out = Image.Exif()
        exif_out.load(exif.tobytes())
        exif_out[_ORIENTATION] = 1
        extra["exif"] = exif_out.tobytes()
    except (ValueError, TypeError, OSError, struct.error):
        pass  # EXIF Pillow cannot re-serialise: store without it (the Photo fields keep its values)
    buf = io.BytesIO()
    if fmt == "PNG":
        upright.save(buf, format="PNG", **extra)
    else:
        upright.convert("RGB").save(buf, format="JPEG", quality=JPEG_QUALITY, **extra)
    return DecodedImage(buf.getvalue(), media_type, upright.width, upright.height, exif, True)


def _exif_sub(exif: Image.Exif, ifd: int) -> dict[int, object]:
    try:
        return dict(exif.get_ifd(ifd))
    except (KeyError, ValueError, TypeError, OSError):
        return {}


def _parse_offset(text: str) -> dt.timezone | None:
    s = text.strip()
    if len(s) >= 6 and s[0] in "+-" and s[3] == ":":
        try:
            sign = 1 if s[0] == "+" else -1
            return dt.timezone(sign * dt.timedelta(hours=int(s[1:3]), minutes=int(s[4:6])))
        except ValueError:
            return None
    return None


def exif_capture_time_ns(exif: Image.Exif, tz: str | None) -> int | None:
    """Capture time (ns UTC) from EXIF DateTimeOriginal (+ SubSecTimeOriginal) with
    OffsetTimeOriginal, else interpreted in the IANA zone ``tz``; ``None`` without a date.

    Raises PhotoError when the date is unreadable or there is neither an offset nor ``tz``.
    """
    sub = _exif_sub(exif, _EXIF_IFD)
    raw = sub.get(_DATETIME_ORIGINAL) or exif.get(_DATETIME)
    if not raw:
        return None
    text = str(raw).strip().rstrip("\x00")
    try:
        naive = dt.datetime.strptime(text, "%Y:%m:%d %H:%M:%S")
    except ValueError as exc:
        raise PhotoError(f"unreadable EXIF DateTimeOriginal {text!r}") from exc
    subsec = str(sub.get(_SUBSEC_ORIGINAL) or "").strip().rstrip("\x00")
    micro = int((subsec + "000000")[:6]) if subsec.isdigit() else 0
    naive = naive.replace(microsecond=micro)
    offset = _parse_offset(str(sub.get(_OFFSET_TIME_ORIGINAL) or sub.get(_OFFSET_TIME) or ""))
    if offset is not None:
        aware = naive.replace(tzinfo=offset)
    elif tz:
        try:
            aware = naive.replace(tzinfo=ZoneInfo(tz))
        except (ZoneInfoNotFoundError, ValueError) as exc:
            raise PhotoError(f"unknown site time zone {tz!r}") from exc
    else:
        raise PhotoError("EXIF time has no OffsetTimeOriginal and no site time zone is configured (set tz)")
    delta = aware - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


def exif_focal(exif: Image.Exif, width_px: int, height_px: int) -> tuple[float | None, float | None]:
    """(focal_px, focal_35mm_mm) of the stored image from EXIF; ``(None, None)`` when unknown.

    35 mm equivalent: ``f_px = f35 * diag_px / 43.27`` (diagonal of 36x24 mm). Else focal length
    in mm times the focal-plane resolution (pixels per mm, rescaled when the stored image is
    smaller than PixelXDimension). Raises PhotoError when the result gives a horizontal field of
    view outside [1, 170] degrees.
    """
    sub = _exif_sub(exif, _EXIF_IFD)
    f35 = _rational(sub.get(_FOCAL_35MM))
    f_mm = _rational(sub.get(_FOCAL_LENGTH))
    long_px = max(width_px, height_px)
    f_px: float | None = None
    if f35 is not None and f35 > 0:
        f_px = cam.focal_px_from_35mm(f35, width_px, height_px)
    elif f_mm is not None and f_mm > 0:
        res = _rational(sub.get(_FP_XRES))
        unit_mm = _FP_UNIT_MM.get(int(sub.get(_FP_UNIT, 2) or 2))  # type: ignore[call-overload]
        if res is not None and res > 0 and unit_mm is not None:
            px_per_mm = res / unit_mm
            dims = [d for d in (_rational(sub.get(_PIXEL_X_DIM)), _rational(sub.get(_PIXEL_Y_DIM))) if d]
            scale = long_px / max(dims) if dims else 1.0
            f_px = f_mm * px_per_mm * scale
            f35 = None
    elif (f35 is not None and f35 < 0) or (f_mm is not None and f_mm < 0):
        raise PhotoError(f"absurd EXIF focal length ({f35 or f_mm} mm)")
    if f_px is None:
        return None, f35 if f35 else None
    fov_deg = math.degrees(2.0 * math.atan(width_px / (2.0 * f_px)))
    if not (MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG):
        raise PhotoError(
            f"absurd EXIF focal length: {f_px:.1f} px for {width_px} px width = {fov_deg:.2f} deg field of view"
        )
    return f_px, f35 if f35 else None


def photo_from_bytes(
    data: bytes,
    *,
    site: str,
    camera_id: str | None,
    tz: str | None,
    filename: str = "",
    source: str = "",
    capture_time_ns: int | None = None,
    fallback_time_ns: int | None = None,
    now_ns: int | None = None,
    max_pixels: int = MAX_PIXELS,
    future_tolerance_s: float = FUTURE_TOLERANCE_S,
) -> Photo:
    """A ``Photo`` message from image bytes.

    Capture time: ``capture_time_ns`` if given, else EXIF, else ``fallback_time_ns`` (e.g. the
    file's mtime when the operator allows it), else PhotoError. ``tz``: the site's IANA zone,
    used for EXIF times without an offset (``None`` = not configured). ``now_ns`` (default the
    clock) bounds capture times from above (+ ``future_tolerance_s``).
    """
    img = check_image(data, max_pixels)
    t_ns = capture_time_ns
    if t_ns is None:
        t_ns = exif_capture_time_ns(img.exif, tz)
    if t_ns is None:
        t_ns = fallback_time_ns
    if t_ns is None:
        raise PhotoError("photo has no EXIF DateTimeOriginal and no capture time was given")
    now = time.time_ns() if now_ns is None else now_ns
    if t_ns > now + int(future_tolerance_s * 1e9):
        when = dt.datetime.fromtimestamp(t_ns / 1e9, tz=dt.UTC).isoformat()
        raise PhotoError(f"capture time {when} is in the future (check the camera clock / time zone)")
    f_px, f35 = exif_focal(img.exif, img.width_px, img.height_px)
    return Photo(
        site=site,
        photo_id=hashlib.sha256(img.data).hexdigest()[:16],
        camera_id=camera_id,
        capture_time_ns=int(t_ns),
        tz=tz or "UTC",
        media_type=img.media_type,  # type: ignore[arg-type]
        data=img.data,
        width_px=img.width_px,
        height_px=img.height_px,
        focal_px=f_px,
        focal_35mm_mm=f35,
        gps=exif_gps(img.exif),
        filename=filename,
        source=source,
    )


def photo_from_file(
    path: str | Path,
    camera_id: str | None,
    site: str,
    tz: str | None,
    *,
    use_mtime: bool = False,
    source: str = "file",
    max_pixels: int = MAX_PIXELS,
) -> Photo:
    """``Photo`` from an image file (what ``constructaide push`` and the folder watcher use).

    ``use_mtime``: take the file's modification time when EXIF has no capture time.
    Raises PhotoError (a ValueError) with the file name in the message.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
        mtime_ns = p.stat().st_mtime_ns
    except OSError as exc:
        raise PhotoError(f"{p}: cannot read: {exc}") from exc
    try:
        return photo_from_bytes(
            data,
            site=site,
            camera_id=camera_id,
            tz=tz,
            filename=p.name,
            source=source,
            fallback_time_ns=mtime_ns if use_mtime else None,
            max_pixels=max_pixels,
        )
    except PhotoError as exc:
        raise PhotoError(f"{p.name}: {exc}") from exc
