"""Spherical harmonics (SH) model: basis, hemisphere solid angles and projections.

Basis (docs/reference/conventions.md, 004 eqs. 12.1-12.5): real, orthonormal over the full sphere,
index ``i = l (l + 1) + m``, ``n`` bands give ``n^2`` coefficients per channel::

    y_l^m = sqrt(2) K_l^m cos(m phi) P_l^m(cos theta)      m > 0
    y_l^m = sqrt(2) K_l^m sin(-m phi) P_l^-m(cos theta)    m < 0
    y_l^0 = K_l^0 P_l^0(cos theta)

with the Condon-Shortley phase inside ``P_m^m`` (004 eq. 12.1 rule 2). theta is the
zenith and phi the azimuth of a direction in the surface frame.

The samples cover only the upper hemisphere; ``hemisphere`` selects how (004 ch. 12.3):

- ``zh`` (zero hemisphere): project with the lower hemisphere taken as zero;
- ``mirror``: the samples reflected below the equator (the function is even in z);
- ``lsop``: least-squares optimal projection, ``A c = b`` with A the Gram matrix of the
  basis over the upper hemisphere (004 eq. 12.14);
- ``rlsop``: regularised LSOP, ``(A + lambda D) c = b`` with ``D = diag((l (l + 1))^2)``:
  Tikhonov damping of the surface Laplacian of the reconstruction over the whole sphere.
  The unsampled lower hemisphere is what leaves plain LSOP free to oscillate (the
  ringing 004 saw at 64+ coefficients, its ch. 18 suggests filtering); penalising
  roughness removes that freedom, most for the highest bands, while barely touching
  the low bands that carry the data;
- ``wls``: weighted least squares directly on the samples (solid angles as weights).

Every projection integrates with per-sample solid angles: the spherical Voronoi cells of
the texel's valid directions, mirrored below the equator so that the cells of the
upper points tile exactly the upper hemisphere (any upper direction is nearer to an
upper sample than to that sample's mirror image, so no cell crosses the equator and
cells of samples near the equator end exactly on it: the "half cells").
"""

from __future__ import annotations

import math

import numpy as np

from ...config import default
from ...conventions import (
    SH_CAP_AWARE,
    SH_HEMISPHERES,
    FitArray,
    FitStatus,
)
from ...errors import InputError
from ..display import display_weights
from ..residuals import mean_percentage_residual
from ..weights import noise_weights, reduced_chi2
from .basis import hemisphere_gram, planar_solid_angles, project, sh_basis, sh_eval, solid_angles
from .cap import (
    GUARD_STEPS,
    ROBUST_ROUNDS,
    SampledCap,
    batch_cap,
    coefficient_sd,
    guarded_project,
    hemisphere_grid,
    pad_bands,
    project_cap,
    robust_weights,
    shrink_to_mean,
    smoother,
    smoother_loo,
    stack_smoothers,
)

__all__ = ["GUARD_STEPS", "SampledCap", "coefficient_sd", "fit_sh_tile", "guarded_project",
           "hemisphere_gram", "hemisphere_grid", "parse_sh_model", "planar_solid_angles",
           "project", "project_cap", "sh_basis", "sh_eval", "sh_outputs", "shrink_to_mean",
           "smoother",
           "smoother_loo", "solid_angles"]


# ---------------------------------------------------------------------------------
# Tiles and maps


def sh_outputs(n: int) -> dict[str, tuple[tuple[int, ...], str, float]]:
    """Arrays of an SH fit store: name -> (trailing shape, dtype, fill value)."""
    return {
        FitArray.COEFFS: ((3 * n * n,), "float32", float("nan")),
        FitArray.SD: ((3 * n * n,), "float32", float("nan")),
        FitArray.RMSE: ((3,), "float32", float("nan")),
        FitArray.MPR: ((3,), "float32", float("nan")),
        FitArray.CHI2: ((), "float32", float("nan")),
        FitArray.REG: ((), "float32", float("nan")),
        FitArray.GUARD: ((), "int8", 0),
        FitArray.BANDS: ((), "int8", n),
        FitArray.ROBUST: ((), "float32", float("nan")),
        FitArray.SHRINK: ((), "float32", float("nan")),
        FitArray.STATUS: ((), "int8", int(FitStatus.NOT_FITTED)),
    }


