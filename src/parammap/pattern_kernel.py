"""Compiled prediction of a marker's pattern as a photo shows it, for pose refinement
on the whole pattern (:class:`parammap.calibration.PatternView`).

Each pixel is ``s`` sub-pixel rays (undistorted, normalised); each ray meets the
surface plane z = 0 of a camera with rotation R and centre C, the plane point maps to
the pattern by a homography, and the blurred pattern is read there with bilinear
interpolation (edge values beyond it, as ``scipy.ndimage.map_coordinates`` with
``order=1, mode="nearest"``). The numpy chain of those steps spent most of a pose's
time in temporaries; this is one compiled loop. Where numba is missing
:func:`pattern_predict` is None and the numpy chain is used.
"""

from __future__ import annotations

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover - exercised only without numba
    njit = None


def _pattern_predict(R: np.ndarray, C: np.ndarray, nrm: np.ndarray, A: np.ndarray,
                     tex: np.ndarray, ns: int, pred: np.ndarray, xm: np.ndarray,
                     ym: np.ndarray) -> None:
    """Fill ``pred`` (n,) with each pixel's mean pattern value over its ``ns`` rays
    ``nrm`` (n ns, 2), and ``xm``, ``ym`` (n,) with its mean pattern coordinates
    (samples). R (3, 3), C (3,): the camera; A (3, 3): plane (mm) -> pattern."""
    H, W = tex.shape
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
            # bilinear at (row v - 0.5, column u - 0.5), edges extended
            r = min(max(v - 0.5, 0.0), H - 1.0)
            c = min(max(u - 0.5, 0.0), W - 1.0)
            r0 = min(int(r), H - 2) if H > 1 else 0
            c0 = min(int(c), W - 2) if W > 1 else 0
            fr = r - r0
            fc = c - c0
            r1 = min(r0 + 1, H - 1)
            c1 = min(c0 + 1, W - 1)
            acc += ((1 - fr) * ((1 - fc) * tex[r0, c0] + fc * tex[r0, c1])
                    + fr * ((1 - fc) * tex[r1, c0] + fc * tex[r1, c1]))
        pred[i] = acc / ns
        xm[i] = ax / ns
        ym[i] = ay / ns


pattern_predict = njit(cache=True, nogil=True)(_pattern_predict) if njit is not None \
    else None
