"""Ingest photos: EXIF time/offset/GPS/focal/orientation, content hash, bad input, folder watcher."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import math
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from constructaide.photos import PhotoError, photo_from_bytes, photo_from_file
from nodes.ingest.watcher import FolderWatcher, SeenHashes

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NOW_NS = int(dt.datetime(2026, 1, 1, tzinfo=dt.UTC).timestamp() * 1e9)


def make_jpeg(
    w: int = 90,
    h: int = 60,
    *,
    when: str | None = "2025:05:01 10:30:00",
    offset: str | None = "+02:00",
    f35: float | None = 28.0,
    f_mm: float | None = None,
    fp_res: float | None = None,
    orientation: int | None = None,
    gps: bool = False,
    seed: int = 0,
    fmt: str = "JPEG",
) -> bytes:
    rng = np.random.default_rng(seed)
    arr = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    arr[: h // 4, : w // 4] = (255, 0, 0)  # red block marks the top-left corner
    im = Image.fromarray(arr)
    ex = Image.Exif()
    sub = ex.get_ifd(0x8769)
    if when:
        sub[0x9003] = when
    if offset:
        sub[0x9011] = offset
    if f35 is not None:
        sub[0xA405] = f35
    if f_mm is not None:
        sub[0x920A] = f_mm
    if fp_res is not None:
        sub[0xA20E] = fp_res
        sub[0xA210] = 4  # pixels per mm
    if orientation:
        ex[0x0112] = orientation
    if gps:
        g = ex.get_ifd(0x8825)
        g[1], g[2], g[3], g[4], g[6] = "S", (33.0, 51.0, 36.0), "W", (70.0, 30.0, 0.0), 512.0
    buf = io.BytesIO()
    if len(ex) or sub:
        im.save(buf, format=fmt, exif=ex.tobytes())
    else:
        im.save(buf, format=fmt)
    return buf.getvalue()


def test_exif_time_offset_focal_gps_hash() -> None:
    data = make_jpeg(gps=True)
    p = photo_from_bytes(data, site="s", camera_id="cam-a", tz=None, now_ns=NOW_NS)
    assert p.capture_time_ns == int(dt.datetime(2025, 5, 1, 8, 30, tzinfo=dt.UTC).timestamp() * 1e9)
    assert p.photo_id == hashlib.sha256(p.data).hexdigest()[:16] and p.data == data  # upright: stored as given
    assert (p.width_px, p.height_px, p.media_type) == (90, 60, "image/jpeg")
    # 28 mm equivalent on a 3:2 image 90 px wide: 28/36 * 90 = 70 px.
    assert p.focal_px == pytest.approx(70.0, rel=1e-6) and p.focal_35mm_mm == 28.0
    assert p.gps is not None
    assert p.gps.lat_deg == pytest.approx(-(33 + 51 / 60 + 36 / 3600))
    assert p.gps.lon_deg == pytest.approx(-70.5) and p.gps.alt_m == pytest.approx(512.0)
    # Same bytes -> same id; different content -> different id.
    assert photo_from_bytes(data, site="s", camera_id=None, tz=None, now_ns=NOW_NS).photo_id == p.photo_id
    assert photo_from_bytes(make_jpeg(seed=1), site="s", camera_id=None, tz=None, now_ns=NOW_NS).photo_id != p.photo_id


def test_site_timezone_used_without_offset() -> None:
    data = make_jpeg(when="2025:01:15 12:00:00", offset=None)
    p = photo_from_bytes(data, site="s", camera_id=None, tz="Europe/Amsterdam", now_ns=NOW_NS)
    assert p.capture_time_ns == int(dt.datetime(2025, 1, 15, 11, 0, tzinfo=dt.UTC).timestamp() * 1e9)  # CET = UTC+1
    summer = make_jpeg(when="2025:07:15 12:00:00", offset=None)
    p2 = photo_from_bytes(summer, site="s", camera_id=None, tz="Europe/Amsterdam", now_ns=NOW_NS)
    assert p2.capture_time_ns == int(dt.datetime(2025, 7, 15, 10, 0, tzinfo=dt.UTC).timestamp() * 1e9)  # CEST
    assert p2.tz == "Europe/Amsterdam"
    with pytest.raises(PhotoError, match="no site time zone"):
        photo_from_bytes(data, site="s", camera_id=None, tz=None, now_ns=NOW_NS)


def test_focal_from_sensor_resolution_and_absurd_values() -> None:
    # 4 mm lens, 250 px/mm focal plane (4 um pixels) -> 1000 px.
    data = make_jpeg(400, 300, f35=None, f_mm=4.0, fp_res=250.0)
    p = photo_from_bytes(data, site="s", camera_id=None, tz=None, now_ns=NOW_NS)
    assert p.focal_px == pytest.approx(1000.0) and p.focal_35mm_mm is None
    none = photo_from_bytes(make_jpeg(f35=None), site="s", camera_id=None, tz=None, now_ns=NOW_NS)
    assert none.focal_px is None
    with pytest.raises(PhotoError, match="absurd EXIF focal length"):
        photo_from_bytes(make_jpeg(f35=0.5), site="s", camera_id=None, tz=None, now_ns=NOW_NS)  # > 170 deg FOV
    with pytest.raises(PhotoError, match="absurd EXIF focal length"):
        photo_from_bytes(make_jpeg(f35=50000.0), site="s", camera_id=None, tz=None, now_ns=NOW_NS)  # < 1 deg


def test_orientation_applied_and_reencoded() -> None:
    data = make_jpeg(90, 60, orientation=6)  # stored landscape, "rotate 90 CW to view"
    p = photo_from_bytes(data, site="s", camera_id=None, tz=None, now_ns=NOW_NS)
    assert (p.width_px, p.height_px) == (60, 90)
    assert p.data != data and p.photo_id == hashlib.sha256(p.data).hexdigest()[:16]
    im = Image.open(io.BytesIO(p.data))
    assert im.size == (60, 90) and im.getexif().get(0x0112) == 1
    arr = np.asarray(im.convert("RGB")).astype(int)
    # Rotating 90 deg clockwise moves the red top-left block to the top-right corner.
    assert arr[3, 56, 0] > 200 and arr[3, 56, 1] < 60
    assert arr[3, 3, 0] < 200 or arr[3, 3, 1] > 60
    # Focal length is rotation invariant: 28 mm eq on a 60x90 image = 28 * diag / 43.27.
    assert p.focal_px == pytest.approx(28.0 * math.hypot(60, 90) / math.hypot(36, 24))
    assert p.capture_time_ns == int(dt.datetime(2025, 5, 1, 8, 30, tzinfo=dt.UTC).timestamp() * 1e9)


def _png_bomb(w: int, h: int) -> bytes:
    """A PNG whose header claims w x h pixels (tiny file)."""

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    idat = chunk(b"IDAT", zlib.compress(b"\x00" * 64))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b"")


def test_bad_photos_give_clear_errors() -> None:
    good = make_jpeg()
    kw = {"site": "s", "camera_id": None, "tz": "UTC", "now_ns": NOW_NS}
    with pytest.raises(PhotoError, match="truncated"):
        photo_from_bytes(good[: len(good) * 2 // 3], **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="truncated"):
        photo_from_bytes(good[:-2], **kw)  # type: ignore[arg-type]  # only the EOI marker missing
    with pytest.raises(PhotoError, match="not an image"):
        photo_from_bytes(b"%PDF-1.4 definitely not a photo" * 10, **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="empty"):
        photo_from_bytes(b"", **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="decompression bomb"):
        photo_from_bytes(_png_bomb(20000, 20000), **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="decompression bomb"):
        photo_from_bytes(_png_bomb(100000, 100000), **kw)  # type: ignore[arg-type]  # beyond Pillow's own limit
    with pytest.raises(PhotoError, match="no EXIF DateTimeOriginal"):
        photo_from_bytes(make_jpeg(when=None, offset=None, f35=None), **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="in the future"):
        photo_from_bytes(make_jpeg(when="2026:06:01 00:00:00"), **kw)  # type: ignore[arg-type]
    with pytest.raises(PhotoError, match="unreadable EXIF DateTimeOriginal"):
        photo_from_bytes(make_jpeg(when="yesterday"), **kw)  # type: ignore[arg-type]
    gif = io.BytesIO()
    Image.new("RGB", (8, 8)).save(gif, format="GIF")
    with pytest.raises(PhotoError, match="unsupported image format GIF"):
        photo_from_bytes(gif.getvalue(), **kw)  # type: ignore[arg-type]
    # An explicit capture time (e.g. from a camera's own metadata) replaces a missing EXIF time.
    p = photo_from_bytes(make_jpeg(when=None, offset=None), capture_time_ns=NOW_NS - 10**9, **kw)  # type: ignore[arg-type]
    assert p.capture_time_ns == NOW_NS - 10**9


def test_png_and_file_mtime(tmp_path: Path) -> None:
    path = tmp_path / "frame.png"
    path.write_bytes(make_jpeg(when=None, offset=None, f35=None, fmt="PNG"))
    with pytest.raises(PhotoError, match="frame.png: .*no EXIF DateTimeOriginal"):
        photo_from_file(path, "cam-b", "s", "UTC")
    p = photo_from_file(path, "cam-b", "s", "UTC", use_mtime=True)
    assert p.media_type == "image/png" and p.filename == "frame.png" and p.camera_id == "cam-b"
    assert p.capture_time_ns == path.stat().st_mtime_ns
    with pytest.raises(PhotoError, match="cannot read"):
        photo_from_file(tmp_path / "missing.jpg", None, "s", "UTC")


FOUNTAIN = DATA / "strecha" / "fountain-P11" / "images"


@pytest.mark.skipif(not FOUNTAIN.is_dir(), reason="Strecha fountain-P11 not present")
def test_real_jpeg_decodes() -> None:
    path = sorted(FOUNTAIN.glob("*.jpg"))[0]
    p = photo_from_bytes(path.read_bytes(), site="s", camera_id="c", tz="UTC", capture_time_ns=NOW_NS)
    assert (p.width_px, p.height_px) == (3072, 2048)


def test_folder_watcher_stable_files_and_dedupe(tmp_path: Path) -> None:
    w = FolderWatcher(tmp_path)
    (tmp_path / "cam-a").mkdir()
    a = tmp_path / "cam-a" / "a.jpg"
    a.write_bytes(b"x" * 10)
    (tmp_path / "upload.jpg.part").write_bytes(b"y")
    (tmp_path / ".hidden.jpg").write_bytes(b"z")
    (tmp_path / "notes.txt").write_text("n")
    assert w.poll() == []  # first sight: not yet known to be stable
    assert w.poll() == [a]
    assert w.poll() == []  # reported once
    with a.open("ab") as fh:  # still growing -> waits for a stable size
        fh.write(b"more")
    assert w.poll() == []
    assert w.poll() == [a]
    seen_file = tmp_path / "seen.txt"
    seen = SeenHashes(capacity=3, path=seen_file)
    assert seen.add("h1") and seen.add("h2") and not seen.add("h1")
    assert SeenHashes(capacity=3, path=seen_file).add("h2") is False  # persisted
    for h in ("h3", "h4", "h5"):
        seen.add(h)
    assert len(seen) == 3 and "h2" not in seen and "h5" in seen
    assert "h2" not in SeenHashes(capacity=3, path=seen_file)


def test_now_default_rejects_far_future() -> None:
    future = dt.datetime.fromtimestamp(time.time() + 86400 * 2, tz=dt.UTC).strftime("%Y:%m:%d %H:%M:%S")
    with pytest.raises(PhotoError, match="in the future"):
        photo_from_bytes(make_jpeg(when=future, offset="+00:00"), site="s", camera_id=None, tz=None)