def fit_sh_tile(radiance: np.ndarray, direction: np.ndarray, valid: np.ndarray, n: int,
                hemisphere: str, reg: float | str = "auto", batch: int = 256,
                min_obs: int | None = None, sampled_cap: bool = default("fit.sh.sampled_cap"),
                noise: np.ndarray | None = None, areas: str = "spherical",
                loo: bool = False, shrink: bool = default("fit.sh.shrink"),
                robust: bool = default("fit.sh.robust"),
                display_gamma: float | None = None) -> dict[str, np.ndarray]:
    """Project every texel of a tile, batched (texels sharing one validity pattern
    share one triangulation and one :class:`SampledCap`). (t, u, N, 3) inputs; outputs
    as :func:`sh_outputs`. ``sampled_cap`` (default) fits lsop, rlsop and wls with
    :func:`project_cap` and its guard; ``False`` gives the published projections of
    :func:`project` (Voronoi cells out to the equator, fixed ``reg``). ``noise`` (t, u,
    N) relative sd per observation: cell weights are multiplied by the noise weights
    of :func:`parammap.models.weights.noise_weights`, and ``chi2`` is reported.
    ``areas``: ``spherical`` Voronoi cells (default) or 004's ``planar`` cells divided
    by cos(theta) (:func:`planar_solid_angles`), for reproducing its artefacts.
    ``loo``: also ``loo`` (t, u, N, 3), each valid view's leave-one-out residual
    (prediction minus observation, :func:`smoother_loo`; inf where the view alone
    determines the fit), for the projections on the sampled cap (NaN otherwise).
    On the sampled cap, ``robust`` (default) stacks each texel's fit with a robust
    refit (:func:`robust_weights`, ``ROBUST_ROUNDS`` rounds; the robust share in
    ``robust``) and ``shrink`` (default) then blends the result with its DC term
    (:func:`shrink_to_mean`; the share kept in ``shrink``), both by leave-one-view-out
    error; coefficients, ``sd`` and ``loo`` are the final blend's. ``display_gamma``
    (on the sampled cap): the fit minimises the error of the values shown with that
    tone map's gamma instead of the radiance's, each view's weight multiplied by
    :func:`parammap.models.display.display_weights` and refitted ``DISPLAY_ROUNDS``
    times."""
    t, u, N, _ = radiance.shape
    outputs = sh_outputs(n) | ({FitArray.LOO: ((N, 3), "float64", float("nan"))} if loo else {})
    out = {k: np.full((t, u) + shp, fill, dtype) for k, (shp, dtype, fill) in
           outputs.items()}
    flat = {k: v.reshape((t * u,) + v.shape[2:]) for k, v in out.items()}
    L = radiance.reshape(t * u, N, 3).astype(float)
    V = direction.reshape(t * u, N, 3).astype(float)
    W = valid.reshape(t * u, N) & np.isfinite(L).all(-1) & np.isfinite(V).all(-1) \
        & (V[..., 2] > 0)
    NW = noise_weights(None if noise is None else noise.reshape(t * u, N), W)
    NZ = None if noise is None else noise.reshape(t * u, N)
    min_obs = min_obs or 4
    nobs = W.sum(1)
    flat[FitArray.STATUS][nobs < min_obs] = FitStatus.TOO_FEW
    todo = np.flatnonzero(nobs >= min_obs)
    # group texels by validity pattern: one triangulation per pattern and batch
    keys = {}
    for b in todo:
        keys.setdefault(W[b].tobytes(), []).append(b)
    for idx in keys.values():
        idx = np.array(idx)
        w = W[idx[0]]
        for s0 in range(0, len(idx), batch):
            sel = idx[s0:s0 + batch]
            v, y = V[sel][:, w], L[sel][:, w]
            try:
                omega = (planar_solid_angles(v) if areas == "planar" else solid_angles(v)) \
                    * NW[sel][:, w]
                Y = sh_basis(v, n)
                if sampled_cap and hemisphere in SH_CAP_AWARE:
                    cap = batch_cap(v, n)[1]  # one per batch: the robust refits share it
                    if display_gamma is not None:
                        omega = _display_omega(y, v, omega, n, hemisphere, reg, Y, cap,
                                               display_gamma)
                    c, lam, esc, bands, M, om = guarded_project(y, v, omega, n, hemisphere,
                                                                reg, Y, system=True, cap=cap)
                    flat[FitArray.REG][sel], flat[FitArray.GUARD][sel] = lam, esc
                    flat[FitArray.BANDS][sel] = bands
                    sigma = None if NZ is None else NZ[sel][:, w][..., None] * np.abs(y)
                    Yk = Y[..., : bands * bands]
                    Sm = smoother(M, Yk, om)
                    e = None
                    if robust:
                        Sr = Sm
                        for _ in range(ROBUST_ROUNDS):
                            u = robust_weights(y, Yk @ (Sr @ y))
                            *_, Mr, omr = guarded_project(y, v, omega * u, n, hemisphere,
                                                          reg, Y, system=True, cap=cap)
                            Sr = smoother(Mr, Yk, omr)
                        Sm, a, e = stack_smoothers(y, Yk, Sm, Sr, om)
                        flat[FitArray.ROBUST][sel] = 1 - a
                        c = pad_bands(np.swapaxes(Sm @ y, 1, 2), n)
                    if shrink:
                        Sm, flat[FitArray.SHRINK][sel], e = shrink_to_mean(y, Yk, Sm, om)
                        c = pad_bands(np.swapaxes(Sm @ y, 1, 2), n)
                    r = y - np.matmul(Y, c.transpose(0, 2, 1))
                    sd = coefficient_sd(Sm, Yk, r, n, sigma)
                    flat[FitArray.SD][sel] = sd.reshape(len(sel), -1)
                    if loo:  # prediction - observation
                        flat[FitArray.LOO][sel[:, None], np.flatnonzero(w)[None]] = \
                            e if e is not None else smoother_loo(Sm, Yk, -r)
                else:
                    c = project(y, v, omega, n, hemisphere,
                                1e-4 if reg == "auto" else float(reg), basis=Y)
            except Exception:  # noqa: BLE001 - a failed batch is flagged, never fatal
                flat[FitArray.STATUS][sel] = FitStatus.FAILED
                continue
            fitted = np.matmul(Y, c.transpose(0, 2, 1))
            flat[FitArray.COEFFS][sel] = c.reshape(len(sel), -1)
            flat[FitArray.RMSE][sel] = np.sqrt(np.mean((fitted - y) ** 2, axis=1))
            flat[FitArray.MPR][sel] = mean_percentage_residual(y, fitted)
            if NZ is not None:
                flat[FitArray.CHI2][sel] = reduced_chi2(y, fitted, NZ[sel][:, w],
                                                 np.ones(y.shape[:2], bool), 3 * n * n)
            flat[FitArray.STATUS][sel] = np.where(np.isfinite(c).all((1, 2)), FitStatus.OK,
                                           FitStatus.FAILED)
    return out


