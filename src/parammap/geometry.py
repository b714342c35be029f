"""Camera and surface geometry shared by every stage.

Frames follow ``docs/reference/conventions.md``: the surface lies in z = 0 of the surface (world)
frame, units are millimetres, and a pose maps ``p_cam = R @ p_world + t`` (OpenCV).
Intrinsics are a 3x3 camera matrix ``K`` and OpenCV's distortion vector
``(k1, k2, p1, p2[, k3])`` (004 app. F).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "Intrinsics",
    "camera_centre",
    "distort_normalized",
    "look_at",
    "normalized_to_plane",
    "pixel_to_normalized",
    "pixel_to_plane",
    "plane_to_texel",
    "project_points",
    "texel_centres",
    "undistort_normalized",
    "unit",
]


@dataclass
class Intrinsics:
    """Pinhole camera with OpenCV distortion ``(k1, k2, p1, p2, k3)``; K in pixels."""

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]  # width, height
    rms_px: float = float("nan")
    images_used: int = 0
    per_image_rms_px: dict | None = None


def unit(v: np.ndarray, axis: int = -1) -> np.ndarray:
    """Normalise vectors along ``axis`` (zero vectors stay zero)."""
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def camera_centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centre in the surface frame, ``C = -R.T @ t`` (mm), shape (3,)."""
    return -np.asarray(R).T @ np.asarray(t).reshape(3)


