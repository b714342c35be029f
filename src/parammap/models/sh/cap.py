"""SH fits restricted to the sampled cap of the hemisphere: the cap's grid, the prior
that fills its holes, the bands its views resolve, the range guard, leave-one-out
errors and the coefficients' standard deviations."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ...conventions import (
    sh_degree_order,
)
from ...errors import InputError
from .basis import sh_basis

LOW_BANDS = 1  # band 0: the prior fills unsampled directions with the texel's mean level


GRID_STEP_DEG = 2.0  # midpoint quadrature step of the hemisphere grid


@lru_cache(maxsize=4)
def hemisphere_grid(step_deg: float = GRID_STEP_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint quadrature of the upper hemisphere: (G, 3) directions and (G,) solid
    angles (sum 2 pi), uniform in zenith and azimuth so that the pole is resolved as
    finely as the equator."""
    nt = int(round(90 / step_deg))
    npk = int(round(360 / step_deg))
    th = (np.arange(nt) + 0.5) * (np.pi / 2 / nt)
    ph = (np.arange(npk) + 0.5) * (2 * np.pi / npk)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1)
    w = np.sin(TH) * (np.pi / 2 / nt) * (2 * np.pi / npk)
    w *= 2 * np.pi / w.sum()
    d, w = d.reshape(-1, 3), w.ravel()
    d.setflags(write=False)
    w.setflags(write=False)
    return d, w


