"""SH baked from a fitted MH map: each texel's MH model sampled over its sampled cap and
projected onto n bands in the values shown.

A texel's views sample the hemisphere at a few scattered directions, and an SH fit to
them alone either rings between the views (the projections of :mod:`.cap` guard
against it) or leaves a highlight out. The MH fit of the same views is a parametric
interpolant: between views it follows the lobe the views determine. Projecting that
function, densely sampled, onto the SH basis gives the SH map the MH fit implies; the
projection is weighted by the slope of the held-out comparison's tone map
(:func:`parammap.models.display.display_weights`, the secant between fit and target,
refitted until it settles) so that the bands go where the shown error is, not to a
highlight's peak radiance.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ...conventions import FitArray, FitStatus
from ..display import display_weights
from ..mh.model import mh_eval
from ..residuals import mean_percentage_residual
from . import sh_outputs
from .basis import sh_basis
from .cap import cap_radius, hemisphere_grid

__all__ = ["BAKE_GRID_DEG", "BAKE_ROUNDS", "bake_mh", "bake_outputs", "bake_tile", "baked_cap"]

BAKE_GRID_DEG = 4.0  # sampling step of the MH model: ~45 samples per period of band 9
BAKE_ROUNDS = 3  # secant reweightings (session 52: the shown error settles by then)
# damping of the coefficients above the constant, relative to the mean of the normal
# matrix's diagonal: over a cap, bands left free cancel each other in coefficients of
# hundreds (which a half-float EXR or the viewer's 8-bit planes cannot hold); the sphere
# energy of a texel's bands is what is damped, and a constant is never
BAKE_RIDGE = 1e-4
# weight of the directions outside the cap, relative to those inside: only enough to
# hold the bands there to the MH model's extrapolation (the cap alone leaves them free
# to take any value where nobody looked, which the viewer would show at grazing)
BAKE_OUTSIDE = 0.01


@lru_cache(maxsize=4)
def _grid_products(n: int) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The basis on the bake grid (G, n^2), the products of its pairs
    of functions (G, n^2 (n^2 + 1) / 2) and the upper triangle's indices they fill."""
    Y = sh_basis(hemisphere_grid(BAKE_GRID_DEG)[0], n)
    iu = np.triu_indices(n * n)
    YY = np.ascontiguousarray(Y[:, iu[0]] * Y[:, iu[1]])
    for a in (Y, YY, *iu):
        a.setflags(write=False)
    return Y, YY, iu


def baked_cap(directions: np.ndarray, valid: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """(B, G) mask of the grid directions (G, 3) inside each texel's sampled cap: within
    :func:`parammap.models.sh.cap.cap_radius` of one of its valid view directions
    (B, N, 3), as :class:`parammap.models.sh.cap.SampledCap` defines it."""
    B = len(directions)
    inside = np.zeros((B, len(grid)), bool)
    for b in range(B):
        v = directions[b][valid[b]]
        if len(v) == 0:
            continue
        v = v / np.linalg.norm(v, axis=1, keepdims=True)
        inside[b] = (grid @ v.T).max(1) >= math.cos(cap_radius(v))
    return inside


def bake_mh(params: np.ndarray, directions: np.ndarray, valid: np.ndarray, n: int,
            gamma: float, rounds: int = BAKE_ROUNDS) -> tuple[np.ndarray, np.ndarray]:
    """SH coefficients of MH models over their sampled caps, in the values shown.

    Parameters
    ----------
    params : (B, 4 + 6K) MH parameter vectors (docs/reference/conventions.md layout).
    directions : (B, N, 3) each texel's view directions (surface frame, unit).
    valid : (B, N) which of them the texel's fit saw.
    n : bands (n^2 coefficients per channel).
    gamma : the held-out comparison's tone-map gamma (1/radiance units,
        :meth:`parammap.stores.observation.ObservationMap.display_gamma`).
    rounds : secant reweightings after the first fit.

    Returns
    -------
    coeffs : (B, 3, n^2) per channel.
    shown_rmse : (B,) root-mean-square difference of the values shown (0-1) between
        the baked SH and the MH model over the cap, solid-angle weighted.

    Directions outside the cap are weighted :data:`BAKE_OUTSIDE` times theirs inside.
    """
    g, w = hemisphere_grid(BAKE_GRID_DEG)
    inside = baked_cap(directions, valid, g)
    B = len(params)
    target = np.maximum(mh_eval(np.asarray(params, float),
                                np.broadcast_to(g, (B,) + g.shape)), 0.0)  # (B, G, 3)
    Y, YY, iu = _grid_products(n)  # (G, n2), (G, n2 (n2 + 1) / 2), upper triangle
    area = w[None] * np.where(inside, 1.0, BAKE_OUTSIDE)  # (B, G)
    ridge = np.diag(np.r_[0.0, np.full(n * n - 1, BAKE_RIDGE / (n * n))])
    k = display_weights(target, gamma)
    for _ in range(rounds + 1):
        om = area * k
        om *= area.sum(1, keepdims=True) / np.maximum(om.sum(1, keepdims=True), 1e-300)
        A = np.empty((B, n * n, n * n))
        A[:, iu[0], iu[1]] = om @ YY  # one product for every texel's normal matrix
        A[:, iu[1], iu[0]] = A[:, iu[0], iu[1]]
        A += ridge * np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300)[:, None, None]
        rhs = np.matmul(Y.T, om[..., None] * target)  # (B, n2, 3)
        c = np.linalg.solve(A, rhs)  # (B, n2, 3)
        fitted = Y @ c  # (B, G, 3)
        k = display_weights(target, gamma, fitted)
    shown = np.exp(-gamma * np.maximum(fitted, 0)) - np.exp(-gamma * target)
    cap = w[None] * inside
    rmse = np.sqrt(np.einsum("bg,bgc->b", cap, shown ** 2)
                   / np.maximum(3 * cap.sum(1), 1e-300))
    return np.swapaxes(c, 1, 2), rmse


