"""Image and mask codec shared by every node and bench: JPEG/PNG bytes <-> uint8 arrays (OpenCV).

Colour images are BGR (OpenCV's order) unless a function says RGB. Masks are (H, W) uint8 0/255 PNGs on the
wire (``OcclusionMask.mask_png``); a pixel is set where the decoded value is > 127.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from schemas.messages import OcclusionMask

U8 = NDArray[np.uint8]


def _decode(data: bytes, flags: int, what: str) -> U8:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise ValueError(f"{what}: not a decodable JPEG/PNG image ({len(data)} bytes)")
    return np.asarray(img, np.uint8)


_REDUCED_COLOR = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}
_REDUCED_GRAY = {
    2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
    4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
    8: cv2.IMREAD_REDUCED_GRAYSCALE_8,
}


def decode_bgr(data: bytes, what: str = "image", reduced: int = 1) -> U8:
    """(H, W, 3) uint8 BGR of JPEG/PNG bytes, decoded at 1/``reduced`` size (1, 2, 4 or 8; JPEGs decode faster);
    ValueError naming ``what`` when undecodable."""
    return _decode(data, cv2.IMREAD_COLOR if reduced == 1 else _REDUCED_COLOR[reduced], what)


def decode_rgb(data: bytes, what: str = "image") -> U8:
    """(H, W, 3) uint8 RGB of JPEG/PNG bytes; ValueError naming ``what`` when undecodable."""
    return np.asarray(cv2.cvtColor(decode_bgr(data, what), cv2.COLOR_BGR2RGB), np.uint8)


def decode_unchanged(data: bytes, what: str = "image") -> U8:
    """The stored channels as they are (grey (H, W), BGR or BGRA (H, W, C)); ValueError when undecodable."""
    return _decode(data, cv2.IMREAD_UNCHANGED, what)


def decode_gray(data: bytes, what: str = "image", reduced: int = 1) -> U8:
    """(H, W) uint8 grey of JPEG/PNG bytes at 1/``reduced`` size (1, 2, 4 or 8); ValueError naming ``what`` when
    undecodable."""
    return _decode(data, cv2.IMREAD_GRAYSCALE if reduced == 1 else _REDUCED_GRAY[reduced], what)


def encode_png(img: U8, compression: int | None = None) -> bytes:
    """PNG bytes of a grey (H, W) or BGR / BGRA (H, W, 3|4) uint8 image (zlib level ``compression``, 0-9; None:
    OpenCV's default)."""
    params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise ValueError(f"cannot encode a {img.shape} {img.dtype} image as PNG")
    return buf.tobytes()


def encode_png_rgb(img: U8, compression: int = 1) -> bytes:
    """PNG bytes of an RGB or RGBA (H, W, 3|4) uint8 image."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    return encode_png(np.asarray(bgr, np.uint8), compression)


def encode_jpeg(img: U8, quality: int = 90) -> bytes:
    """JPEG bytes of a BGR (H, W, 3) or grey uint8 image at ``quality`` (0-100)."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"cannot encode a {img.shape} {img.dtype} image as JPEG")
    return buf.tobytes()


def encode_mask(mask: NDArray[np.generic]) -> bytes:
    """PNG bytes of a mask (H, W): 255 where ``mask`` is non-zero, else 0."""
    return encode_png(np.where(np.asarray(mask) > 0, 255, 0).astype(np.uint8))


def decode_mask(png: bytes, shape: tuple[int, int] | None = None, what: str = "mask") -> NDArray[np.bool_]:
    """(H, W) bool of a mask PNG (pixel > 127), resized (nearest) to ``shape`` = (H, W) when given and different."""
    m = decode_gray(png, what)
    if shape is not None and m.shape != tuple(shape):
        m = np.asarray(cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST), np.uint8)
    return np.asarray(m > 127)


def mask_of_message(msg: OcclusionMask | None, shape: tuple[int, int]) -> NDArray[np.bool_] | None:
    """(H, W) bool of a usable (status ``ok``, PNG present) occlusion mask resized to ``shape``, else None."""
    if msg is None or msg.status != "ok" or not msg.mask_png:
        return None
    return decode_mask(msg.mask_png, shape, f"occlusion mask of {msg.photo_id}")
