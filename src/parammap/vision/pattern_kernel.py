"""Compiled prediction of a marker's pattern as a photo shows it, for pose refinement
on the whole pattern (:class:`parammap.stages.calibration.PatternView`).

Each pixel is ``s`` sub-pixel rays (undistorted, normalised); each ray meets the
surface plane z = 0 of a camera with rotation R and centre C, the plane point maps to
the pattern by a homography, and the blurred pattern is read there with bilinear
interpolation (edge values beyond it, as ``scipy.ndimage.map_coordinates`` with
``order=1, mode="nearest"``). The numpy chain of those steps spent most of a pose's
time in temporaries; this is one compiled loop. Where numba is missing
:func:`pattern_predict` is None and the numpy chain is used;
:func:`pattern_predict_grad` adds the derivatives by the pose for an analytic Jacobian.
"""

from __future__ import annotations

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only without numba
    njit = None


def _read(tex: np.ndarray, u: float, v: float) -> tuple[float, float, float]:
    """The pattern at (u, v) (samples; read at row v - 0.5, column u - 0.5, bilinear,
    edges extended) and its slopes by u and v (zero where the read is clamped)."""
    H, W = tex.shape
    r = min(max(v - 0.5, 0.0), H - 1.0)
    c = min(max(u - 0.5, 0.0), W - 1.0)
    r0 = min(int(r), H - 2) if H > 1 else 0
    c0 = min(int(c), W - 2) if W > 1 else 0
    fr = r - r0
    fc = c - c0
    r1 = min(r0 + 1, H - 1)
    c1 = min(c0 + 1, W - 1)
    t00, t01, t10, t11 = tex[r0, c0], tex[r0, c1], tex[r1, c0], tex[r1, c1]
    val = (1 - fr) * ((1 - fc) * t00 + fc * t01) + fr * ((1 - fc) * t10 + fc * t11)
    gu = ((1 - fr) * (t01 - t00) + fr * (t11 - t10)) if 0.0 < u - 0.5 < W - 1.0 else 0.0
    gv = ((1 - fc) * (t10 - t00) + fc * (t11 - t01)) if 0.0 < v - 0.5 < H - 1.0 else 0.0
    return val, gu, gv


if njit is not None:
    _read = njit(cache=True, nogil=True, inline="always")(_read)


def _pattern_predict(R: np.ndarray, C: np.ndarray, nrm: np.ndarray, A: np.ndarray,
                     tex: np.ndarray, ns: int, pred: np.ndarray, xm: np.ndarray,
                     ym: np.ndarray) -> None:
    """Fill ``pred`` (n,) with each pixel's mean pattern value over its ``ns`` rays
    ``nrm`` (n ns, 2), and ``xm``, ``ym`` (n,) with its mean pattern coordinates
    (samples). R (3, 3), C (3,): the camera; A (3, 3): plane (mm) -> pattern."""
    n = pred.shape[0]
    for i in range(n):
        acc = 0.0
        ax = 0.0
        ay = 0.0
        for k in range(ns):
            x = nrm[i * ns + k, 0]
            y = nrm[i * ns + k, 1]
            s = -C[2] / (x * R[0, 2] + y * R[1, 2] + R[2, 2])
            X = C[0] + s * (x * R[0, 0] + y * R[1, 0] + R[2, 0])
            Y = C[1] + s * (x * R[0, 1] + y * R[1, 1] + R[2, 1])
            w = A[2, 0] * X + A[2, 1] * Y + A[2, 2]
            u = (A[0, 0] * X + A[0, 1] * Y + A[0, 2]) / w
            v = (A[1, 0] * X + A[1, 1] * Y + A[1, 2]) / w
            ax += u
            ay += v
            acc += _read(tex, u, v)[0]
        pred[i] = acc / ns
        xm[i] = ax / ns
        ym[i] = ay / ns




def _pattern_predict_grad(R: np.ndarray, C: np.ndarray, dR: np.ndarray, t: np.ndarray,
                          nrm: np.ndarray, A: np.ndarray, tex: np.ndarray, ns: int,
                          pred: np.ndarray, xm: np.ndarray, ym: np.ndarray,
                          dpred: np.ndarray, dxm: np.ndarray, dym: np.ndarray) -> None:
    """:func:`_pattern_predict` and its derivatives by the pose (rvec, tvec): ``dR``
    (3, 3, 3) the rotation's derivative by each rvec component (``cv2.Rodrigues``'
    Jacobian), ``t`` (3,) the translation; fills ``dpred``, ``dxm``, ``dym`` (n, 6)."""
    n = pred.shape[0]
    dC = np.empty((6, 3))
    for k in range(3):
        for i in range(3):
            # C = -R^T t: by rvec through R, by t directly
            dC[k, i] = -(dR[k, 0, i] * t[0] + dR[k, 1, i] * t[1] + dR[k, 2, i] * t[2])
            dC[3 + k, i] = -R[k, i]
    dw = np.empty((6, 3))
    for i in range(n):
        acc = 0.0
        ax = 0.0
        ay = 0.0
        for j in range(6):
            dpred[i, j] = 0.0
            dxm[i, j] = 0.0
            dym[i, j] = 0.0
        for q in range(ns):
            x = nrm[i * ns + q, 0]
            y = nrm[i * ns + q, 1]
            w0 = x * R[0, 0] + y * R[1, 0] + R[2, 0]
            w1 = x * R[0, 1] + y * R[1, 1] + R[2, 1]
            w2 = x * R[0, 2] + y * R[1, 2] + R[2, 2]
            for k in range(3):
                for c in range(3):
                    dw[k, c] = x * dR[k, 0, c] + y * dR[k, 1, c] + dR[k, 2, c]
                    dw[3 + k, c] = 0.0
            s = -C[2] / w2
            X = C[0] + s * w0
            Y = C[1] + s * w1
            a = A[0, 0] * X + A[0, 1] * Y + A[0, 2]
            b = A[1, 0] * X + A[1, 1] * Y + A[1, 2]
            wh = A[2, 0] * X + A[2, 1] * Y + A[2, 2]
            u = a / wh
            v = b / wh
            ax += u
            ay += v
            val, gu, gv = _read(tex, u, v)
            acc += val
            for j in range(6):
                ds = -dC[j, 2] / w2 + C[2] * dw[j, 2] / (w2 * w2)
                dX = dC[j, 0] + ds * w0 + s * dw[j, 0]
                dY = dC[j, 1] + ds * w1 + s * dw[j, 1]
                dwh = A[2, 0] * dX + A[2, 1] * dY
                du = (A[0, 0] * dX + A[0, 1] * dY - u * dwh) / wh
                dv = (A[1, 0] * dX + A[1, 1] * dY - v * dwh) / wh
                dpred[i, j] += gu * du + gv * dv
                dxm[i, j] += du
                dym[i, j] += dv
        pred[i] = acc / ns
        xm[i] = ax / ns
        ym[i] = ay / ns
        for j in range(6):
            dpred[i, j] /= ns
            dxm[i, j] /= ns
            dym[i, j] /= ns


pattern_predict = njit(cache=True, nogil=True)(_pattern_predict) if njit is not None \
    else None
pattern_predict_grad = njit(cache=True, nogil=True)(_pattern_predict_grad) \
    if njit is not None else None
