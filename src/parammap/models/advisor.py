"""Capture advisor: the camera directions that would pin down a fit's poorly determined
texels most (004 ch. 16-18: highlights that fell between views were found only after
the capture, when it was too late to shoot again).

For a texel with MH parameters x (the fitters' space: Kd, ln m, per lobe Ks and two
angles), the views it has give the information matrix ``A = J^T W J`` (J the Jacobian
of its predicted radiance, W the observation weights, mean 1): its parameters'
covariance is ``sigma^2 A^-1``. A new view in direction v adds the three rows ``J_v``
(its RGB radiance) and shrinks that uncertainty's volume by ``log det(I + J_v A^-1
J_v^T)`` (D-optimal design; sigma cancels, since the new view is as noisy as the
others). The candidate with the largest gain summed over (a sample of) the texels is
advised first; every texel's A is then updated with it (rank-three update), so the next
advice adds what the first does not already give, and so on (greedy D-optimal design,
within a factor 1 - 1/e of the best set). A lobe whose highlight fell between the views
has a poorly determined shininess and direction, and the views that see its peak gain
most; a texel without a lobe gains little anywhere. Pure numerics.
"""

from __future__ import annotations

import numpy as np

from ..config import default
from .mh.model import mh_eval
from .mh.uncertainty import _linearised

__all__ = ["CRITERIA", "advise_directions", "hemisphere_candidates", "prediction_gains",
           "view_gains"]


def hemisphere_candidates(count: int = 400, max_zenith_deg: float = 80.0) -> np.ndarray:
    """(count, 3) directions spread evenly in solid angle over the upper hemisphere to
    ``max_zenith_deg`` (a Fibonacci spiral)."""
    i = np.arange(count) + 0.5
    z = 1 - i / count * (1 - np.cos(np.radians(max_zenith_deg)))
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _information(P, V, L, W, weights):
    """Information matrices A (n, nx, nx) of texels from their own views, and which of
    their parameters are free (n, nx)."""
    _, _, _, _, free, A, _ = _linearised(P, V, L, W, weights)
    # a small ridge: a parameter no view determines has huge, not infinite, variance
    scale = np.maximum(np.trace(A, axis1=1, axis2=2) / A.shape[1], 1e-12)
    return A + 1e-6 * scale[:, None, None] * np.eye(A.shape[1]), free


def _candidate_rows(P: np.ndarray, cand: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Jacobian rows (n, M, 3, nx) of every texel's radiance in every candidate
    direction (M, 3), restricted to its free parameters."""
    n, M = len(P), len(cand)
    Vc = np.broadcast_to(cand, (n, M, 3))
    J, *_ = _linearised(P, Vc, np.zeros((n, M, 3)), np.ones((n, M), bool), None)
    J = J.reshape(n, M, 3, -1)
    return np.where(free[:, None, None, :], J, 0.0)


def view_gains(A: np.ndarray, Jc: np.ndarray) -> np.ndarray:
    """(n, M) ``log det(I + J_v A^-1 J_v^T)`` of every texel and candidate."""
    Ai = np.linalg.inv(A)
    S = np.einsum("nmik,nkl,nmjl->nmij", Jc, Ai, Jc, optimize=True)
    sign, logdet = np.linalg.slogdet(np.eye(3) + S)
    return np.where(sign > 0, logdet, 0.0)


def prediction_gains(A: np.ndarray, Jc: np.ndarray, Mu: np.ndarray) -> np.ndarray:
    """(n, M) how much a view in each candidate direction would lower each texel's
    summed prediction variance ``tr(M_U A^-1)`` (in units of the noise variance):
    ``tr((I + J_v A^-1 J_v^T)^-1 J_v A^-1 M_U A^-1 J_v^T)`` (Woodbury), ``Mu`` (n, nx,
    nx) the texel's ``sum_u J_u^T J_u`` over the directions its renders are judged in."""
    Ai = np.linalg.inv(A)
    G = np.matmul(np.matmul(Ai, Mu), Ai)
    S = np.einsum("nmik,nkl,nmjl->nmij", Jc, Ai, Jc, optimize=True)
    T = np.einsum("nmik,nkl,nmjl->nmij", Jc, G, Jc, optimize=True)
    g = np.trace(np.linalg.solve(np.eye(3) + S, T), axis1=2, axis2=3)
    return np.where(np.isfinite(g), np.maximum(g, 0.0), 0.0)


CRITERIA = ("prediction", "volume")


def advise_directions(P: np.ndarray, V: np.ndarray, L: np.ndarray, W: np.ndarray,
                      weights: np.ndarray | None, cand: np.ndarray,
                      count: int = default("advisor.count"),
                      criterion: str = default("advisor.criterion"),
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedy choice of ``count`` new view directions among ``cand``: I-optimal
    (``prediction``: the largest drop of the variance of the renders over the
    hemisphere, each texel relative to its own brightness) or D-optimal (``volume``:
    the parameters' uncertainty volume, module docstring).

    Parameters
    ----------
    P : (n, 4 + 6K) fitted MH parameters of (a sample of) the texels.
    V, L : (n, N, 3) their observed directions and radiance; W : (n, N) valid;
    weights : (n, N) the fit's observation weights (None: equal).
    cand : (M, 3) candidate view directions (unit, surface frame).

    Returns
    -------
    order : (count,) indices into ``cand``, best first; gain : (count,) the summed
    log-det gain of each when chosen; first : (M,) every candidate's gain before any
    choice (the map a figure draws).
    """
    if criterion not in CRITERIA:
        raise ValueError(f"unknown advisor criterion {criterion!r} (one of {CRITERIA})")
    P = np.asarray(P, float)
    A, free = _information(P, V, L, W, weights)
    Jc = _candidate_rows(P, np.asarray(cand, float), free)
    if criterion == "prediction":
        # renders judged over the candidates themselves (spread evenly in solid angle),
        # each texel's variance relative to its mean radiance there: a display error
        # is about relative (a tone curve), and a bright texel must not rule alone

        level = np.maximum(np.mean(mh_eval(P, np.broadcast_to(cand, (len(P),) + cand.shape)),
                                   (1, 2)), 1e-12)
        Mu = np.einsum("nmik,nmil->nkl", Jc, Jc) / level[:, None, None] ** 2
    order, gain, first = [], [], None
    for _ in range(min(count, len(cand))):
        g = (prediction_gains(A, Jc, Mu) if criterion == "prediction"
             else view_gains(A, Jc)).sum(0)
        if first is None:
            first = g.copy()
        g[order] = -np.inf
        best = int(np.argmax(g))
        order.append(best)
        gain.append(float(g[best]))
        A = A + np.einsum("nik,nil->nkl", Jc[:, best], Jc[:, best])
    return np.array(order, int), np.array(gain), first
