"""Procedural, seeded RGB textures (uint8, (H, W, 3)) rich in SIFT-detectable detail.

Each texture also has a physical tile size in metres (``TEXTURE_TILE_M``) used by the world-planar UV mapping.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]

# (width_m, height_m) one texture repeat covers.
TEXTURE_TILE_M: dict[str, tuple[float, float]] = {
    "concrete": (2.4, 2.4),
    "brick": (2.025, 2.025),
    "glass": (1.8, 1.8),
    "steel": (2.0, 2.0),
    "roof": (2.4, 2.4),
    "grass": (6.0, 6.0),
    "foliage": (3.0, 3.0),
    "bark": (1.0, 1.0),
    "facade_a": (12.0, 12.0),
    "facade_b": (10.0, 10.0),
    "facade_c": (15.0, 15.0),
    "hoarding": (8.0, 2.2),
    "truck": (7.0, 3.5),
    "cabin": (6.0, 3.0),
    "crane": (2.0, 2.0),
    "asphalt": (5.0, 5.0),
}


def fractal_noise(rng: np.random.Generator, h: int, w: int, octaves: int = 5, base_cells: int = 4) -> F32:
    """Smooth multi-octave value noise in [0, 1], tileable (wraps at the borders)."""
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        grid = rng.random((cells, cells)).astype(np.float32)
        grid = np.pad(grid, ((0, 1), (0, 1)), mode="wrap")
        up = cv2.resize(grid, (w + w // cells, h + h // cells), interpolation=cv2.INTER_CUBIC)[:h, :w]
        out += amp * up
        total += amp
        amp *= 0.55
        cells *= 2
        if cells > min(h, w) // 2:
            break
    out /= total
    return np.clip((out - out.min()) / max(float(np.ptp(out)), 1e-6), 0, 1)


def _speckle(rng: np.random.Generator, h: int, w: int, density: float, radius: int = 1) -> F32:
    """Sparse dots in [0, 1]: ``density`` dots per pixel."""
    img = np.zeros((h, w), np.float32)
    n = int(density * h * w)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    vals = rng.random(n).astype(np.float32)
    for y, x, v in zip(ys, xs, vals, strict=True):
        cv2.circle(img, (int(x), int(y)), radius + int(v * 2), float(v), -1)
    return img


def _to_u8(rgb: NDArray) -> U8:
    return np.clip(rgb, 0, 255).astype(np.uint8)


def concrete(rng: np.random.Generator, px: int) -> U8:
    n = fractal_noise(rng, px, px, 6, 4)
    sp = _speckle(rng, px, px, 0.004, 0)
    g = 150 + 45 * (n - 0.5) - 70 * sp
    # formwork joints (1.2 m panels) and tie holes
    step = px // 2
    g[:, ::step] -= 35
    g[::step, :] -= 35
    for yy in range(step // 4, px, step // 2):
        for xx in range(step // 4, px, step // 2):
            cv2.circle(g, (xx, yy), max(px // 180, 2), 80.0, -1)
    g = cv2.GaussianBlur(g, (3, 3), 0)
    return _to_u8(np.stack([g * 1.0, g * 0.99, g * 0.95], -1))


def brick(rng: np.random.Generator, px: int) -> U8:
    """Running bond: 9 bricks across, 27 courses (0.225 m x 0.075 m modules over 2.025 m)."""
    img = np.zeros((px, px, 3), np.float32)
    mortar = np.array([185, 180, 170], np.float32)
    img[:] = mortar
    bw, bh = px / 9, px / 27
    for row in range(27):
        off = (row % 2) * bw / 2
        for col in range(-1, 10):
            x0, x1 = int(round(col * bw + off + bw * 0.05)), int(round((col + 1) * bw + off - bw * 0.05))
            y0, y1 = int(round(row * bh + bh * 0.1)), int(round((row + 1) * bh - bh * 0.1))
            base = np.array([150, 60, 40], np.float32) * rng.uniform(0.7, 1.25) + rng.normal(0, 12, 3)
            xs = [x % px for x in range(x0, x1)]
            img[y0:y1, xs] = base
    n = fractal_noise(rng, px, px, 6, 8)
    sp = _speckle(rng, px, px, 0.003, 0)
    img *= (0.8 + 0.4 * n)[..., None]
    img -= 60 * sp[..., None]
    return _to_u8(img)


def glass(rng: np.random.Generator, px: int) -> U8:
    n = fractal_noise(rng, px, px, 4, 2)
    y = np.linspace(0, 1, px, dtype=np.float32)[:, None]
    g = 40 + 60 * n + 40 * y
    img = np.stack([g * 0.7, g * 0.85, g * 1.1], -1)
    # reflections of clouds/frames: diagonal streaks
    for _ in range(6):
        x0 = int(rng.integers(0, px))
        cv2.line(img, (x0, 0), (x0 + px // 3, px), (150, 160, 170), int(rng.integers(2, 8)))
    return _to_u8(cv2.GaussianBlur(img, (5, 5), 0))


def steel(rng: np.random.Generator, px: int) -> U8:
    n = fractal_noise(rng, px, px, 6, 4)
    rust = _speckle(rng, px, px, 0.002, 1)
    base = np.array([70, 90, 120], np.float32)
    img = base * (0.8 + 0.4 * n)[..., None]
    img += rust[..., None] * np.array([90, 30, -30], np.float32)
    for yy in range(px // 8, px, px // 4):
        for xx in range(px // 8, px, px // 4):
            cv2.circle(img, (xx, yy), max(px // 100, 2), (30, 30, 35), -1)
    return _to_u8(img)


def roof(rng: np.random.Generator, px: int) -> U8:
    img = np.zeros((px, px, 3), np.float32)
    rows, cols = 8, 12
    th, tw = px / rows, px / cols
    for r in range(rows):
        off = (r % 2) * tw / 2
        for c in range(-1, cols + 1):
            col = np.array([160, 70, 45], np.float32) * rng.uniform(0.65, 1.2)
            x0, x1 = int(c * tw + off), int((c + 1) * tw + off) - 2
            xs = [x % px for x in range(x0, x1)]
            for k in range(int(th) - 2):
                shade = 0.6 + 0.4 * k / th
                img[int(r * th) + k, xs] = col * shade
    n = fractal_noise(rng, px, px, 5, 8)
    img *= (0.85 + 0.3 * n)[..., None]
    return _to_u8(img)


def grass(rng: np.random.Generator, px: int) -> U8:
    n1 = fractal_noise(rng, px, px, 6, 4)
    n2 = fractal_noise(rng, px, px, 3, 2)
    sp = _speckle(rng, px, px, 0.01, 0)
    img = np.stack([60 + 50 * n2, 100 + 60 * n1, 40 + 20 * n1], -1) + 50 * sp[..., None]
    return _to_u8(img)


def asphalt(rng: np.random.Generator, px: int) -> U8:
    n = fractal_noise(rng, px, px, 6, 8)
    sp = _speckle(rng, px, px, 0.01, 0)
    g = 70 + 30 * n + 60 * sp
    return _to_u8(np.stack([g, g, g * 1.03], -1))


def foliage(rng: np.random.Generator, px: int) -> U8:
    img = np.zeros((px, px, 3), np.float32)
    img[:] = (25, 45, 20)
    for _ in range(int(px * px / 60)):
        x, y = rng.integers(0, px, 2)
        col = np.array([50, 110, 40], np.float32) * rng.uniform(0.5, 1.4)
        cv2.ellipse(
            img,
            (int(x), int(y)),
            (int(rng.integers(3, 9)), int(rng.integers(2, 5))),
            float(rng.uniform(0, 180)),
            0,
            360,
            col.tolist(),
            -1,
        )
    return _to_u8(img)


def bark(rng: np.random.Generator, px: int) -> U8:
    n = fractal_noise(rng, px, px // 8, 4, 2)
    n = cv2.resize(n, (px, px))
    g = 70 + 60 * n + 20 * fractal_noise(rng, px, px, 5, 8)
    return _to_u8(np.stack([g, g * 0.8, g * 0.6], -1))


def facade(rng: np.random.Generator, px: int, tile_m: float, plaster: tuple[int, int, int]) -> U8:
    """Neighbour facade: plaster with a grid of windows (3 m storeys, 2.5 m window pitch)."""
    n = fractal_noise(rng, px, px, 6, 4)
    img = np.array(plaster, np.float32) * (0.85 + 0.3 * n)[..., None]
    m_to_px = px / tile_m
    storeys, pitch = max(1, int(round(tile_m / 3.0))), max(1, int(round(tile_m / 2.5)))
    for r in range(storeys):
        for c in range(pitch):
            x0 = int((c * tile_m / pitch + 0.6) * m_to_px)
            y0 = int((r * tile_m / storeys + 0.8) * m_to_px)
            x1, y1 = x0 + int(1.2 * m_to_px), y0 + int(1.5 * m_to_px)
            cv2.rectangle(img, (x0 - 3, y0 - 3), (x1 + 3, y1 + 3), (235, 235, 230), -1)
            glass_col = np.array([50, 60, 75], np.float32) * rng.uniform(0.7, 1.5)
            cv2.rectangle(img, (x0, y0), (x1, y1), glass_col.tolist(), -1)
            if rng.random() < 0.5:  # curtain
                cv2.rectangle(
                    img,
                    (x0, y0),
                    (x0 + int((x1 - x0) * rng.uniform(0.2, 0.6)), y1),
                    (float(rng.integers(120, 230)), float(rng.integers(100, 220)), 180.0),
                    -1,
                )
            cv2.line(img, ((x0 + x1) // 2, y0), ((x0 + x1) // 2, y1), (220, 220, 215), 2)
    return _to_u8(img)


def hoarding(rng: np.random.Generator, w: int, h: int) -> U8:
    """Site hoarding panels with a printed banner (text and logos)."""
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = (30, 110, 60)
    panel = w // 8
    for i in range(8):
        cv2.line(img, (i * panel, 0), (i * panel, h), (20, 60, 35), 3)
    words = ["BOUWBEDRIJF", "NIJMEGEN", "LENT", "PLOT 7", "VEILIG WERKEN", "HELM OP", "24 WONINGEN", "2026"]
    for _ in range(14):
        txt = words[int(rng.integers(0, len(words)))]
        x, y = int(rng.integers(0, w - 60)), int(rng.integers(h // 6, h - 5))
        cv2.putText(
            img,
            txt,
            (x, y),
            cv2.FONT_HERSHEY_SIMPLEX,
            float(rng.uniform(0.6, 1.6)) * h / 256,
            (245, 245, 240),
            max(1, h // 120),
            cv2.LINE_AA,
        )
    for _ in range(10):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.circle(img, (x, y), int(rng.integers(h // 20, h // 8)), (230, 200, 40), -1)
        cv2.circle(img, (x, y), int(rng.integers(h // 40, h // 20)), (30, 110, 60), -1)
    n = fractal_noise(rng, h, w, 4, 4)
    return _to_u8(img * (0.85 + 0.3 * n)[..., None])


def vehicle(rng: np.random.Generator, w: int, h: int, body: tuple[int, int, int], label: str) -> U8:
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = body
    cv2.rectangle(img, (0, int(h * 0.55)), (w, int(h * 0.62)), (200, 40, 30), -1)
    cv2.putText(
        img,
        label,
        (int(w * 0.08), int(h * 0.45)),
        cv2.FONT_HERSHEY_DUPLEX,
        h / 140,
        (30, 40, 90),
        max(1, h // 60),
        cv2.LINE_AA,
    )
    for k in range(0, w, max(w // 24, 4)):
        cv2.line(img, (k, int(h * 0.7)), (k, h), (np.array(body) * 0.7).tolist(), 1)
    n = fractal_noise(rng, h, w, 4, 4)
    return _to_u8(img * (0.9 + 0.2 * n)[..., None])


def crane(rng: np.random.Generator, px: int) -> U8:
    img = np.zeros((px, px, 3), np.float32)
    img[:] = (70, 80, 90)
    yellow = (235, 190, 30)
    t = max(px // 30, 2)
    cv2.rectangle(img, (0, 0), (px, px), yellow, 2 * t)
    cv2.line(img, (0, 0), (px, px), yellow, t)
    cv2.line(img, (0, px), (px, 0), yellow, t)
    n = fractal_noise(rng, px, px, 4, 4)
    img *= (0.85 + 0.3 * n)[..., None]
    return _to_u8(img)


def make_textures(rng: np.random.Generator, px: int) -> dict[str, U8]:
    """All repeating material textures at side ``px`` (non-square ones scaled to their aspect)."""
    return {
        "concrete": concrete(rng, px),
        "brick": brick(rng, px),
        "glass": glass(rng, px // 2),
        "steel": steel(rng, px // 2),
        "roof": roof(rng, px),
        "grass": grass(rng, px),
        "foliage": foliage(rng, px // 2),
        "bark": bark(rng, px // 4),
        "facade_a": facade(rng, px, 12.0, (215, 200, 170)),
        "facade_b": facade(rng, px, 10.0, (190, 190, 195)),
        "facade_c": facade(rng, px, 15.0, (160, 90, 70)),
        "hoarding": hoarding(rng, px * 2, max(px // 2, 64)),
        "truck": vehicle(rng, px, px // 2, (235, 235, 230), "VAN DER BERG TRANSPORT"),
        "cabin": vehicle(rng, px, px // 2, (40, 80, 160), "BOUWKEET 04"),
        "crane": crane(rng, px // 4),
        "asphalt": asphalt(rng, px),
    }


def site_ground(
    rng: np.random.Generator,
    px: int,
    extent_m: float,
    paths: list[tuple[float, float, float, float]],
    pads: list[tuple[float, float, float, float]],
) -> U8:
    """Non-repeating gravel ground of the site, ``extent_m`` square centred on the origin, with paved
    ``paths`` (x0, y0, x1, y1 centre line, 2.5 m wide) and concrete ``pads`` (x0, y0, x1, y1 boxes).
    Row 0 is the south edge (y = -extent/2; pyrender uploads rows bottom-up), column 0 the west edge."""
    n1 = fractal_noise(rng, px, px, 7, 4)
    n2 = fractal_noise(rng, px, px, 3, 3)
    gravel = 110 + 50 * (n1 - 0.5) + 25 * (n2 - 0.5)
    img = np.stack([gravel * 1.02, gravel * 0.97, gravel * 0.88], -1)
    # stones
    n = int(px * px / 25)
    ys, xs = rng.integers(0, px, n), rng.integers(0, px, n)
    vals = rng.uniform(-70, 70, n)
    img[ys, xs] += vals[:, None]
    img = cv2.GaussianBlur(img, (3, 3), 0)
    scale = px / extent_m

    def to_px(x: float, y: float) -> tuple[int, int]:
        return int((x + extent_m / 2) * scale), int((y + extent_m / 2) * scale)

    for x0, y0, x1, y1 in pads:
        cv2.rectangle(img, to_px(x0, y1), to_px(x1, y0), (150, 148, 140), -1)
    for x0, y0, x1, y1 in paths:
        cv2.line(img, to_px(x0, y0), to_px(x1, y1), (95, 90, 92), int(2.5 * scale))
        # paving joints along the path
        length = float(np.hypot(x1 - x0, y1 - y0))
        for k in range(int(length / 0.6)):
            t = k * 0.6 / length
            cx, cy = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
            nx, ny = -(y1 - y0) / length * 1.25, (x1 - x0) / length * 1.25
            cv2.line(img, to_px(cx - nx, cy - ny), to_px(cx + nx, cy + ny), (70, 66, 68), max(1, int(scale * 0.03)))
    # tyre tracks and puddles
    for _ in range(12):
        pts = np.cumsum(rng.normal(0, 3, (8, 2)), 0) + rng.uniform(-extent_m / 3, extent_m / 3, 2)
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            cv2.line(img, to_px(*a), to_px(*b), (80, 75, 65), max(1, int(0.25 * scale)))
    mottling = fractal_noise(rng, px, px, 5, 6)
    img *= (0.85 + 0.3 * mottling)[..., None]
    return _to_u8(img)
