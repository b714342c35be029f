"""Camera response recovery and HDR merging (Debevec-Malik 1997, 004 ch. 7.2).

The response is stored as the log-exposure curve ``g[z, c] = ln X`` for every 8-bit
level z and channel c, anchored at ``g[128] = 0``; radiance is then
``exp(g(z)) / t``, relative, with one global scale shared by every view of a capture
(docs/reference/conventions.md, *Radiance*).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import nnls

from ..config import default
from ..parallel import executor, progress
from ..plots import plot_reexposure, plot_response
from ..stores.capture import Capture, Exposure, View
from ..stores.hdr import (
    HdrError,
    hdr_provenance,
    load_reference_response,
    load_response,
    save_linear_response,
    save_response,
    write_hdr,
)
from ..stores.images import (
    RAW_FULL,
    ImageReadError,
    demosaic,
    is_raw,
    read_image,
    read_raw_mosaic,
)
from ..stores.metrics import digest, write_metrics
from ..stores.paths import Processed
from ..stores.radiometry import merged_frame_radiometry

logger = logging.getLogger(__name__)

__all__ = ["HdrError", "bracket_stops", "fit_sensor_noise", "hat_weights", "load_response",
           "merge_bracket", "merge_linear", "merge_view", "recover_response",
           "reexposure_error", "run_hdr", "run_response", "sample_pixels", "save_response",
           "select_smoothness", "smooth_candidates", "solve_debevec"]


def hat_weights(low: int = default("hdr.low"), high: int = default("hdr.high")) -> np.ndarray:
    """Debevec's hat weight over levels 0..255, zero at and beyond ``low``/``high`` so
    black and saturated pixels never count (OpenCV's weights do not vanish there)."""
    z = np.arange(256, dtype=float)
    mid = 0.5 * (low + high)
    w = np.where(z <= mid, z - low, high - z)
    return np.clip(w, 0, None) / (mid - low)


# Response samples come from pixels whose level a misregistration of the bracket by
# SAMPLE_SHIFT_PX moves by at most one level (the 8-bit quantisation's own error): the
# 5x5 morphological gradient spans 4 px, so a pixel of gradient G levels moves by about
# G / 4 * SAMPLE_SHIFT_PX. (The 12 levels used before left a finely printed or glossy
# surface without any bright sample and the top of the curve to the smoothness prior:
# pbr-mirror's HDR error 2.5x an oracle merge's, 1.0-1.1x now over four seeds; the real
# Frobisher bracket's re-exposure error unchanged.)
SAMPLE_SHIFT_PX = 0.1
SAMPLE_MAX_GRADIENT = 4.0 / SAMPLE_SHIFT_PX


def _draws(n: int, brackets: int) -> int:
    """Pixels drawn at random from each of ``brackets`` brackets for ``n`` samples."""
    return 6 * n // max(brackets, 1) + 50


def smooth_candidates(stack: np.ndarray, draws: int, rng: np.random.Generator,
                      low: int = default("hdr.low"), high: int = default("hdr.high"),
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of one bracket that may serve as response samples: ``draws`` drawn at
    random (``rng``), kept where smooth (a misaligned bracket or an edge would tie two
    radiances) and within the working range in some exposure.

    All the response needs of a bracket: a capture's brackets are reduced to these as
    they are read, so the response stage's memory does not grow with the photos' size.

    Parameters
    ----------
    stack : (P, H, W, 3) uint8 bracket.

    Returns
    -------
    (P, 1, k, 3) uint8 the k candidates' levels (a one-row image of them), (k,) their
    rows and (k,) their columns in the bracket.
    """
    mid = stack[len(stack) // 2].astype(np.float32).mean(axis=2)
    grad = cv2.morphologyEx(mid, cv2.MORPH_GRADIENT, np.ones((5, 5), np.uint8))
    H, W = mid.shape
    rr = rng.integers(4, H - 4, draws)
    cc = rng.integers(4, W - 4, rr.size)
    keep = grad[rr, cc] < SAMPLE_MAX_GRADIENT
    z = stack[:, rr, cc, :]
    keep &= ((z > low) & (z < high)).all(axis=2).any(axis=0)
    return np.ascontiguousarray(z[:, None, keep]), rr[keep], cc[keep]


def sample_pixels(
    brackets: list[np.ndarray], n: int, seed: int = 0, low: int = default("hdr.low"),
    high: int = default("hdr.high")
) -> np.ndarray:
    """Choose response samples: a fixed, seeded set of smooth pixels spread over the
    levels of every channel.

    Parameters
    ----------
    brackets : list of (P, H, W, 3) uint8 stacks, one per view (exposures long to short
        or in any order).
    n : number of samples wanted in total.

    Returns
    -------
    (n, 3) int array of (bracket index, row, col).
    """
    rng = np.random.default_rng(seed)
    cands = [smooth_candidates(b, _draws(n, len(brackets)), rng, low, high)
             for b in brackets]
    idx = _choose_samples([c[0] for c in cands], n, low, high)
    return np.array([(b, cands[b][1][j], cands[b][2][j]) for b, _, j in idx], int
                    ).reshape(-1, 3)


def _choose_samples(candidates: list[np.ndarray], n: int, low: int, high: int) -> np.ndarray:
    """(n, 3) (bracket, 0, candidate) of the samples chosen among the brackets'
    candidates ((P, 1, k, 3) each, :func:`smooth_candidates`)."""
    cands = np.concatenate([np.stack([np.full(c.shape[2], b), np.zeros(c.shape[2], int),
                                      np.arange(c.shape[2])], 1)
                            for b, c in enumerate(candidates)])
    if len(cands) < 20:
        raise HdrError("too few smooth, well-exposed pixels to recover the response")
    # Spread over the levels: in every exposure, every band of levels gets its share,
    # so the ends of the curve are pinned by data, not only by smoothness.
    lv = np.stack([candidates[b][:, r, c, :].mean(axis=1) for b, r, c in cands])  # (N, P)
    # Distinct radiances pin the curve; repeats of one radiance add little.
    _, first = np.unique(np.round(lv / 2), axis=0, return_index=True)
    first = np.sort(first)
    cands, lv = cands[first], lv[first]
    n_p = lv.shape[1]
    edges = np.linspace(low, high, 17)
    per = max(1, n // (16 * n_p))
    chosen: list[int] = []
    taken = np.zeros(len(cands), bool)
    for p in range(n_p):
        for lo_e, hi_e in zip(edges[:-1], edges[1:], strict=True):
            idx = np.flatnonzero(~taken & (lv[:, p] >= lo_e) & (lv[:, p] < hi_e))[:per]
            taken[idx] = True
            chosen.extend(idx.tolist())
    rest = np.flatnonzero(~taken)
    chosen.extend(rest[: max(0, n - len(chosen))].tolist())
    return cands[np.sort(np.array(chosen[:n] if len(chosen) > n else chosen, int))]


def _debevec_normal(Z: np.ndarray, log_t: np.ndarray, weights: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations (256 x 256, 256) of Debevec-Malik's data rows with each sample's
    ln E eliminated in closed form (a sample's ln E is the weighted mean of its
    exposures' g(z) - ln t)."""
    Z = np.asarray(Z, np.intp)
    w2 = weights[Z] ** 2
    W = w2.sum(axis=1)
    ok = W > 0
    Z, log_t, w2, W = Z[ok], np.asarray(log_t, float)[ok], w2[ok], W[ok]
    G = np.zeros((256, 256))
    rhs = np.zeros(256)
    np.add.at(G, (Z.ravel(), Z.ravel()), w2.ravel())
    np.add.at(rhs, Z.ravel(), (w2 * log_t).ravel())
    mean_log_t = (w2 * log_t).sum(axis=1) / W
    for p in range(Z.shape[1]):
        np.add.at(rhs, Z[:, p], -w2[:, p] * mean_log_t)
        for q in range(Z.shape[1]):
            np.add.at(G, (Z[:, p], Z[:, q]), -w2[:, p] * w2[:, q] / W)
    return G, rhs


def _debevec_prior(weights: np.ndarray) -> np.ndarray:
    """(256, 256) normal matrix of the second-difference rows at lambda = 1 plus the
    anchor g[128] = 0 (its unit row is added separately)."""
    zz = np.arange(1, 255)
    wz = np.maximum(weights[zz], 0.05)
    D = np.zeros((254, 256))
    D[zz - 1, zz - 1] = wz
    D[zz - 1, zz] = -2 * wz
    D[zz - 1, zz + 1] = wz
    return D.T @ D


def _solve_normal(G: np.ndarray, rhs: np.ndarray, prior: np.ndarray, smoothness: float
                  ) -> np.ndarray:
    M = G + smoothness**2 * prior
    M[128, 128] += 1.0
    return np.linalg.solve(M, rhs)


def solve_debevec(
    Z: np.ndarray, log_t: np.ndarray, smoothness: float, weights: np.ndarray
) -> np.ndarray:
    """Debevec-Malik's ``gsolve`` for one channel.

    The same least squares as the paper's (weighted data rows, second-difference rows,
    g[128] = 0), solved with each sample's log radiance eliminated in closed form: a
    256 x 256 system whatever the number of samples.

    Parameters
    ----------
    Z : (N, P) int levels of N samples in P exposures (each sample's own exposures).
    log_t : (N, P) log exposure times.
    smoothness : lambda, weight of the second-difference term.
    weights : (256,) weight per level.

    Returns
    -------
    (256,) float64 g(z) = ln X, anchored at g[128] = 0.
    """
    G, rhs = _debevec_normal(Z, log_t, weights)
    return _solve_normal(G, rhs, _debevec_prior(weights), smoothness)


def _inconsistency(g: np.ndarray, Z: np.ndarray, log_t: np.ndarray, weights: np.ndarray
                   ) -> np.ndarray:
    """(N,) each sample's weighted squared spread of g(z) - ln t about its mean: how far
    curve ``g`` (256,) is from merging the sample's exposures to one radiance."""
    w = weights[Z]
    y = g[Z] - log_t
    W = w.sum(axis=1)
    m = (w * y).sum(axis=1) / np.maximum(W, 1e-12)
    return np.where(W > 0, (w * (y - m[:, None]) ** 2).sum(axis=1), 0.0)


# The share of the noise's variance that the response curve's own error may add to the
# bracket's inconsistency (select_smoothness).
SMOOTHING_BUDGET = 0.1


def select_smoothness(Z: np.ndarray, log_t: np.ndarray, Zv: np.ndarray, log_tv: np.ndarray,
                      weights: np.ndarray, smoothness: float, stops: float
                      ) -> tuple[np.ndarray, float]:
    """Debevec's curve with the most smoothing the data allow.

    Exposures a ratio r apart leave the samples blind to any change of g that is
    periodic in ln X with period ln r (each sample ties g only at exposures r apart);
    only the second-difference prior holds such a wave down, and its curvature falls as
    (ln r)^-2, so the prior that restrains it at ``stops`` is ``smoothness * stops**2``.
    A real response may bend more than that prior lets it: lambda is halved from there
    (down to ``smoothness``) until the curve merges the validation samples ``Zv`` about
    as consistently as the least smoothed curve: their mean squared spread at most
    :data:`SMOOTHING_BUDGET` above the least (or one standard error, where that is
    more). The spread's excess is what the curve's own error adds to the noise's
    variance, so a tenth of it costs the merge under 5 % (sqrt(1.1)).

    Parameters
    ----------
    Z, log_t : (N, P) levels and log times of the fitting samples.
    Zv, log_tv : (M, P) the same of validation samples, none of them fitted.
    smoothness : lambda for exposures one stop apart.
    stops : the brackets' spacing (:func:`bracket_stops`).

    Returns
    -------
    (256,) g(z), anchored at g[128] = 0, and the lambda chosen.
    """
    G, rhs = _debevec_normal(Z, log_t, weights)
    prior = _debevec_prior(weights)
    lams = [smoothness * max(stops, 1.0) ** 2]
    while lams[-1] / 2 > smoothness * 1.001:
        lams.append(lams[-1] / 2)
    if lams[-1] > smoothness * 1.001:
        lams.append(smoothness)
    curves = [_solve_normal(G, rhs, prior, lam) for lam in lams]
    if len(curves) == 1 or len(Zv) < 20:
        return curves[0], lams[0]
    scores = np.array([_inconsistency(g, Zv, log_tv, weights) for g in curves])
    best = int(np.argmin(scores.mean(axis=1)))
    spread = scores[best].mean()
    limit = spread + max(SMOOTHING_BUDGET * spread, scores[best].std() / np.sqrt(scores.shape[1]))
    k = next(k for k in range(len(lams)) if scores[k].mean() <= limit)
    return curves[k], lams[k]


def bracket_stops(times: list[np.ndarray]) -> float:
    """Median spacing, in stops, between neighbouring exposures of the brackets (1 where
    no bracket has two distinct times)."""
    steps = [np.diff(np.log2(np.unique(np.asarray(t, float)))) for t in times]
    steps = np.concatenate([s for s in steps if s.size] or [np.ones(1)])
    return float(np.median(steps))


def _sample_levels(brackets: list[np.ndarray], times: list[np.ndarray], idx: np.ndarray,
                   channel: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, P) levels and log times of samples ``idx`` ((N, 3) bracket, row, column) in
    one channel; brackets of fewer exposures are padded with level 0 (weight 0)."""
    P = max(len(b) for b in brackets)
    Z = np.zeros((len(idx), P), np.intp)
    LT = np.zeros((len(idx), P))
    for k, (b, r, cc) in enumerate(idx):
        p = len(brackets[b])
        Z[k, :p] = brackets[b][:, r, cc, channel]
        LT[k, :p] = np.log(times[b])
    return Z, LT


def _monotonic(g: np.ndarray) -> np.ndarray:
    """Force a strictly increasing curve; unconstrained tails can wiggle."""
    out = np.maximum.accumulate(g, axis=0)
    eps = 1e-6 * np.arange(256)[:, None]
    return out + eps


def recover_response(
    brackets: list[np.ndarray], times: list[np.ndarray], method: str = default("hdr.method"),
    samples: int = default("hdr.samples"), smoothness: float = default("hdr.smoothness"),
    seed: int = 0, low: int = default("hdr.low"),
    high: int = default("hdr.high"), candidates: bool = False, info: dict | None = None,
) -> np.ndarray:
    """Recover the response from the brackets of one or more views.

    Parameters
    ----------
    brackets : list of (P_v, H, W, 3) uint8 stacks, or with ``candidates`` each
        bracket's candidate samples already drawn (:func:`smooth_candidates`, drawn
        with ``default_rng(seed)`` in the brackets' order).
    times : list of (P_v,) exposure times in seconds.
    method : ``debevec`` (this module's solver, zero weight at black and saturated
        levels) or ``robertson`` (OpenCV's, on the same samples).
    smoothness : Debevec's lambda for exposures one stop apart, scaled by the square of
        the brackets' spacing in stops (:func:`bracket_stops`).
    info : filled (``debevec``) with ``stops``, the brackets' spacing, and
        ``smoothness``, the lambda kept per channel (R, G, B).

    Returns
    -------
    (256, 3) g(z) = ln X per channel, anchored at g[128] = 0, strictly increasing.

    Notes
    -----
    Exposures a ratio r apart leave the samples blind to any change of g that is
    periodic in ln X with period ln r (each sample only ties g at levels r apart in
    exposure); only the second-difference prior holds such a wave down, and its
    curvature falls as (ln r)^-2, so lambda grows as the square of the spacing.
    """
    if not brackets:
        raise HdrError("no brackets to recover the response from")
    if all(len(b) < 2 for b in brackets):
        raise HdrError("every bracket has a single exposure; the response needs two or more")
    brackets = [b for b in brackets if len(b) >= 2]
    times = [np.asarray(t, float) for t in times if len(t) >= 2]
    if not candidates:
        rng = np.random.default_rng(seed)
        brackets = [smooth_candidates(b, _draws(samples, len(brackets)), rng, low, high)[0]
                    for b in brackets]
    idx = _choose_samples(brackets, samples, low, high)
    w = hat_weights(low, high)
    g = np.zeros((256, 3))
    if method == "debevec":
        # The candidates not chosen judge how much smoothing the data allow.
        chosen = {(int(b), int(j)) for b, _, j in idx}
        rest = np.array([(b, 0, j) for b, br in enumerate(brackets)
                         for j in range(br.shape[2]) if (b, j) not in chosen], int
                        ).reshape(-1, 3)
        stops = bracket_stops(times)
        chosen_lams = []
        for c in range(3):
            Z, LT = _sample_levels(brackets, times, idx, c)
            Zv, LTv = _sample_levels(brackets, times, rest, c)
            g[:, c], lam = select_smoothness(Z, LT, Zv, LTv, w, smoothness, stops)
            chosen_lams.append(float(f"{lam:.4g}"))
        logger.info(f"response: brackets {stops:.2f} stops apart, smoothness (R, G, B) "
                    f"{', '.join(f'{lam:g}' for lam in chosen_lams)}")
        if info is not None:
            info.update(stops=round(stops, 4), smoothness=chosen_lams)
    elif method == "robertson":
        groups: dict[int, list] = {}
        for b, r, cc in idx:
            groups.setdefault(len(brackets[b]), []).append((b, r, cc))
        # OpenCV treats each pixel of the strip as one scene point, so samples from
        # different views share one solve when their brackets have equal times.
        b0 = max(groups, key=lambda k: len(groups[k]))
        sel = groups[b0]
        t0 = times[sel[0][0]]
        strips = [np.ascontiguousarray(np.array(
            [brackets[b][p, r, cc, ::-1] for b, r, cc in sel], np.uint8)[None])
            for p in range(b0)]
        crf = cv2.createCalibrateRobertson().process(strips, t0.astype(np.float32))
        g = np.log(np.maximum(crf[:, 0, ::-1].astype(float), 1e-12))
        # Levels no sample showed come back NaN from OpenCV: interpolate them.
        z = np.arange(256)
        for c in range(3):
            ok = np.isfinite(g[:, c])
            if ok.sum() < 2:
                raise HdrError("robertson: too few distinct levels in the pixel sample")
            g[:, c] = np.interp(z, z[ok], g[ok, c])
        g -= g[128]
    else:
        raise HdrError(f"unknown response method {method!r}")
    return _monotonic(g)


def _weighted_exposures(stack: np.ndarray, low: int, high: int):
    """(index, levels as indices, hat weights) of each exposure of a (P, H, W, 3) stack."""
    w = hat_weights(low, high)
    for p in range(len(stack)):
        z = stack[p].astype(np.intp)
        yield p, z, w[z]


def merge_bracket(
    stack: np.ndarray, times: np.ndarray, g: np.ndarray, low: int = default("hdr.low"),
    high: int = default("hdr.high")
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge one bracket into linear relative radiance (Debevec-Malik eq. 6).

    Parameters
    ----------
    stack : (P, H, W, 3) uint8.
    times : (P,) exposure times, seconds.
    g : (256, 3) log-exposure response.

    Returns
    -------
    radiance : (H, W, 3) float32, ``exp(g(z)) / t`` averaged with hat weights.
    saturated : (H, W) bool, some channel at or above ``high`` in every exposure; its
        value comes from the shortest exposure and is a lower bound.
    dark : (H, W) bool, some channel at or below ``low`` in every exposure.
    """
    stack = np.asarray(stack)
    t = np.asarray(times, float)
    num = np.zeros(stack.shape[1:], float)
    den = np.zeros(stack.shape[1:], float)
    ch = np.arange(3)
    for p, z, wp in _weighted_exposures(stack, low, high):
        num += wp * (g[z, ch] - np.log(t[p]))
        den += wp
    short = int(np.argmin(t))
    long_ = int(np.argmax(t))
    fallback_hi = g[stack[short].astype(np.intp), ch] - np.log(t[short])
    fallback_lo = g[stack[long_].astype(np.intp), ch] - np.log(t[long_])
    zmax = stack.max(axis=0)
    lnE = np.where(den > 0, num / np.maximum(den, 1e-12),
                   np.where(zmax >= high, fallback_hi, fallback_lo))
    saturated = (stack.min(axis=0) >= high).any(axis=2)
    dark = (zmax <= low).any(axis=2)
    return np.exp(lnE).astype(np.float32), saturated, dark


QUANTISATION_SD = 1 / math.sqrt(12)  # sd of rounding to integer levels


def merge_noise(
    stack: np.ndarray, times: np.ndarray, g: np.ndarray, level_sd: float,
    low: int = default("hdr.low"), high: int = default("hdr.high"),
) -> np.ndarray:
    """Relative standard deviation of :func:`merge_bracket`'s radiance per pixel.

    Each exposure's log radiance ``g(z) - ln t`` moves by ``g'(z)`` per level, so a
    level noise of ``level_sd`` gives it an sd of ``g'(z) level_sd``; the hat-weighted
    mean of the exposures has sd ``sqrt(sum w^2 g'^2) level_sd / sum w``, which is the
    relative sd of the radiance. Pixels seen by several well-exposed photos come out
    low, pixels only the toe or shoulder of the response saw come out high.

    Returns
    -------
    (H, W) float32, mean over the three channels.
    """
    stack = np.asarray(stack)
    t = np.asarray(times, float)
    dg = np.abs(np.gradient(np.asarray(g, float), axis=0))  # (256, 3) d ln E / d level
    var = np.zeros(stack.shape[1:], float)
    den = np.zeros(stack.shape[1:], float)
    ch = np.arange(3)
    for _, z, wp in _weighted_exposures(stack, low, high):
        var += (wp * dg[z, ch]) ** 2
        den += wp
    single = dg[stack[int(np.argmin(t))].astype(np.intp), ch]  # fallback exposure
    rel = np.where(den > 0, np.sqrt(var) / np.maximum(den, 1e-12), single) * level_sd
    return rel.mean(-1).astype(np.float32)


def level_noise(mean_error: float | None, exposures: int) -> float:
    """Level noise (sd, 8-bit levels) of one exposure from the mean absolute re-exposure
    error (None: no pixel in range): the mean absolute error of a Gaussian is 0.80 sd,
    and the merged prediction contains the photo it predicts (about 1/P of it), which
    hides a share 1/P of the variance; never below the quantisation sd."""
    if mean_error is None:
        return QUANTISATION_SD
    P = max(exposures, 2)
    sd = math.sqrt(math.pi / 2) * float(mean_error) / math.sqrt(1 - 1 / P)
    return max(sd, QUANTISATION_SD)


BRIGHTNESS_TOLERANCE = 1.0  # levels: a photo's mean level is known far better than this


def bracket(view: View) -> tuple[list[Exposure], list[dict]]:
    """A view's exposures in one order whatever the order they are listed in: longest
    first, ties by file name. Of photos that claim one exposure time only the first is
    kept: the others are left out, each with the reason (``file``, ``reason``)."""
    ordered = sorted(view.exposures, key=lambda e: (-e.exposure_s, e.path.name))
    kept: list[Exposure] = []
    left_out = []
    for e in ordered:
        if kept and math.isclose(e.exposure_s, kept[-1].exposure_s, rel_tol=1e-6):
            left_out.append({"file": e.path.name, "reason": f"claims the exposure time of "
                             f"{kept[-1].path.name} ({e.exposure_s:g} s)"})
        else:
            kept.append(e)
    return kept, left_out


def load_bracket_checked(view: View) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """A view's photos as (P, H, W, 3) uint8, longest exposure first, their times (P,)
    and the photos left out (:func:`bracket`; and a photo brighter on average than a
    longer exposure of the bracket by more than ``BRIGHTNESS_TOLERANCE`` levels: its
    time is wrong or the scene changed)."""
    kept, left_out = bracket(view)
    imgs = []
    for ex in kept:
        img = read_image(ex.path)
        if img.dtype != np.uint8:
            raise HdrError(f"{ex.path}: 16-bit photo needs camera.response: linear")
        imgs.append(img)
    shapes = {im.shape for im in imgs}
    if len(shapes) > 1:
        raise HdrError(f"view {view.id}: photos of different sizes {sorted(shapes)}")
    keep = []
    for i, (ex, img) in enumerate(zip(kept, imgs, strict=True)):
        level = float(img.mean())
        brighter = [kept[j].path.name for j in keep
                    if level > float(imgs[j].mean()) + BRIGHTNESS_TOLERANCE]
        if brighter:
            left_out.append({"file": ex.path.name, "reason": f"brighter than the longer "
                             f"exposure {brighter[0]} ({ex.exposure_s:g} s claimed)"})
        else:
            keep.append(i)
    return (np.stack([imgs[i] for i in keep]),
            np.array([kept[i].exposure_s for i in keep]), left_out)


def load_bracket(view: View) -> tuple[np.ndarray, np.ndarray]:
    """A view's photos as (P, H, W, 3) uint8, longest exposure first, and their times
    (P,) (:func:`load_bracket_checked` without the photos it left out)."""
    stack, t, _ = load_bracket_checked(view)
    return stack, t


# Bins of level in which the sensor's noise is measured from a bracket's own pairs of
# exposures, and the pixels (a sample of rows) it is measured on.
NOISE_BINS, NOISE_SAMPLE_PIXELS = 24, 2**20


def fit_sensor_noise(stack: np.ndarray, t: np.ndarray, full: float,
                     high: int = default("hdr.high")) -> tuple[float, float]:
    """The sensor's noise in a linear bracket, ``var(v) = a v + b`` (shot and read
    noise; v the value over ``full``), measured from the bracket itself.

    Each exposure predicts the next shorter one, ``k v_p`` with ``k = t_q / t_p``; the
    difference ``r = v_q - k v_p`` has variance ``a k (1 + k) v_p + b (1 + k^2)``. Robust
    variances of r in bins of ``v_p`` (median absolute deviation, so edges and moving
    pixels do not count) are fitted by non-negative least squares, each bin weighted by
    its relative precision. A bracket of one exposure, or with too few unsaturated
    pairs, gives pure shot noise at one level per electron (``a = 1 / full``) and the
    quantisation of ``full`` levels (``b``).

    Returns
    -------
    (a, b) in units of the normalised value (v in [0, 1]).
    """
    fallback = (1.0 / full, QUANTISATION_SD ** 2 / full ** 2)
    P, H, W = stack.shape[:3]
    if P < 2:
        return fallback
    step = max(1, int(math.ceil(H * W / NOISE_SAMPLE_PIXELS)))
    sample = np.asarray(stack[:, ::step], np.float32) / full
    order = np.argsort(-np.asarray(t, float))
    sat = full * high / 255.0 / full
    rows, obs = [], []
    for p, q in zip(order[:-1], order[1:], strict=True):
        k = float(t[q] / t[p])
        vp, vq = sample[p], sample[q]
        ok = (vp < sat) & (vq < sat) & (vp > 0) & (vq > 0)
        vp, r = vp[ok], vq[ok] - k * vp[ok]
        if vp.size < 50 * NOISE_BINS:
            continue
        edges = np.unique(np.quantile(vp, np.linspace(0, 1, NOISE_BINS + 1)))
        which = np.clip(np.searchsorted(edges, vp, side="right") - 1, 0, len(edges) - 2)
        for b in range(len(edges) - 1):
            rb = r[which == b]
            if rb.size < 50:
                continue
            var = (1.4826 * np.median(np.abs(rb - np.median(rb)))) ** 2
            rows.append([k * (1 + k) * float(np.mean(vp[which == b])), 1 + k * k])
            obs.append(var)
    if len(obs) < 3:
        return fallback
    A, y = np.array(rows), np.array(obs)
    w = 1 / np.maximum(y, 1e-30)  # relative errors: each bin's variance to a share of it
    (a, b), _ = nnls(A * w[:, None], y * w)
    if a <= 0:
        return fallback
    return float(a), float(max(b, fallback[1]))


def merge_linear(stack: np.ndarray, t: np.ndarray, full: float,
                 low: int = default("hdr.low"), high: int = default("hdr.high"),
                 noise_model: tuple[float, float] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge a linear bracket (P, H, W, 3) of values up to ``full`` (16-bit, or RAW
    through :func:`parammap.stores.images.read_raw`).

    Each unsaturated exposure's ``v / t`` is weighted by its inverse variance under the
    sensor's noise model ``var(v) = a v + b`` (``noise_model``, from
    :func:`fit_sensor_noise` when None), evaluated at the value a first, shot-noise
    merge (``sum v / sum t``) predicts, so a pixel's own noise does not weight it.

    Returns
    -------
    radiance : (H, W, 3) float32, value per second (relative).
    saturated, dark : (H, W) bool; ``low`` and ``high`` in 8-bit levels, scaled to
        ``full``.
    noise : (H, W) float32, the merge's relative sd (mean over channels).
    """
    a, b = noise_model if noise_model is not None else fit_sensor_noise(stack, t, full, high)
    v = np.asarray(stack, np.float32) / np.float32(full)
    ok = v < high / 255.0
    tt = np.asarray(t, np.float32)[:, None, None, None]
    X0 = np.where(ok, v, 0).sum(0) / np.maximum(np.where(ok, tt, 0).sum(0), 1e-30)
    vhat = np.clip(X0[None] * tt, 0, 1)
    w = np.where(ok, tt ** 2 / (a * vhat + b), 0)
    wsum = w.sum(0)
    rad = (w * v / tt).sum(0) / np.maximum(wsum, 1e-30)
    saturated = (~ok).all(axis=0).any(axis=2)
    rad = np.where(saturated[..., None], v[np.argmin(t)] / float(np.min(t)), rad)
    dark = (v <= low / 255.0).all(axis=0).any(axis=2)
    rel = np.sqrt(1 / np.maximum(wsum, 1e-30)) / np.maximum(rad, 1e-30)
    rel = np.where(wsum > 0, rel, np.sqrt(a * v[np.argmin(t)] + b) / np.maximum(
        v[np.argmin(t)], 1e-30))
    return (rad * full).astype(np.float32), saturated, dark, rel.mean(-1).astype(np.float32)


# Pixels merged at once: the merge's float64 temporaries and re-exposure errors take
# about 100 bytes a pixel, so a strip of 2**21 pixels keeps a 24 MP bracket's merge
# near 1 GiB (the photos and the merged frame themselves, about 25 bytes a pixel,
# come on top) where merging it whole took several.
MERGE_STRIP_PIXELS = 2**21


def _strips(H: int, W: int) -> list[slice]:
    rows = max(1, MERGE_STRIP_PIXELS // max(W, 1))
    return [slice(r, min(r + rows, H)) for r in range(0, H, rows)]


def _merge_in_strips(stack: np.ndarray, t: np.ndarray, g: np.ndarray, low: int, high: int,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """:func:`merge_bracket`, its re-exposure errors and :func:`merge_noise` over strips
    of rows: radiance (H, W, 3), saturated, dark, noise (H, W) and the re-exposure
    summary. The noise's level sd comes from the whole frame's errors (a second pass)."""
    H, W = stack.shape[1:3]
    rad = np.empty((H, W, 3), np.float32)
    saturated, dark = np.empty((H, W), bool), np.empty((H, W), bool)
    parts = []
    for rows in _strips(H, W):
        rad[rows], saturated[rows], dark[rows] = merge_bracket(stack[:, rows], t, g, low, high)
        parts.append(reexposure_summary(reexposure_error(stack[:, rows], t, rad[rows], g,
                                                         low, high)))
    summary = parts[0] if len(parts) == 1 else pool_reexposure(parts)
    level = level_noise(summary["mean_levels"], len(t))
    noise = np.empty((H, W), np.float32)
    for rows in _strips(H, W):
        noise[rows] = merge_noise(stack[:, rows], t, g, level, low, high)
    return rad, saturated, dark, noise, summary


def merge_mosaic(sites: list[tuple[np.ndarray, np.ndarray]], t: np.ndarray,
                 low: int = default("hdr.low"), high: int = default("hdr.high"),
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The photosites of a bracket of camera RAWs merged as :func:`merge_linear` merges
    pixels, before any demosaicing, with the sensor's noise measured on them: where the
    scene is grey (the markers) they sample it at every pixel, which the demosaiced
    frame's interpolation does not. ``sites``: each exposure's photosites and filters
    (:func:`parammap.stores.images.read_raw_mosaic`), in the order of ``t``.

    Returns
    -------
    mosaic : (H, W) float32, value per second over the white level, in the units of
        :func:`merge_linear`'s radiance.
    colors : (H, W) uint8, each photosite's filter (0 R, 1 G, 2 B).
    """
    stack = np.stack([m for m, _ in sites])[..., None]
    model = fit_sensor_noise(stack, t, RAW_FULL, high)
    H, W = stack.shape[1:3]
    out = np.empty((H, W), np.float32)
    for rows in _strips(H, W):
        out[rows] = merge_linear(stack[:, rows], t, RAW_FULL, low, high, model)[0][..., 0]
    return out, sites[0][1]


def merge_view(
    view: View, g: np.ndarray | None, out: str | Path, low: int = default("hdr.low"),
    high: int = default("hdr.high"),
    provenance: dict[str, str] | None = None,
) -> dict:
    """Merge one view into ``out`` (EXR: R, G, B, saturated, dark, noise). ``g`` None
    means linear input (16-bit or RAW): radiance = value / t, averaged over unsaturated
    exposures; a bracket of camera RAWs also keeps its merged photosites
    (:func:`merge_mosaic`). ``provenance``: extra header attributes
    (:func:`hdr_provenance`)."""
    mosaic = None
    if g is None:
        kept, left_out = bracket(view)
        # a bracket of RAWs is decoded once: its photosites, and the frame demosaiced
        sites = [read_raw_mosaic(e.path) for e in kept] \
            if all(is_raw(e.path) for e in kept) else None
        stack = np.stack([demosaic(*x) for x in sites] if sites
                         else [read_image(e.path) for e in kept])
        full = 65535.0 if stack.max() > 255 else 255.0
        t = np.array([e.exposure_s for e in kept])
        H, W = stack.shape[1:3]
        rad = np.empty((H, W, 3), np.float32)
        saturated, dark = np.empty((H, W), bool), np.empty((H, W), bool)
        noise = np.empty((H, W), np.float32)
        model = fit_sensor_noise(stack, t, full, high)
        for rows in _strips(H, W):
            rad[rows], saturated[rows], dark[rows], noise[rows] = merge_linear(
                stack[:, rows], t, full, low, high, model)
        if sites:
            mosaic = merge_mosaic(sites, t, low, high)
    else:
        stack, t, left_out = load_bracket_checked(view)
        rad, saturated, dark, noise, reexposure = _merge_in_strips(stack, t, g, low, high)
    write_hdr(out, rad, saturated, dark, noise, view.id, provenance, mosaic)
    stats = {"view": view.id, "saturated_fraction": float(saturated.mean()),
             "dark_fraction": float(dark.mean())}
    if g is not None:
        stats["reexposure"] = reexposure
    if left_out:  # photos that contradict their exposure times: named, not merged
        stats["left_out"] = left_out
        for x in left_out:
            logger.warning(f"hdr: view {view.id}: {x['file']} left out: {x['reason']}")
    return stats


# Re-exposure errors are pooled over views through a histogram of REEXPOSURE_BIN levels.
REEXPOSURE_BIN = 0.05
REEXPOSURE_BINS = int(256 / REEXPOSURE_BIN)


def reexposure_summary(err: np.ndarray) -> dict:
    """Mean, 95th percentile and histogram (``REEXPOSURE_BIN`` levels wide) of
    absolute re-exposure errors in 8-bit levels."""
    hist = np.bincount(np.minimum((err / REEXPOSURE_BIN).astype(int), REEXPOSURE_BINS - 1),
                       minlength=REEXPOSURE_BINS)
    last = int(np.flatnonzero(hist)[-1]) + 1 if hist.any() else 0
    return {"mean_levels": float(err.mean()) if err.size else None,
            "p95_levels": float(np.percentile(err, 95)) if err.size else None,
            "pixels": int(err.size), "sum_levels": float(err.sum()),
            "histogram": hist[:last].tolist(), "bin_levels": REEXPOSURE_BIN}


def pool_reexposure(summaries: list[dict]) -> dict:
    """Pooled :func:`reexposure_summary` of several (views, or strips of one frame):
    the mean exact, the 95th percentile exact to one histogram bin."""
    summaries = [s for s in summaries if s and s["pixels"]]
    if not summaries:
        return {"mean_levels": None, "p95_levels": None, "pixels": 0, "sum_levels": 0.0,
                "histogram": [], "bin_levels": REEXPOSURE_BIN}
    n = sum(s["pixels"] for s in summaries)
    hist = np.zeros(max(len(s["histogram"]) for s in summaries), np.int64)
    for s in summaries:
        hist[: len(s["histogram"])] += s["histogram"]
    k = int(np.searchsorted(np.cumsum(hist), 0.95 * n))
    total = sum(s["sum_levels"] for s in summaries)
    return {"mean_levels": total / n, "p95_levels": (k + 1) * REEXPOSURE_BIN, "pixels": n,
            "sum_levels": total, "histogram": hist.tolist(), "bin_levels": REEXPOSURE_BIN}


def reexposure_error(
    stack: np.ndarray, times: np.ndarray, radiance: np.ndarray, g: np.ndarray,
    low: int = default("hdr.low"), high: int = default("hdr.high"),
) -> np.ndarray:
    """Absolute 8-bit differences between each photo and the merged radiance
    re-exposed with the response, over pixels in the working range."""
    levels = np.arange(256)
    errs = []
    for p, t in enumerate(times):
        lnX = np.log(np.maximum(radiance.astype(float), 1e-30)) + np.log(t)
        pred = np.stack([np.interp(lnX[..., c], g[:, c], levels) for c in range(3)], -1)
        z = stack[p].astype(float)
        ok = (z > low) & (z < high)
        errs.append(np.abs(pred - z)[ok])
    return np.concatenate(errs)


def response_for_capture(
    cap: Capture, cfg: dict, max_views: int = 24
) -> tuple[np.ndarray | None, dict]:
    """The capture's response: recovered from (up to ``max_views``, spread) brackets,
    read from a saved curve, or None for linear input. Unreadable or single-exposure
    views are skipped with a logged reason."""
    t0 = time.perf_counter()
    if cap.response == "linear":
        return None, {"response": "linear"}
    if cap.response != "auto":
        return load_response(cap.response), {"response": "file", "path": cap.response}
    views = cap.views
    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    # each bracket is reduced to its candidate samples as it is read: memory is one
    # bracket's, not the views'
    rng = np.random.default_rng(cfg["seed"])
    draws = _draws(cfg["samples"], len(pick))
    brackets, times, used = [], [], []
    for n, k in enumerate(pick):
        v = views[k]
        try:
            stack, t = load_bracket(v)
        except (ImageReadError, HdrError) as exc:
            logger.info(f"response: skipping view {v.id}: {exc}")
            continue
        if len(t) < 2:
            continue
        brackets.append(smooth_candidates(stack, draws, rng, cfg["low"], cfg["high"])[0])
        times.append(t)
        used.append(v.id)
        del stack
        if (n + 1) % 8 == 0:
            logger.info(f"response: read {n + 1}/{len(pick)} brackets")
    info: dict = {}
    g = recover_response(brackets, times, cfg["method"], cfg["samples"], cfg["smoothness"],
                         cfg["seed"], cfg["low"], cfg["high"], candidates=True, info=info)
    return g, {"response": cfg["method"], "views_used": used, **info,
               "samples": cfg["samples"], "seconds": time.perf_counter() - t0}


def run_response(cap: Capture, processed: str | Path, config: dict[str, Any], *,
                 figure: str | Path | None = None, reference: str | Path | None = None,
                 reference_label: str = "reference") -> dict:
    """The response stage: recover (or read) the capture's response into
    ``camera/response.csv`` (for linear input a file that says so,
    :func:`parammap.stores.hdr.save_linear_response`), with an optional figure of the
    curve beside a reference. ``config``: the validated workflow config (section
    ``hdr``)."""
    cfg = config["hdr"]
    out = Processed(processed)
    g, meta = response_for_capture(cap, cfg)
    if g is None:
        save_linear_response(out.response_csv, meta)
    else:
        save_response(out.response_csv, g, meta)
        if figure:

            ref = load_reference_response(reference) if reference else None
            plot_response(g, figure, reference=ref, reference_label=reference_label,
                          title=f"{cap.surface_id}: recovered response")
    logger.info(f"response: {meta['response']} -> {out.camera}")
    return meta


def _merge_job(job: tuple) -> dict:
    view, g, path, low, high, prov, stats_path = job

    t0 = time.perf_counter()
    st = merge_view(view, g, path, low, high, prov)
    st["seconds"] = time.perf_counter() - t0
    write_metrics(stats_path, st)
    return st


def run_hdr(cap: Capture, processed: str | Path, config: dict[str, Any], *,
            view_ids: list[str] | None = None, response: str | Path | None = None,
            workers: int | None = None) -> list[dict]:
    """The hdr stage: merge the brackets of the given views (default: all, with the
    white card's and the colour chart's) into
    ``hdr/<view>.exr`` with per-view statistics in ``hdr/<view>.json``, on ``workers``
    processes (default: config ``workers``); ``config`` section ``hdr``."""
    cfg = config["hdr"]
    workers = workers or config["workers"]
    out = Processed(processed)
    g = None if cap.response == "linear" else load_response(response or out.response_csv)
    views = ([cap.view(v) for v in view_ids] if view_ids
             else [*cap.views, *cap.radiometry_views])
    prov = hdr_provenance(digest(cfg), "linear" if g is None else digest(g),
                          merged_frame_radiometry(cap))
    jobs = [(v, g, out.hdr(v.id), cfg["low"], cfg["high"], prov, out.hdr_stats(v.id))
            for v in views]
    stats = []
    with executor(min(workers, len(jobs)) if jobs else 1) as ex:
        merged = progress(ex.map(_merge_job, jobs), len(jobs), "hdr: merged", logger)
        for v, st in zip(views, merged, strict=True):
            logger.debug(f"hdr: {v.id} saturated {st['saturated_fraction']:.4f}")
            stats.append(st)
    return stats


def gather_hdr_metrics(stats_paths: list[str | Path], out: str | Path,
                       figure: str | Path | None = None) -> dict:
    """Pool per-view HDR stats (``hdr/<view>.json``) into ``metrics/hdr.json``: views,
    worst saturated fraction and the re-exposure self-check (mean and 95th percentile,
    8-bit levels, pixels in the working range)."""
    views = {Path(p).stem: json.loads(Path(p).read_text()) for p in stats_paths}
    pooled = pool_reexposure([v.get("reexposure") for v in views.values()])
    per_view = {k: {kk: vv for kk, vv in v.items() if kk != "reexposure"}
                | ({"reexposure_mean_levels": v["reexposure"]["mean_levels"],
                    "reexposure_p95_levels": v["reexposure"]["p95_levels"]}
                   if v.get("reexposure") else {})
                for k, v in views.items()}
    left_out = {k: v["left_out"] for k, v in views.items() if v.get("left_out")}
    data = {"views": len(views),
            "saturated_fraction_max": max(v["saturated_fraction"] for v in views.values()),
            **({"photos_left_out": left_out} if left_out else {}),
            "reexposure_mean_levels": pooled["mean_levels"],
            "reexposure_p95_levels": pooled["p95_levels"],
            "reexposure_pixels": pooled["pixels"],
            "per_view": per_view}
    write_metrics(out, data)
    if figure:

        plot_reexposure(data, figure)
    return data