def look_at(
    centre: np.ndarray, target: np.ndarray, roll_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pose of a camera at ``centre`` looking at ``target``.

    The image's up direction follows the surface's +z (or +y for views near the
    normal), then is rolled by ``roll_rad`` about the optical axis.

    Returns
    -------
    R : (3, 3) float64 rotation, world to camera.
    t : (3,) float64 translation (mm).
    """
    centre = np.asarray(centre, float)
    z_c = unit(np.asarray(target, float) - centre)
    up = np.array([0.0, 0.0, 1.0]) if abs(z_c[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y_c = -unit(up - (up @ z_c) * z_c)  # OpenCV's y points down the image
    x_c = np.cross(y_c, z_c)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x_r, y_r = c * x_c + s * y_c, -s * x_c + c * y_c
    R = np.stack([x_r, y_r, z_c])
    return R, -R @ centre


def _coefficients(dist: np.ndarray) -> np.ndarray:
    d = np.zeros(5)
    dist = np.asarray(dist, float).ravel()
    d[: min(5, dist.size)] = dist[:5]
    return d


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's radial-tangential distortion to normalised coordinates (N, 2)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _distort_with_jacobian(xy: np.ndarray, dist: np.ndarray):
    """:func:`distort_normalized` and its Jacobian (d xd/dx, d xd/dy, d yd/dx, d yd/dy)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    g = 2 * k1 + r2 * (4 * k2 + 6 * k3 * r2)  # d radial / d(x, y) = g (x, y)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    a = radial + g * x * x + 2 * p1 * y + 6 * p2 * x
    b = g * x * y + 2 * p1 * x + 2 * p2 * y
    c = g * x * y + 2 * p1 * x + 2 * p2 * y
    d = radial + g * y * y + 6 * p1 * y + 2 * p2 * x
    return np.stack([xd, yd], axis=-1), (a, b, c, d)


def ray_jacobian(xy: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """How the undistorted normalised point ``xy`` (..., 2) of a fixed pixel moves with
    the intrinsics: (..., 2, 9) derivatives by fx, fy, cx, cy, k1, k2, p1, p2, k3.

    The pixel fixes the distorted point ``xd = K^-1 (u, v)``; ``xy`` solves
    ``distort(xy) = xd``, so ``d xy = J^-1 (d xd - d distort / d dist)`` with J the
    distortion's Jacobian at ``xy`` (implicit function theorem).
    """
    xy = np.asarray(xy, float)
    xd, (a, b, c, d) = _distort_with_jacobian(xy, dist)
    fx, s, fy = float(K[0, 0]), float(K[0, 1]), float(K[1, 1])
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    zero = np.zeros_like(x)
    # the distorted point's change by fx, fy, cx, cy (xd = (u - cx - s yd) / fx,
    # yd = (v - cy) / fy), then minus the distortion's change by its coefficients
    dyd = [zero, -xd[..., 1] / fy, zero, np.full_like(x, -1.0 / fy)]
    dxd = [-xd[..., 0] / fx, -s / fx * dyd[1], np.full_like(x, -1.0 / fx), -s / fx * dyd[3]]
    dxd += [-x * r2, -x * r2 * r2, -2 * x * y, -(r2 + 2 * x * x), -x * r2 ** 3]
    dyd += [-y * r2, -y * r2 * r2, -(r2 + 2 * y * y), -2 * x * y, -y * r2 ** 3]
    ex, ey = np.stack(dxd, -1), np.stack(dyd, -1)
    det = a * d - b * c
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)[..., None]
    return np.stack([(d[..., None] * ex - b[..., None] * ey) / det,
                     (-c[..., None] * ex + a[..., None] * ey) / det], -2)


def undistort_normalized(xy_d: np.ndarray, dist: np.ndarray, iters: int = 40,
                         guess: np.ndarray | None = None) -> np.ndarray:
    """Invert :func:`distort_normalized` by Newton iterations with the analytic
    Jacobian (vectorised), started at ``guess`` (the points of a nearby camera: two
    iterations instead of about eight) or at ``xy_d``.

    Accurate to ~1e-13 for the moderate distortion of real lenses; OpenCV's
    ``undistortPoints`` stops after 5 fixed-point steps, too few for sub-0.01 px work.
    """
    xy_d = np.asarray(xy_d, float)
    xy = xy_d.copy() if guess is None else np.array(guess, float, copy=True)
    for _ in range(iters):
        dxy, (a, b, c, d) = _distort_with_jacobian(xy, dist)
        f = dxy - xy_d
        if np.max(np.abs(f), initial=0.0) < 1e-13:
            break
        det = a * d - b * c
        det = np.where(np.abs(det) > 1e-12, det, 1e-12)
        xy = xy - np.stack([(d * f[..., 0] - b * f[..., 1]) / det,
                            (-c * f[..., 0] + a * f[..., 1]) / det], axis=-1)
    return xy


def project_points(
    points: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Project world points (N, 3) to distorted pixel coordinates (N, 2) with OpenCV."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    uv, _ = cv2.projectPoints(
        np.asarray(points, float).reshape(-1, 1, 3), rvec, np.asarray(t, float).reshape(3, 1),
        np.asarray(K, float), np.asarray(dist, float),
    )
    return uv.reshape(-1, 2)


def pixel_to_plane(
    uv: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Intersect the rays of pixel coordinates (..., 2) with the plane z = 0.

    Pixel centres are at integer coordinates (OpenCV's convention).

    Returns
    -------
    points : (..., 3) intersection points in the surface frame (mm).
    hit : (...) bool, True where the ray meets the plane in front of the camera.
    """
    return normalized_to_plane(pixel_to_normalized(uv, K, dist), R, t)


def pixel_to_normalized(uv: np.ndarray, K: np.ndarray, dist: np.ndarray,
                        guess: np.ndarray | None = None) -> np.ndarray:
    """Undistorted normalised image coordinates (..., 2) of pixel coordinates
    (..., 2): the camera-frame ray (x, y, 1) of each pixel (``guess``: a warm start of
    the undistortion, :func:`undistort_normalized`)."""
    uv = np.asarray(uv, float)
    K = np.asarray(K, float)
    xd = np.stack([(uv[..., 0] - K[0, 2] - K[0, 1] * (uv[..., 1] - K[1, 2]) / K[1, 1]) / K[0, 0],
                   (uv[..., 1] - K[1, 2]) / K[1, 1]], axis=-1)
    return undistort_normalized(xd, dist, guess=guess)


def normalized_to_plane(xn: np.ndarray, R: np.ndarray, t: np.ndarray,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pixel_to_plane` of camera rays (x, y, 1) given by their undistorted
    normalised coordinates xn (..., 2) (:func:`pixel_to_normalized`)."""
    ray_cam = np.concatenate([xn, np.ones(xn.shape[:-1] + (1,))], axis=-1)
    R = np.asarray(R, float)
    ray = ray_cam @ R  # R.T @ ray for each ray
    C = camera_centre(R, t)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -C[2] / ray[..., 2]
    hit = np.isfinite(s) & (s > 0)
    s = np.where(hit, s, 0.0)
    return C + s[..., None] * ray, hit


def texel_centres(S: int, T: int, width_mm: float, height_mm: float,
                  rows: np.ndarray | None = None, cols: np.ndarray | None = None,
                  ) -> np.ndarray:
    """Centres of the S x T texel grid in the surface frame, shape (T, S, 3) (mm); of
    the texel rows ``rows`` and columns ``cols`` only (index arrays), shape (len(rows),
    len(cols), 3), when given."""
    j = np.arange(S) if cols is None else np.asarray(cols)
    i = np.arange(T) if rows is None else np.asarray(rows)
    x = (j + 0.5) * width_mm / S
    y = height_mm - (i + 0.5) * height_mm / T
    X, Y = np.meshgrid(x, y)
    return np.stack([X, Y, np.zeros_like(X)], axis=-1)


def plane_to_texel(
    x: np.ndarray, y: np.ndarray, S: int, T: int, width_mm: float, height_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates (row, col) of plane points; texel centres are at
    integer + 0.5, so ``floor`` gives the texel index."""
    col = np.asarray(x) * S / width_mm
    row = (height_mm - np.asarray(y)) * T / height_mm
    return row, col


def sample_image(img: np.ndarray, x: np.ndarray, y: np.ndarray, nearest: bool = False,
                 border: float = np.nan) -> np.ndarray:
    """Sample an image at pixel coordinates (any shape; pixel centres at integers) with
    bilinear (or nearest) interpolation; ``border`` outside. Returns x.shape + channels.

    cv2.remap is fast but wants 2-D maps under 32767 rows and columns; points are laid
    out in rows of 4096 here.
    """
    shape = np.shape(x)
    xf = np.asarray(x, np.float32).ravel()
    yf = np.asarray(y, np.float32).ravel()
    n = xf.size
    w = 4096
    rows = max(1, -(-n // w))
    pad = rows * w - n
    mx = np.pad(xf, (0, pad), constant_values=-1e6).reshape(rows, w)
    my = np.pad(yf, (0, pad), constant_values=-1e6).reshape(rows, w)
    src = np.ascontiguousarray(img)
    chans = src.shape[2] if src.ndim == 3 else 1
    out = np.empty((rows, w, chans), src.dtype)
    for r0 in range(0, rows, 4096):
        sl = slice(r0, min(rows, r0 + 4096))
        res = cv2.remap(src, mx[sl], my[sl],
                        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=(border,) * 4)
        out[sl] = res.reshape(res.shape[:2] + (chans,))
    out = out.reshape(-1, chans)[:n]
    return out.reshape(shape + ((chans,) if src.ndim == 3 else ()))
