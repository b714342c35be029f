"""Colour charts: the reference colours of a chart, the colour correction fitted to a
photo of it, and its error in CIEDE2000 (colour-science's data and formulas).

The correction itself, and its application to frames, is
:func:`parammap.models.radiometry.apply_colour`.
"""

from __future__ import annotations

from dataclasses import dataclass

import colour
import cv2
import numpy as np

from ..conventions import LUMINANCE
from .radiometry import apply_colour, colour_terms

__all__ = ["CHART_REFERENCES", "COLOUR_SPACES", "ChartReference", "chart_patch_means",
           "chart_reference", "colour_delta_e", "fit_colour_matrix"]

#: scene-linear spaces a colour matrix can map to: name -> colour-science's colourspace
COLOUR_SPACES = {"srgb-linear": "sRGB", "acescg": "ACEScg"}
#: the reference data of each chart (colour-science's names); MCC24 is the X-Rite
#: ColorChecker Classic, whose reflectances changed in November 2014
CHART_REFERENCES = {"MCC24": "ColorChecker24 - After November 2014"}


@dataclass(frozen=True)
class ChartReference:
    """A chart's patches in a scene-linear space and in CIE L*a*b*.

    rgb : (N, 3) linear reflectance in ``space``; lab : (N, 3) L*a*b* under the
    chart data's illuminant; neutral : (N,) bool grey patches; names : (N,).
    """

    rgb: np.ndarray
    lab: np.ndarray
    neutral: np.ndarray
    names: tuple[str, ...]
    space: str
    illuminant: np.ndarray  # CIE xy of the chart data's white

    def to_lab(self, rgb: np.ndarray) -> np.ndarray:
        """Linear RGB of ``space`` (N, 3) -> L*a*b* under the chart's illuminant
        (Bradford adaptation)."""
        xyz = colour.RGB_to_XYZ(rgb, COLOUR_SPACES[self.space], illuminant=self.illuminant,
                                chromatic_adaptation_transform="Bradford")
        return colour.XYZ_to_Lab(xyz, self.illuminant)


def chart_reference(reference: str, space: str = "srgb-linear") -> ChartReference:
    """The reference of a chart by colour-science's name (e.g. ``ColorChecker24 -
    After November 2014``, ``BabelColor Average``) in the scene-linear ``space``."""
    cc = colour.CCS_COLOURCHECKERS[reference]
    xyy = np.array(list(cc.data.values()), float)
    xyz = colour.xyY_to_XYZ(xyy)
    ill = np.asarray(cc.illuminant, float)
    rgb = colour.XYZ_to_RGB(xyz, COLOUR_SPACES[space], illuminant=ill,
                            chromatic_adaptation_transform="Bradford")
    lab = colour.XYZ_to_Lab(xyz, ill)
    neutral = np.hypot(lab[:, 1], lab[:, 2]) < 4.0  # the grey row (white to black)
    return ChartReference(rgb, lab, neutral, tuple(cc.data), space, ill)


def colour_delta_e(rgb: np.ndarray, reference_lab: np.ndarray, to_lab) -> np.ndarray:
    """CIEDE2000 between linear RGB (N, 3) and reference L*a*b* (N, 3); ``to_lab``
    converts the RGB (:meth:`ChartReference.to_lab`)."""
    return np.asarray(colour.delta_E(to_lab(rgb), reference_lab, method="CIE 2000"))


#: noisy copies of a left-out patch whose corrected colours judge a correction's noise
NOISE_COPIES = 16