DISPLAY_ROUNDS = 3  # reweightings of a display-weighted fit (it moves < 0.1 % after)


def _display_omega(y, v, omega, n, hemisphere, reg, Y, cap, gamma):
    """(B, N) the cell weights ``omega`` times the display weights of the fit they give,
    reweighted ``DISPLAY_ROUNDS`` times from the tone map's slope at the observations;
    each texel's total weight kept, so that the prior and lambda keep their strength."""
    def scaled(k):
        w = omega * k
        return w * (omega.sum(1, keepdims=True) / np.maximum(w.sum(1, keepdims=True), 1e-300))

    w = scaled(display_weights(y, gamma))
    for _ in range(DISPLAY_ROUNDS):
        c = guarded_project(y, v, w, n, hemisphere, reg, Y, system=True, cap=cap)[0]
        w = scaled(display_weights(y, gamma, np.matmul(Y, c.transpose(0, 2, 1))))
    return w


def parse_sh_model(name: str) -> tuple[str, int]:
    """``sh-<hemisphere>-<coefficients>`` -> (hemisphere, bands)."""
    parts = name.split("-")
    if len(parts) != 3 or parts[0] != "sh" or parts[1] not in SH_HEMISPHERES:
        raise InputError(f"SH model name must be sh-<{'|'.join(SH_HEMISPHERES)}>-<n^2> "
                         f"(got {name!r})")
    try:
        nc = int(parts[2])
    except ValueError:
        nc = -1
    n = int(round(math.sqrt(max(nc, 0))))
    if nc < 1 or n * n != nc:
        raise InputError(f"{name}: the coefficient count must be a square (1, 4, 9, 16...)")
    return parts[1], n