@lru_cache(maxsize=8)
def _grid_basis(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The basis at :func:`hemisphere_grid`'s directions (G, n^2) and the mask (n^2,)
    of the bands above :data:`LOW_BANDS`, computed once per n (every validity pattern
    of a map needs them)."""
    Yg = sh_basis(hemisphere_grid()[0], n)
    l_, _ = sh_degree_order(n)
    high = l_ >= LOW_BANDS
    Yg.setflags(write=False)
    high.setflags(write=False)
    return Yg, high


def cap_radius(directions: np.ndarray, expected_views: float = 3.0) -> float:
    """Radius (radians) of a hole among view directions (N, 3) that counts as
    unsampled: the disc that would hold ``expected_views`` views at the capture's mean
    density over the zenith range it covers (a Poisson count of 3 is absent by chance
    in 5 % of such discs, so only real gaps and the region beyond the last views
    qualify; the median nearest-neighbour spacing, tried first, flagged most of the
    hemisphere of an irregular capture)."""
    d = np.asarray(directions, float)
    covered = 2 * np.pi * (1 - np.clip(d[:, 2], 0, 1).min())
    return float(np.sqrt(expected_views * covered / (np.pi * len(d))))


class SampledCap:
    """The part of the upper hemisphere a texel's views cover, for one batch of texels
    sharing a reference set of directions.

    A grid direction is *sampled* when a view direction lies within ``rho`` of it
    (:func:`cap_radius`); farther from every view, nothing was looked at. Attributes:

    - ``rho`` : radius (radians); ``bands`` : n;
    - ``fraction`` : (N,) part of each sample's Voronoi cell inside the cap, so that
      cells next to an unsampled region stay bounded (a sample at 72 deg no longer
      stands for the whole ring out to the equator);
    - ``prior`` : (n^2, n^2) ``int_U h_i h_j`` over the unsampled directions U, with h
      the basis above the low bands (band 0 zeroed): its quadratic form is the energy
      of a reconstruction's variation where no view looked, which the projections
      below penalise so that U is filled by the texel's mean level, not by an
      extrapolated lobe (a linear band-1 extrapolation, tried too, overshoots at
      grazing angles);
    - ``basis_u``, ``zenith_u`` : (|U|, n^2) basis values at the unsampled grid
      directions and their zenith angles (the guard).
    """

    def __init__(self, reference: np.ndarray, n: int, rho: float | None = None):
        ref = np.asarray(reference, float)
        ref = ref / np.linalg.norm(ref, axis=-1, keepdims=True)
        self.rho = cap_radius(ref) if rho is None else float(rho)
        self.bands = int(n)
        g, w = hemisphere_grid()
        c = g @ ref.T  # (G, N)
        near = c.argmax(1)
        inside = c[np.arange(len(g)), near] >= math.cos(self.rho)
        N = len(ref)
        cell = np.bincount(near, w, minlength=N)
        kept = np.bincount(near[inside], w[inside], minlength=N)
        self.fraction = np.where(cell > 0, kept / np.maximum(cell, 1e-300), 1.0)
        Yg, high = _grid_basis(n)
        H = Yg[~inside] * high
        self.prior = (H * w[~inside, None]).T @ H
        self.basis_u = Yg[~inside]
        self.zenith_u = np.arccos(g[~inside, 2])
        self.unsampled_sr = float(w[~inside].sum())


def roughness(n: int) -> np.ndarray:
    """(n^2, n^2) diagonal ``(l (l + 1))^2 / (L (L + 1))^2``: the squared surface
    Laplacian of a reconstruction over the sphere, scaled so that the top band is 1."""
    l_, _ = sh_degree_order(n)
    top = max((n - 1) * n, 1)
    return np.diag((l_ * (l_ + 1.0) / top) ** 2)


def _loo_scores(Y, y, omega, Ms, rhs):
    """Coefficients (G, B, n2, 3) and weighted leave-one-out errors (G, B) of the
    linear projections ``c = M^-1 Y^T diag(omega) y`` for G matrices Ms (G, B, n2, n2)
    of the same views (exact for linear smoothers: r_i / (1 - H_ii)); one solve for
    the coefficients and the hat matrix of every M (small systems: the calls cost more
    than the arithmetic)."""
    X = np.linalg.solve(Ms, np.concatenate([rhs, np.swapaxes(Y, 1, 2)], -1)[None])
    c, Z = X[..., :3], X[..., 3:]  # (G, B, n2, 3), (G, B, n2, N)
    h = omega * np.einsum("bik,gbki->gbi", Y, Z)
    r = (y - Y @ c) / np.maximum(1 - h, 1e-3)[..., None]
    return c, np.sum(omega[..., None] * r * r, axis=(2, 3))


def project_cap(
    radiance: np.ndarray, directions: np.ndarray, weights: np.ndarray, n: int,
    hemisphere: str, cap: SampledCap, reg: float | str | np.ndarray = "auto",
    basis: np.ndarray | None = None, prior_scale: np.ndarray | None = None,
    system: bool = False,
) -> tuple[np.ndarray, ...]:
    """Projections that know which directions were observed (lsop, rlsop, wls).

    Least squares over the sampled cap, ``(A + P + lambda D) c = b``, with b
    ``sum_i w_i f_i y(d_i)`` (cell weights cut at the cap), P the prior of
    :class:`SampledCap` (variation held to zero where no view looked) and D
    :func:`roughness`:

    - ``lsop`` and ``wls``: A the Gram matrix of the samples, ``sum_i w_i y(d_i)
      y(d_i)^T``, lambda 0. On the cap, LSOP's exact Gram matrix (004 eq. 12.14) is
      replaced by this one, consistent with b: with the exact one, b is only a
      quadrature of the data and renders of sharp highlights suffered (measured on the
      physically based capture: LSOP-16 lost to a diffuse texture on one held-out view).
      The two names differ only with ``sampled_cap: false``;
    - ``rlsop``: as ``lsop`` with lambda ``reg`` (relative to the mean diagonal of
      ``A + P``; a number, or (B,) per texel) or, with ``auto``, per texel the value
      of a grid (0 included) with the least leave-one-out error (exact for least
      squares), so the regularised fit is never worse than the plain one on the
      texel's own cross-validation. (Pooling the choice over a batch, tried first,
      let the many matte texels of a batch smooth away a conductor's highlight.)

    Parameters
    ----------
    radiance, directions : (B, N, 3); weights : (B, N) Voronoi solid angles;
    cap : the batch's :class:`SampledCap`; basis : ``sh_basis(directions, n)``.
    prior_scale : (B,) factor on the prior per texel (the guard's escalation).

    system : also return the (B, n^2, n^2) matrix M of the normal equations solved,
        ``c = M^-1 Y^T diag(omega) y`` (for the coefficients' covariance).

    Returns
    -------
    (B, 3, n^2) coefficients and (B,) the relative lambda used (and M).
    """
    Y = sh_basis(directions, n) if basis is None else basis
    omega = weights * cap.fraction
    rhs = np.swapaxes(Y, 1, 2) @ (omega[..., None] * radiance)  # (B, n2, 3)
    A = np.swapaxes(Y, 1, 2) @ (omega[..., None] * Y)
    ps = np.ones(len(Y)) if prior_scale is None else np.asarray(prior_scale, float)
    A = A + ps[:, None, None] * cap.prior
    scale = np.trace(A, axis1=1, axis2=2)[:, None, None] / (n * n)
    A = A + 1e-9 * scale * np.eye(n * n)
    D = roughness(n)
    B = len(Y)
    if hemisphere != "rlsop" or not isinstance(reg, str):
        lam = np.broadcast_to(np.asarray(0.0 if hemisphere != "rlsop" else reg, float),
                              (B,)).copy()
        M = A + (lam[:, None, None] * scale) * D
        c = np.linalg.solve(M, rhs)
        return (np.swapaxes(c, 1, 2), lam) + ((M,) if system else ())
    if reg != "auto":
        raise InputError(f"regularisation must be a number or 'auto' (got {reg!r})")
    grid = np.asarray(REG_GRID)
    c, score = _loo_scores(Y, radiance, omega,
                           A[None] + grid[:, None, None, None] * scale[None] * D, rhs)
    pick = np.nan_to_num(score, nan=np.inf).argmin(0)  # the least; ties: the weakest
    lam = grid[pick]
    best_c = c[pick, np.arange(B)]
    out = (np.swapaxes(best_c, 1, 2), lam)
    return out + ((A + (lam[:, None, None] * scale) * D,) if system else ())


def resolvable_bands(directions: np.ndarray, n: int) -> int:
    """The most bands (at most ``n``, at least 2 where ``n`` allows) that view directions
    (N, 3) resolve.

    With ``N`` views over the solid angle ``Omega`` their zenith range covers, the
    mean spacing is ``Delta = sqrt(Omega / N)``; degree ``L`` varies over half a
    wavelength ``pi / L``, and irregular sampling (spirals, jitter, holes) needs about
    two samples there, so ``L <= pi / (2 Delta)``. Beyond it, a fit is free between the
    views: with 30 views to 75 degrees, 36 coefficients dimmed a conductor's
    highlight seen from between two views to a third of its radiance; the 25 this rule
    gives followed it (held-out error 12.5 against 34 and a diffuse texture's 19).
    """
    d = np.asarray(directions, float)
    covered = 2 * np.pi * (1 - np.clip(d[:, 2], 0, 1).min())
    delta = math.sqrt(covered / len(d))
    return int(min(n, max(2, math.floor(math.pi / (2 * delta)) + 1)))


REG_GRID = (0.0,) + tuple(10.0 ** k for k in range(-5, 1))  # rlsop's lambdas (relative)


PRIOR_FLOOR = 1e-3  # weakest prior (relative), also the pilot fit's


def prior_strength(radiance: np.ndarray, Y: np.ndarray, omega: np.ndarray,
                   pilot: np.ndarray) -> np.ndarray:
    """(B,) weight of the unsampled-region prior per texel: the pilot fit's residual
    variance over the variance of the texel's observations (both weighted by solid
    angle), i.e. ``sigma^2 / tau^2`` of a Gaussian prior whose spread in the holes is
    the spread the texel shows where it was seen, against data whose noise is what the
    model could not explain. Texels whose own data are good get a weak prior (their fit
    is not biased); noisy ones lean on it. Clipped to [``PRIOR_FLOOR``, 1]."""
    w = omega[..., None] / omega.sum(1)[:, None, None]
    fit = Y @ np.swapaxes(pilot, 1, 2)
    res = (w * (radiance - fit) ** 2).sum((1, 2))
    mean = (w * radiance).sum(1, keepdims=True)
    spread = (w * (radiance - mean) ** 2).sum((1, 2))
    return np.clip(res / np.maximum(spread, 1e-30), PRIOR_FLOOR, 1.0)


GUARD_STEPS = 4  # decades the guard escalates (the prior, or rlsop's lambda)


GUARD_TOLERANCE = 0.1  # of the texel's observed range


def guarded_project(
    radiance: np.ndarray, directions: np.ndarray, weights: np.ndarray, n: int,
    hemisphere: str, reg: float | str = "auto", basis: np.ndarray | None = None,
    system: bool = False, cap: SampledCap | None = None,
) -> tuple:
    """:func:`project_cap` with the batch's :class:`SampledCap`, and a guard: a texel
    whose reconstruction at any unsampled direction leaves the range of its own
    observations (widened by ``GUARD_TOLERANCE`` of that range; checked up to one view
    spacing beyond the largest zenith observed) is refitted with the
    prior ten times stronger, up to ``GUARD_STEPS`` times, so that directions no view
    looked at are filled by the low bands rather than by an extrapolated lobe.

    ``rlsop`` has a second remedy: smoother bands, lambda stronger by sqrt(10) per
    escalation (from at least :data:`SMOOTHING_GUARD_START`, up to
    :func:`guard_steps`), until the reconstruction stays in that range wherever renders
    may look, between the views as well as where none looked (every direction of
    :func:`hemisphere_grid` up to the same reach). Of the two, each texel keeps the one
    whose exact leave-one-view-out error is less: a stronger prior where no view looked
    also drags a lobe near the edge of the cap, and leave-one-out judges the lambda it
    chose only at the views, where a lobe's ringing between them does not show.

    Only the bands the views resolve are fitted (:func:`resolvable_bands`); the
    coefficients above them are zero.

    Returns
    -------
    (B, 3, n^2) coefficients, (B,) the relative lambda, (B,) int8 escalations per texel
    (:func:`guard_steps` + 1: still outside after the last one), and the bands fitted; with
    ``system``, also the final normal-equation matrices (B, k^2, k^2) of the k fitted
    bands (:func:`project_cap`) and the (B, N) observation weights they were built
    with (``weights`` times the cap's cell fractions): together the linear smoother
    ``c = M^-1 Y^T diag(omega) y`` of :func:`smoother`.

    cap : the batch's :class:`SampledCap` (:func:`batch_cap`), when the caller holds it
        already (refits of the same views with other weights).
    """
    full = n
    n, cap = batch_cap(directions, n) if cap is None else (cap.bands, cap)
    Y = sh_basis(directions, n) if basis is None else basis[..., : n * n]
    mu = prior_strength(radiance, Y, weights * cap.fraction,
                        project_cap(radiance, directions, weights, n, hemisphere, cap, 0.0,
                                    Y, prior_scale=np.full(len(Y), PRIOR_FLOOR))[0])
    c, lam, M = project_cap(radiance, directions, weights, n, hemisphere, cap, reg, Y,
                            prior_scale=mu, system=True)
    # renders look from within the zenith range the views covered, not beyond it
    reach = np.arccos(np.clip(directions[..., 2].min(), -1, 1)) + cap.rho
    omega = weights * cap.fraction
    lo, hi = radiance.min(1), radiance.max(1)  # (B, 3)
    tol = GUARD_TOLERANCE * (hi - lo) + 1e-12
    flag = guard_steps(hemisphere) + 1

    def refit(sel, lam_, prior):
        return project_cap(radiance[sel], directions[sel], weights[sel], n, hemisphere,
                           cap, lam_, Y[sel], prior_scale=prior, system=True)

    # where no view looked: the prior ten times stronger per escalation
    guard = _RangeGuard(c, M, lam, lo - tol, hi + tol)
    guard.run(cap.basis_u[cap.zenith_u <= reach], GUARD_STEPS, flag,
              lambda sel, esc: refit(sel, lam[sel], mu[sel] * 10.0 ** esc))
    if hemisphere != "rlsop":
        return (pad_bands(guard.c, full), lam, guard.esc, n) + \
            ((guard.M, omega) if system else ())
    # rlsop: or smoother bands, held to the range between the views too (leave-one-out
    # judges a fit only at the views: its lambda may ring there); per texel, the remedy
    # whose leave-one-out error is less
    g, _ = hemisphere_grid()
    smooth = _RangeGuard(c, M, lam, lo - tol, hi + tol)

    def stronger(sel, esc):
        smooth.lam[sel] = np.maximum(10.0 ** (1 / LAMBDA_STEPS_PER_DECADE)
                                     * smooth.lam[sel], SMOOTHING_GUARD_START)
        return refit(sel, smooth.lam[sel], mu[sel])

    smooth.run(_grid_basis(n)[0][np.arccos(g[:, 2]) <= reach], guard_steps(hemisphere),
               flag, stronger)
    acted = np.flatnonzero((guard.esc > 0) | (smooth.esc > 0))
    if len(acted):
        w = omega[acted] / omega[acted].sum(1, keepdims=True)
        err = [np.einsum("bn,bnc->b", w, _loo(smoother(r.M[acted], Y[acted], omega[acted]),
                                              Y[acted], radiance[acted]) ** 2)
               for r in (guard, smooth)]
        take = acted[err[1] < err[0]]
        for name in ("c", "M", "lam", "esc"):
            getattr(guard, name)[take] = getattr(smooth, name)[take]
    return (pad_bands(guard.c, full), guard.lam, guard.esc, n) + \
        ((guard.M, omega) if system else ())


class _RangeGuard:
    """A fit's coefficients (B, 3, k^2), normal-equation matrices and lambdas, refitted
    by :meth:`run` until their reconstructions stay within (B, 3) bounds."""

    def __init__(self, c, M, lam, lo, hi):
        self.c, self.M, self.lam = c.copy(), M.copy(), lam.copy()
        self.lo, self.hi = lo, hi
        self.esc = np.zeros(len(c), np.int8)

    def outside(self, basis: np.ndarray, idx: np.ndarray) -> np.ndarray:
        # one product for all texels, (G, k^2) @ (k^2, 3 B), in single precision (the
        # bounds carry a tolerance of a share of the range; this product was half of
        # an rlsop fit's time), then each texel's extremes over the directions
        cc = np.swapaxes(self.c[idx], 0, 2).reshape(self.c.shape[2], -1)
        f = basis.astype(np.float32) @ cc.astype(np.float32)  # (G, 3 B)
        return ((f.min(0).reshape(3, -1) < self.lo[idx].T)
                | (f.max(0).reshape(3, -1) > self.hi[idx].T)).any(0)

    def run(self, basis: np.ndarray, steps: int, flag: int, refit) -> None:
        """Up to ``steps`` escalations checked at ``basis`` (G, k^2); ``refit(sel, esc)``
        returns the refit of texels ``sel`` at their escalation counts ``esc``. Texels
        still outside after the last get ``flag``."""
        sel = np.arange(len(self.c))  # texels whose current fit is unchecked
        for step in range(steps + 1 if len(basis) else 0):
            sel = sel[self.outside(basis, sel)]
            if not len(sel):
                return
            if step == steps:
                self.esc[sel] = flag  # still outside: reported, not hidden
                return
            self.esc[sel] += 1
            self.c[sel], _, self.M[sel] = refit(sel, self.esc[sel])


SMOOTHING_GUARD_START = 1e-2  # rlsop's first lambda (relative) when its guard acts
LAMBDA_STEPS_PER_DECADE = 2  # rlsop's smoothing guard: lambda x sqrt(10) per escalation


def guard_steps(hemisphere: str) -> int:
    """The most escalations :func:`guarded_project`'s guard makes for a projection; a
    texel with one more is still outside the range after the last (reported)."""
    return GUARD_STEPS * (LAMBDA_STEPS_PER_DECADE if hemisphere == "rlsop" else 1)


def batch_cap(directions: np.ndarray, n: int) -> tuple[int, SampledCap]:
    """The bands the views of a batch (B, N, 3) resolve (:func:`resolvable_bands`, at
    most ``n``) and the batch's :class:`SampledCap`, both from the batch's mean view
    directions."""
    ref = directions.mean(0)
    k = resolvable_bands(ref, n)
    return k, SampledCap(ref, k)


def smoother(M: np.ndarray, Y: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """(B, k^2, N) the linear map ``S = M^-1 Y^T diag(omega)`` from a texel's
    observations to its coefficients (M (B, k^2, k^2), Y (B, N, k^2), omega (B, N))."""
    return np.linalg.solve(M, np.swapaxes(Y, 1, 2) * omega[:, None, :])


def smoother_loo(S: np.ndarray, Y: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(B, N, 3) leave-one-view-out residuals ``r_i / (1 - h_ii)`` of a linear smoother S
    (:func:`smoother`), r (B, N, 3) the residuals of its fit, h the diagonal of the hat
    matrix ``Y S``: exact for a linear smoother with its prior and regularisation held
    fixed. Inf where a view alone determines the fit (h ~ 1)."""
    h = np.einsum("bnk,bkn->bn", Y, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((h > 1 - 1e-9)[..., None], np.inf, r / (1 - h)[..., None])


def shrink_to_mean(y: np.ndarray, Y: np.ndarray, S: np.ndarray, omega: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stack a texel's SH fit with its DC term alone (the weighted mean level, a
    diffuse texture), the share chosen by leave-one-view-out error
    (:func:`stack_smoothers`).

    A highlight narrower than the view spacing, seen by one view, is drawn by the bands
    as a blob as wide as the spacing, bright where the truth is dark: the views beside
    it then predict the mean better than the blob and the share falls toward 0. Where
    the views resolve the highlight, it stays near 1.

    Parameters
    ----------
    y : (B, N, 3) observations; Y : (B, N, k^2) basis at the views;
    S : (B, k^2, N) the fit's smoother (:func:`smoother`); omega : (B, N) its weights.

    Returns
    -------
    As :func:`stack_smoothers`.
    """
    w = omega / omega.sum(1, keepdims=True)
    S0 = np.zeros_like(S)
    S0[:, 0, :] = w / Y[:, :1, 0]
    return stack_smoothers(y, Y, S, S0, omega)


def stack_smoothers(y: np.ndarray, Y: np.ndarray, S: np.ndarray, S0: np.ndarray,
                    omega: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blend ``alpha S + (1 - alpha) S0`` of two linear smoothers of a texel's
    views whose leave-one-view-out error ``sum_i w_i |alpha e_i + (1 - alpha) e0_i|^2``
    is least (e, e0: the smoothers' exact leave-one-out residuals, w the cell weights
    ``omega``; a quadratic in alpha in [0, 1], solved in closed form).

    Returns
    -------
    (B, k^2, N) the blended smoother, (B,) alpha and (B, N, 3) the blend's
    leave-one-out residuals (prediction minus observation).
    """
    w = omega / omega.sum(1, keepdims=True)
    e = _loo(S, Y, y)
    e0 = _loo(S0, Y, y)
    d = (e0 - e) * w[..., None]
    num = np.einsum("bnc,bnc->b", d, e0)
    den = np.einsum("bnc,bnc->b", d, e0 - e)
    alpha = np.clip(np.divide(num, den, out=np.ones_like(num), where=den > 0), 0.0, 1.0)
    a = alpha[:, None, None]
    return a * S + (1 - a) * S0, alpha, a * e + (1 - a) * e0


TUKEY_C = 4.685  # biweight cut-off in robust sd: 95 % efficiency on Gaussian noise
ROBUST_ROUNDS = 3


def robust_weights(y: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """(B, N) Tukey biweights of a texel's views from their residuals (B, N, 3): the
    RGB residual's length against ``TUKEY_C`` robust sds (1.4826 times its median over
    the texel's views). A view the bands cannot follow (a highlight narrower than the
    view spacing) gets weight 0."""
    r = np.linalg.norm(y - fitted, axis=-1)
    s = 1.4826 * np.median(r, axis=1, keepdims=True)
    x = r / np.maximum(TUKEY_C * s, 1e-30)
    return np.where(x < 1, (1 - x * x) ** 2, 0.0)


def _loo(S: np.ndarray, Y: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(B, N, 3) leave-one-out prediction minus observation of a linear smoother,
    ``h_ii`` held below 1 - 1e-3 (a view that alone determines the fit gets a large
    finite error, as in :func:`_loo_scores`)."""
    h = np.einsum("bnk,bkn->bn", Y, S)
    r = Y @ (S @ y) - y
    return r / np.maximum(1 - h, 1e-3)[..., None]


def coefficient_sd(S: np.ndarray, Y: np.ndarray, r: np.ndarray, n: int,
                   sigma: np.ndarray | None = None) -> np.ndarray:
    """Standard deviations of projected coefficients ``c = M^-1 Y^T diag(omega) y``.

    A linear smoother ``S = M^-1 Y^T diag(omega)`` propagates the observations'
    covariance: channel c's is ``S diag(s_c^2) S^T``. With the capture's noise model
    (``sigma``, the sd of each observation the HDR merge recorded) that is the spread
    over noise realisations. Without it, ``s = r`` (the sandwich, heteroscedasticity-
    robust as the MH uncertainties) scaled by ``N / (N - tr H)`` for the degrees of
    freedom the fit used (H = Y S); the residuals then also carry what the bands cannot
    represent (a sharp highlight), so the sd says how far the fit can be trusted
    rather than how it would vary with the noise.

    Parameters
    ----------
    S : (B, k^2, N) the smoother (:func:`smoother`); Y : (B, N, k^2) basis at the views;
    r : (B, N, 3) residuals; n : bands of the output;
    sigma : (B, N, 3) noise sd of each observation (radiance units), or None.

    Returns
    -------
    (B, 3, n^2): NaN for the bands above k (not fitted: zero by construction).
    """
    if sigma is not None:
        var = np.einsum("bkn,bnc->bck", S * S, sigma * sigma)
    else:
        N = Y.shape[1]
        edf = np.einsum("bnk,bkn->b", Y, S)
        scale = N / np.maximum(N - edf, 1.0)
        var = np.einsum("bkn,bnc->bck", S * S, r * r) * scale[:, None, None]
    return pad_bands(np.sqrt(var), n, fill=np.nan)


def pad_bands(c: np.ndarray, n: int, fill: float = 0.0) -> np.ndarray:
    """(B, 3, k^2) coefficients -> (B, 3, n^2), the bands above k ``fill`` (zero)."""
    out = np.full(c.shape[:2] + (n * n,), fill)
    out[..., : c.shape[-1]] = c
    return out