BAKE_BATCH = 64  # texels baked at once: (B, n^2, G) weighted bases of ~20 MB at n = 6


def bake_outputs(n: int) -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of a baked SH store: an SH fit's (:func:`parammap.models.sh.sh_outputs`)
    but the coefficients' sds (the bake has no uncertainty of its own; its source's
    is in the MH map)."""
    return {k: v for k, v in sh_outputs(n).items() if k != FitArray.SD}


def bake_tile(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray,
              params: np.ndarray, fitted: np.ndarray, n: int, gamma: float,
              batch: int = BAKE_BATCH) -> dict[str, np.ndarray]:
    """Bake every texel of a tile from its MH fit (:func:`bake_mh`). (t, u, N, 3)
    observations, ``params`` (t, u, 4 + 6K) the MH fit's and ``fitted`` (t, u) where it
    succeeded; outputs as :func:`bake_outputs` (``rmse`` and ``mpr`` against the
    observations)."""
    t, u, N, _ = radiance.shape
    out = {k: np.full((t, u) + shp, fill, dtype) for k, (shp, dtype, fill)
           in bake_outputs(n).items()}
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    L = radiance.reshape(t * u, N, 3).astype(float)
    V = direction.reshape(t * u, N, 3).astype(float)
    W = valid.reshape(t * u, N) & np.isfinite(L).all(-1) & np.isfinite(V).all(-1) \
        & (V[..., 2] > 0)
    P = params.reshape(t * u, -1).astype(float)
    ok = fitted.reshape(-1) & np.isfinite(P).all(1)
    flat[FitArray.STATUS][~ok] = FitStatus.FAILED
    flat[FitArray.STATUS][ok & (W.sum(1) == 0)] = FitStatus.TOO_FEW
    todo = np.flatnonzero(ok & (W.sum(1) > 0))
    for s0 in range(0, len(todo), batch):
        sel = todo[s0:s0 + batch]
        c, _ = bake_mh(P[sel], V[sel], W[sel], n, gamma)
        pred = np.matmul(sh_basis(V[sel], n), np.swapaxes(c, 1, 2))  # (B, N, 3)
        w = W[sel][..., None]
        r = np.where(w, pred - L[sel], 0.0)
        flat[FitArray.COEFFS][sel] = c.reshape(len(sel), -1)
        flat[FitArray.RMSE][sel] = np.sqrt((r ** 2).sum(1) / w.sum(1))
        flat[FitArray.MPR][sel] = mean_percentage_residual(np.where(w, L[sel], 0.0), pred,
                                                           W[sel])
        flat[FitArray.STATUS][sel] = np.where(np.isfinite(c).all((1, 2)), FitStatus.OK,
                                              FitStatus.FAILED)
    return out
