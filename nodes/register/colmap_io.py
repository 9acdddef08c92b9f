"""COLMAP text model I/O (cameras.txt, images.txt, points3D.txt).

COLMAP conventions: image coordinates have (0, 0) at the upper-left corner of the top-left pixel, so a pixel in
the project's OpenCV convention maps to ``u_colmap = u + 0.5`` (same for v and for the principal point).
``images.txt`` stores ``camera_from_world`` as quaternion (QW QX QY QZ) and translation. Cameras are written
with the RADIAL model ``f cx cy k1 k2`` (the project's distortion model exactly), or, for non-square pixels
(``Intrinsics.fy_over_fx != 1``), the OPENCV model ``fx fy cx cy k1 k2 p1 p2`` with ``p1 = p2 = 0`` (the same
radial model with separate focals).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from constructaide import camera as cam
from schemas.messages import Intrinsics


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a (3, 3) rotation, w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    K = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], R[1, 0] + R[0, 1], R[2, 0] + R[0, 2], R[2, 1] - R[1, 2]],
                [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], R[2, 1] + R[1, 2], R[0, 2] - R[2, 0]],
                [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], R[1, 0] - R[0, 1]],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    w, V = np.linalg.eigh(K)
    q = V[[3, 0, 1, 2], np.argmax(w)]
    return q if q[0] >= 0 else -q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a (w, x, y, z) quaternion."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass
class ColmapImage:
    """One registered image: name, intrinsics (OpenCV pixel convention), ``world_from_camera`` (4, 4), and its
    2D points (K, 2) OpenCV px with the index of their 3D point (K,) (-1 = none)."""

    name: str
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    points2d_px: np.ndarray
    point3d_index: np.ndarray


@dataclass
class ColmapModel:
    """Images, points (P, 3), colours (P, 3) u8, per-point reprojection error (P,) px."""

    images: list[ColmapImage]
    points: np.ndarray
    colors: np.ndarray
    errors_px: np.ndarray


def _f(value: float) -> str:
    """Shortest exact text of a float (numpy scalars included)."""
    return repr(float(value))


def write_text_model(model: ColmapModel, out_dir: Path) -> None:
    """Write cameras.txt, images.txt, points3D.txt (one camera per image, ids from 1)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    imgs = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    tracks: dict[int, list[tuple[int, int]]] = {}
    for k, im in enumerate(model.images):
        cid = iid = k + 1
        x = im.intrinsics
        if x.fy_over_fx == 1.0:
            vals: tuple[float, ...] = (x.f_px, x.cx_px + 0.5, x.cy_px + 0.5, x.k1, x.k2)
            model_name = "RADIAL"
        else:
            fx, fy = cam.focal_xy(x)
            model_name, vals = "OPENCV", (fx, fy, x.cx_px + 0.5, x.cy_px + 0.5, x.k1, x.k2, 0.0, 0.0)
        params = " ".join(_f(v) for v in vals)
        cams.append(f"{cid} {model_name} {x.width_px} {x.height_px} {params}")
        T = cam.invert_rigid(np.asarray(im.world_from_camera, dtype=np.float64))
        q = rotation_to_quaternion(T[:3, :3])
        t = T[:3, 3]
        name = im.name.replace(" ", "_") if " " in im.name else im.name
        imgs.append(f"{iid} {_f(q[0])} {_f(q[1])} {_f(q[2])} {_f(q[3])} {_f(t[0])} {_f(t[1])} {_f(t[2])} {cid} {name}")
        row = []
        for j, (uv, p) in enumerate(zip(im.points2d_px, im.point3d_index, strict=True)):
            pid = int(p) + 1 if p >= 0 else -1
            row.append(f"{uv[0] + 0.5:.3f} {uv[1] + 0.5:.3f} {pid}")
            if pid > 0:
                tracks.setdefault(pid, []).append((iid, j))
        imgs.append(" ".join(row))
    pts = ["# 3D point list with one line of data per point:", "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"]
    for p in range(len(model.points)):
        pid = p + 1
        X = model.points[p]
        c = model.colors[p]
        tr = " ".join(f"{i} {j}" for i, j in tracks.get(pid, []))
        pts.append(
            f"{pid} {_f(X[0])} {_f(X[1])} {_f(X[2])} {int(c[0])} {int(c[1])} {int(c[2])} {model.errors_px[p]:.4f} {tr}"
        )
    (out_dir / "cameras.txt").write_text("\n".join(cams) + "\n")
    (out_dir / "images.txt").write_text("\n".join(imgs) + "\n")
    (out_dir / "points3D.txt").write_text("\n".join(pts) + "\n")


def _intrinsics_from_colmap(model: str, w: int, h: int, p: list[float]) -> Intrinsics:
    aspect = 1.0
    if model == "RADIAL":
        f, cx, cy, k1, k2 = p
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k1 = p
        k2 = 0.0
    elif model == "SIMPLE_PINHOLE":
        f, cx, cy = p
        k1 = k2 = 0.0
    elif model == "PINHOLE":
        f, fy, cx, cy = p
        aspect = fy / f
        k1 = k2 = 0.0
    elif model == "OPENCV":
        f, fy, cx, cy, k1, k2, p1, p2 = p
        if p1 != 0.0 or p2 != 0.0:
            raise ValueError(f"COLMAP OPENCV camera with tangential distortion ({p1}, {p2}) is not supported")
        aspect = fy / f
    else:
        raise ValueError(f"unsupported COLMAP camera model {model}")
    return Intrinsics(width_px=w, height_px=h, f_px=f, cx_px=cx - 0.5, cy_px=cy - 0.5, k1=k1, k2=k2, fy_over_fx=aspect)


def read_text_model(in_dir: Path) -> ColmapModel:
    """Read a COLMAP text model back (OpenCV pixel convention, point ids re-indexed from 0 in file order)."""
    in_dir = Path(in_dir)
    cameras: dict[int, Intrinsics] = {}
    for line in (in_dir / "cameras.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        cameras[int(parts[0])] = _intrinsics_from_colmap(
            parts[1], int(parts[2]), int(parts[3]), [float(v) for v in parts[4:]]
        )
    pids, pts, cols, errs = [], [], [], []
    for line in (in_dir / "points3D.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        pids.append(int(parts[0]))
        pts.append([float(v) for v in parts[1:4]])
        cols.append([int(v) for v in parts[4:7]])
        errs.append(float(parts[7]))
    index = {pid: k for k, pid in enumerate(pids)}
    images = []
    lines = [ln for ln in (in_dir / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    for k in range(0, len(lines) - 1, 2):
        head = lines[k].split()
        if not head:
            continue
        q = np.array([float(v) for v in head[1:5]])
        t = np.array([float(v) for v in head[5:8]])
        vals = lines[k + 1].split()
        uv = np.array([[float(vals[j]), float(vals[j + 1])] for j in range(0, len(vals), 3)]).reshape(-1, 2) - 0.5
        p3 = np.array([index.get(int(vals[j + 2]), -1) for j in range(0, len(vals), 3)], dtype=int)
        images.append(
            ColmapImage(
                name=" ".join(head[9:]),
                intrinsics=cameras[int(head[8])],
                world_from_camera=cam.invert_rigid(cam.rigid(quaternion_to_rotation(q), t)),
                points2d_px=uv,
                point3d_index=p3,
            )
        )
    return ColmapModel(
        images,
        np.array(pts, float).reshape(-1, 3),
        np.array(cols, np.uint8).reshape(-1, 3),
        np.array(errs, float),
    )