def fit_colour_matrix(camera: np.ndarray, reference: np.ndarray, reference_lab: np.ndarray,
                      to_lab, neutral: np.ndarray, model: str = "root-polynomial",
                      noise: float = 0.0) -> tuple[np.ndarray, dict]:
    """The colour correction from a chart's camera RGB to its reference RGB.

    Parameters
    ----------
    camera : (N, 3) mean linear camera RGB of the patches (any exposure scale).
    reference : (N, 3) the patches' reflectance in the target space's linear RGB.
    reference_lab : (N, 3) their L*a*b*; to_lab : linear target RGB -> L*a*b*.
    neutral : (N,) bool, the grey patches.
    model : a name in :data:`parammap.models.radiometry.COLOUR_MODELS`.
    noise : relative sd of one pixel of the frames the correction will be applied to
        (the merge's record): the correction is judged on noisy copies of each left-out
        patch, so one that cancels large coefficients to fit the chart, and would
        multiply every pixel's noise as much, loses.

    Returns
    -------
    matrix : (3, n) on the model's terms of the RGB (:func:`apply_colour`), with
        ``apply_colour(camera_i) ~ s reference_i``, ``s`` the neutral patches' camera
        luminance over their reference luminance: a corrected frame keeps the merge's
        exposure scale (both models are homogeneous of degree one in the RGB).
    stats : ``delta_e`` per patch (CIEDE2000 of the corrected RGB over ``s``), its
        mean and maximum, ``delta_e_loo_mean`` (each patch predicted by a fit without
        it: what a colour the chart does not hold can expect), ``scale`` s, ``ridge``
        (the pull on the root-polynomial's cross terms, relative to their mean square)
        and the matrix's ``largest_coefficient``.

    Notes
    -----
    Least squares, the root-polynomial's cross terms pulled toward zero (ridge) by the
    amount that predicts each patch left out of the fit best, with the frames' pixel
    noise (a grid of 13 values and none): as far as the chart and the noise allow, the
    most the cross terms can follow. ``delta_e_loo_mean`` is that prediction's error,
    the noise included.
    """
    s = float((camera[neutral] @ LUMINANCE).sum() / (reference[neutral] @ LUMINANCE).sum())
    x = camera / s
    lin = colour_terms(x, "linear")
    terms = colour_terms(x, model)
    q = terms.shape[1]
    every = np.arange(len(camera))

    def solve(idx: np.ndarray, lam: float) -> np.ndarray:
        # least squares, the terms beyond R, G, B pulled toward zero by lam (ridge):
        # on a chart they are nearly collinear with R, G, B (sqrt(RG) ~ (R + G) / 2 on
        # its greys), and unpulled they cancel in coefficients of +-100 that a colour
        # off the chart's gamut turns into nonsense
        m0, *_ = np.linalg.lstsq(lin[idx], reference[idx], rcond=None)
        if q == 3:
            return m0.T
        A, b = terms[idx].T @ terms[idx], terms[idx].T @ reference[idx]
        pen = np.diag([0.0] * 3 + [lam] * (q - 3))
        return np.linalg.solve(A + pen + 1e-12 * np.trace(A) * np.eye(q), b).T

    rng = np.random.default_rng(0)
    jitter = 1 + noise * rng.standard_normal((NOISE_COPIES, 3))

    def loo(lam: float) -> np.ndarray:
        out = np.empty(len(every))
        for i in every:
            m = solve(every[every != i], lam)
            seen = np.vstack([x[[i]], x[i] * jitter]) if noise > 0 else x[[i]]
            out[i] = colour_delta_e(apply_colour(seen, m, model),
                                    np.repeat(reference_lab[[i]], len(seen), 0), to_lab).mean()
        return out

    # the pull that predicts a patch left out of the fit best (cross-validation), as a
    # pixel with the frames' noise sees it
    scale = float(np.trace(terms.T @ terms)) / q
    grid = [0.0] if q == 3 else [0.0, *(scale * np.logspace(-5, 1, 13))]
    scores = [float(loo(lam).mean()) for lam in grid]
    lam = grid[int(np.argmin(scores))]
    M = solve(every, lam)
    de = colour_delta_e(apply_colour(x, M, model), reference_lab, to_lab)
    return M, {"delta_e": de.tolist(), "delta_e_mean": float(de.mean()),
               "delta_e_max": float(de.max()), "delta_e_loo_mean": min(scores),
               "scale": s, "model": model, "ridge": lam / scale if scale else 0.0,
               "largest_coefficient": float(np.abs(M).max())}


def chart_patch_means(radiance: np.ndarray, saturated: np.ndarray, polygons: np.ndarray,
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Mean linear RGB (N, 3) inside each patch polygon (N, 4, 2) (pixels) and whether
    the patch had enough unsaturated pixels (N,)."""
    H, W = radiance.shape[:2]
    means = np.full((len(polygons), 3), np.nan)
    ok = np.zeros(len(polygons), bool)
    for i, poly in enumerate(polygons):
        mask = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(mask, np.round(poly).astype(np.int32), 1)
        sel = (mask > 0) & ~saturated
        if sel.sum() >= 0.5 * max(int(mask.sum()), 1) and sel.sum() >= 4:
            means[i] = radiance[sel].mean(0)
            ok[i] = True
    return means, ok
