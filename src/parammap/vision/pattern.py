"""The printed pattern as a model: a view's pose (and the camera's intrinsics, jointly
over views) refined by matching rendered marker patterns to the photo's pixels."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np
import scipy.ndimage as ndi
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares

from ..geometry import (
    Intrinsics,
    ray_jacobian,
)
from ..parallel import executor
from ..stores.capture import Capture, aruco_dictionary
from ..vision.pattern_kernel import pattern_predict, pattern_predict_grad
from .markers import _to_normalized

logger = logging.getLogger(__name__)


# Pattern refinement (refine_pose_pattern): texture samples per marker cell, and
# sub-samples per pixel edge (a pixel integrates the pattern over its area)
PATTERN_TEXELS_PER_CELL = 12


PATTERN_SUBSAMPLES = 3


PATTERN_MARGIN_CELLS = 0.3  # the outer border's outer edge meets an unknown surround


PATTERN_BLURS_PX = (0.05, 0.15, 0.35, 0.7, 1.4, 2.8)  # optical blur (Gaussian sd) tried per view


def _marker_pattern(dictionary: str, marker_id: int, cells: int, blur_texels: float,
                    ) -> np.ndarray:
    """The marker's black-and-white pattern, black border included, (n, n) floats in
    [0, 1] with ``PATTERN_TEXELS_PER_CELL`` samples per cell, blurred by
    ``blur_texels`` (Gaussian sd, samples)."""
    img = aruco_dictionary(dictionary).generateImageMarker(
        int(marker_id), cells * PATTERN_TEXELS_PER_CELL).astype(float) / 255.0
    return ndi.gaussian_filter(img, blur_texels) if blur_texels > 0 else img


def _plane_texture_coords(p: np.ndarray, nrm: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Pattern coordinates (n, 2) where the rays of undistorted normalised image points
    ``nrm`` (n, 2) of a camera with pose ``p`` (rvec, t) meet the surface plane z = 0,
    ``A`` (3, 3) mapping the plane (mm) to the pattern (samples)."""
    Rm, _ = cv2.Rodrigues(p[:3])
    C = -Rm.T @ p[3:]
    # the rays R^T (x, y, 1) in the surface frame, column by column (a thin matmul
    # would spin BLAS threads)
    x, y = nrm[:, 0], nrm[:, 1]
    s = -C[2] / (x * Rm[0, 2] + y * Rm[1, 2] + Rm[2, 2])
    X = C[0] + s * (x * Rm[0, 0] + y * Rm[1, 0] + Rm[2, 0])
    Y = C[1] + s * (x * Rm[0, 1] + y * Rm[1, 1] + Rm[2, 1])
    w = A[2, 0] * X + A[2, 1] * Y + A[2, 2]
    return np.stack([(A[0, 0] * X + A[0, 1] * Y + A[0, 2]) / w,
                     (A[1, 0] * X + A[1, 1] * Y + A[1, 2]) / w], -1)


class PatternView:
    """The pixels of one photo that see its markers' patterns, for pose refinement
    on the whole pattern (:func:`refine_pose_pattern`).

    Built at a starting pose: every pixel whose footprint lies inside a marker (its
    black border and its cells; the border's outer edge meets an unknown surround and is
    left out), ``PATTERN_SUBSAMPLES``^2 sub-pixel rays per pixel, flat cell interiors
    thinned to stay within ``max_pixels``. ``markers`` is empty when no marker lies
    wholly inside the photo.
    """

    def __init__(self, lum: np.ndarray, cap: Capture, marker_ids: list[int],
                 rvec: np.ndarray, tvec: np.ndarray, intr: Intrinsics,
                 max_pixels: int = 40000):
        known = {int(i): k for k, i in enumerate(cap.marker_ids)}
        self.dictionary = cap.marker_dictionary
        self.cells = aruco_dictionary(cap.marker_dictionary).markerSize + 2
        side = self.side = self.cells * PATTERN_TEXELS_PER_CELL
        H, W = lum.shape
        sub = (np.arange(PATTERN_SUBSAMPLES) + 0.5) / PATTERN_SUBSAMPLES - 0.5
        sub = np.stack(np.meshgrid(sub, sub), -1).reshape(-1, 2)
        self.ns = len(sub)
        lo_c = PATTERN_MARGIN_CELLS * PATTERN_TEXELS_PER_CELL
        hi_c = side - lo_c
        p0 = np.r_[np.ravel(rvec), np.ravel(tvec)]
        self.markers = []
        for mid in marker_ids:
            if int(mid) not in known:
                continue
            quad = np.asarray(cap.marker_corners[known[int(mid)]], np.float32)
            A = cv2.getPerspectiveTransform(quad, np.float32(
                [[0, 0], [side, 0], [side, side], [0, side]])).astype(float)
            proj, _ = cv2.projectPoints(np.c_[quad, np.zeros(4)].astype(float), p0[:3],
                                        p0[3:], intr.K, intr.dist)
            proj = proj.reshape(-1, 2)
            lo = np.floor(proj.min(0)).astype(int) - 1
            hi = np.ceil(proj.max(0)).astype(int) + 1
            if (lo < 0).any() or hi[0] >= W or hi[1] >= H:
                continue  # a marker cut by the frame: its pixels would be missing
            xs, ys = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
            px = np.c_[xs.ravel(), ys.ravel()].astype(float)
            # the rays of every sub-pixel sample, undistorted once
            rays = px[:, None, :] + sub[None]
            nrm = _to_normalized(rays.reshape(-1, 2), intr)
            uv = _plane_texture_coords(p0, nrm, A).reshape(len(px), self.ns, 2)
            inside = ((uv > lo_c) & (uv < hi_c)).all((1, 2))
            if inside.sum() < 20:
                continue
            # pattern samples per photo pixel along the marker's longer side
            scale = side / max(float(np.linalg.norm(np.roll(proj, -1, 0) - proj,
                                                    axis=1).max()), 1e-6)
            self.markers.append({"id": int(mid), "A": A, "scale": scale,
                                 "I": lum[ys.ravel(), xs.ravel()][inside].astype(float),
                                 "nrm": nrm.reshape(len(px), self.ns, 2)[inside],
                                 "px": rays[inside], "uv": uv[inside]})
        total = sum(len(m["I"]) for m in self.markers)
        if total > max_pixels:
            frac = max_pixels / total
            for m in self.markers:
                cell = m["uv"].mean(1) / PATTERN_TEXELS_PER_CELL
                edge = np.abs(cell - np.round(cell)).min(1) < 1.0  # near a cell edge
                rng = np.random.default_rng(m["id"])
                keep = edge | (rng.random(len(edge)) < 0.25 * frac)
                if keep.sum() > 1.5 * frac * len(edge):
                    keep &= rng.random(len(edge)) < 1.5 * frac * len(edge) / keep.sum()
                for k in ("I", "nrm", "px", "uv"):
                    m[k] = m[k][keep]
        # a marker thinned below what fits its levels is left out
        self.markers = [m for m in self.markers if len(m["I"]) >= 20]
        for m in self.markers:
            m["nrm"] = m["nrm"].reshape(-1, 2)
            m["px"] = m["px"].reshape(-1, 2)
            del m["uv"]
        self.pixels = sum(len(m["I"]) for m in self.markers)

    def set_intrinsics(self, intr: Intrinsics) -> None:
        """Re-cast every sub-pixel ray through the camera ``intr`` (the pixels and
        their photo values stay): for refining the intrinsics on the pattern."""
        for m in self.markers:
            m["nrm"] = _to_normalized(m["px"], intr, guess=m["nrm"])

    def textures(self, blur_px: float) -> list[np.ndarray]:
        """Each marker's pattern blurred by ``blur_px`` photo pixels."""
        return [_marker_pattern(self.dictionary, m["id"], self.cells, blur_px * m["scale"])
                for m in self.markers]

    def residuals(self, p: np.ndarray, textures: list[np.ndarray]) -> np.ndarray:
        """(pixels,) photo minus predicted luminance at pose ``p`` (rvec, tvec), each
        marker's black and white levels fitted (linear least squares), in units of its
        black-to-white step (markers in shade count alike)."""
        out = []
        for m, tex in zip(self.markers, textures, strict=True):
            e, coef = self._marker_residuals(m, tex, p)
            out.append(e / max(abs(coef[3]), 1e-12))
        return np.concatenate(out)

    def _marker_residuals(self, m: dict, tex: np.ndarray, p: np.ndarray,
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Photo minus prediction (photo units) of marker ``m`` at pose ``p``, and its
        fitted levels (:func:`_levels`)."""


        if pattern_predict is not None:
            Rm, _ = cv2.Rodrigues(np.asarray(p[:3], float))
            C = -Rm.T @ np.asarray(p[3:], float)
            n = len(m["I"])
            pred, x, y = np.empty(n), np.empty(n), np.empty(n)
            pattern_predict(Rm, C, m["nrm"], m["A"], tex, self.ns, pred, x, y)
            x, y = x / self.side - 0.5, y / self.side - 0.5
        else:
            uv = _plane_texture_coords(p, m["nrm"], m["A"])
            pred = map_coordinates(tex, [uv[:, 1] - 0.5, uv[:, 0] - 0.5], order=1,
                                   mode="nearest").reshape(-1, self.ns).mean(1)
            x, y = (uv.reshape(-1, self.ns, 2).mean(1) / self.side - 0.5).T
        X, _, coef = _levels(pred, x, y, m["I"])
        return m["I"] - X @ coef, coef

    def residuals_jacobian(self, p: np.ndarray, textures: list[np.ndarray],
                           ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`residuals` and their Jacobian (pixels, 6) by the pose, analytic: the
        compiled kernel's derivatives of the prediction, with the levels refitted at
        the moved pose (variable projection) and the step they scale by. None where
        numba is missing."""
        if pattern_predict_grad is None:
            return None
        Rm, dR = cv2.Rodrigues(np.asarray(p[:3], float))
        t = np.asarray(p[3:], float)
        C = -Rm.T @ t
        dR = np.ascontiguousarray(dR.reshape(3, 3, 3))
        rs, Js = [], []
        for m, tex in zip(self.markers, textures, strict=True):
            n = len(m["I"])
            f, x, y = np.empty(n), np.empty(n), np.empty(n)
            df, dx, dy = np.empty((n, 6)), np.empty((n, 6)), np.empty((n, 6))
            pattern_predict_grad(Rm, C, dR, t, m["nrm"], m["A"], tex, self.ns, f, x, y,
                                 df, dx, dy)
            x, y = x / self.side - 0.5, y / self.side - 0.5
            dx, dy = dx / self.side, dy / self.side
            X, G, c = _levels(f, x, y, m["I"])
            e = m["I"] - X @ c
            scale = max(abs(c[3]), 1e-12)
            r = e / scale
            # the design's derivative times the levels, then the levels' own change
            # (their refit at the moved pose) and the step's
            D = (c[1] + c[4] * f)[:, None] * dx + (c[2] + c[5] * f)[:, None] * dy \
                + (c[3] + c[4] * x + c[5] * y)[:, None] * df
            dXe = np.stack([np.zeros(6), e @ dx, e @ dy, e @ df,
                            e @ (df * x[:, None] + f[:, None] * dx),
                            e @ (df * y[:, None] + f[:, None] * dy)])  # (6 columns, 6)
            dc = np.linalg.solve(G, dXe - np.einsum("ni,nj->ij", X, D))  # (6 coef, 6)
            de = -(D + X @ dc)
            rs.append(r)
            Js.append(de / scale - np.outer(r, np.sign(c[3]) * dc[3] / scale))
        return np.concatenate(rs), np.concatenate(Js)

    def marker_fits(self, p: np.ndarray, textures: list[np.ndarray],
                    ) -> list[tuple[int, float, float]]:
        """Per marker at pose ``p``: (id, residual sd in units of its black-to-white
        step, that step over the marker's mean luminance). A marker that is not where
        the pose puts it (hidden, or not printed as listed) fits with a large residual
        and a small or negative step."""
        out = []
        for m, tex in zip(self.markers, textures, strict=True):
            e, c = self._marker_residuals(m, tex, p)
            out.append((m["id"], float(np.std(e)) / max(abs(c[3]), 1e-12),
                        float(c[3]) / max(float(np.mean(m["I"])), 1e-12)))
        return out


def _levels(pred: np.ndarray, x: np.ndarray, y: np.ndarray, lum: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A marker's black and white levels, each linear in the pattern position (the
    light may vary across a marker): the design X (n, 6), its normal matrix G and the
    least-squares coefficients for the photo's luminance ``lum``."""
    X = np.stack([np.ones_like(pred), x, y, pred, pred * x, pred * y], -1)
    # normal equations by einsum: BLAS would spin threads for these thin products, idle
    # work beside a pool's other workers
    G = np.einsum("ni,nj->ij", X, X)
    G[np.diag_indices(6)] += 1e-12 * np.trace(G)
    return X, G, np.linalg.solve(G, np.einsum("ni,n->i", X, lum))


def _pattern_noise(r: np.ndarray, free: int) -> tuple[float, float]:
    """Residual variance (``free`` fitted values) and the variance inflation of
    residuals correlated between neighbouring pixels (blur, demosaicing): the
    effective number of independent pixels, from the correlation of consecutive
    residuals (a 2-D field, correlated along both axes)."""
    n = len(r)
    s2 = float(r @ r) / max(n - free, 1)
    rho = float(np.clip(np.corrcoef(r[:-1], r[1:])[0, 1], 0.0, 0.95)) if n > 2 else 0.0
    return s2, ((1 + rho) / (1 - rho)) ** 2


def refine_pose_pattern(lum: np.ndarray, cap: Capture, marker_ids: list[int],
                        R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                        max_pixels: int = 40000, others: Sequence[int] = ()) -> dict | None:
    """Refine a pose on the whole pattern of its markers, not only their outlines.

    Every pixel inside a marker (its black border and every black or white cell, whose
    layout the dictionary gives; :class:`PatternView`) is predicted from the pose: the
    pixel's footprint meets the surface plane and samples the marker's pattern blurred
    by the optics, and a per-marker black and white level turns that into luminance.
    The pose minimises the squared difference to the photo. Each inner cell edge
    constrains the pose, so a marker gives tens of edges instead of four: at grazing
    views, where a marker is a few pixels high, this is what pins the camera down
    (pbr-tiny's 74 deg view: 2.3 -> 0.3 mm). The blur (Gaussian sd in pixels) is the
    one of ``PATTERN_BLURS_PX`` that fits best.

    Markers the detector missed (``others``: at grazing views, markers a few pixels
    high, often the far ones that pin the rotation best) then join where the refined
    pose puts them wholly inside the photo and their pattern fits there as well as the
    detected markers' (residual within ``PATTERN_NOISE_FACTOR`` times theirs, a step at
    least half theirs: a hidden or misplaced marker fails both), and the pose is solved
    again on all of them (pbr-bench's 81 deg view: 4 of its 10 markers detected).

    Parameters
    ----------
    lum : (H, W) linear luminance.
    marker_ids : markers detected in the view.
    R, t : starting pose.
    max_pixels : pixels used at most.
    others : the capture's other markers.

    Returns
    -------
    dict or None
        None when no marker lies wholly in the photo or the solve fails; else a dict with
        ``R``, ``t``, ``cov`` (6, 6) covariance of (rvec, tvec) (inflated for correlated
        residuals, :func:`_pattern_noise`), ``noise`` (residual sd in units of the
        black-to-white step), ``blur_px``, ``pixels``, ``markers`` (how many),
        ``marker_ids`` (which: the detected ones and the others that joined).
    """
    rvec, _ = cv2.Rodrigues(np.asarray(R, float))
    view = PatternView(lum, cap, marker_ids, rvec, np.asarray(t, float), intr, max_pixels)
    if not view.markers:
        return None
    p0 = np.r_[rvec.ravel(), np.asarray(t, float).ravel()]

    def solve(blur: float, view: PatternView = view, p0: np.ndarray = p0):
        tex = view.textures(blur)
        last: dict = {}

        def both(p):  # residuals and Jacobian in one pass, asked for at the same point
            if last.get("p") is None or not np.array_equal(last["p"], p):
                last.update(p=np.array(p, copy=True), rj=view.residuals_jacobian(p, tex))
            return last["rj"]

        analytic = view.residuals_jacobian(p0, tex) is not None
        try:
            if analytic:
                sol = least_squares(lambda p: both(p)[0], p0, jac=lambda p: both(p)[1],
                                    method="lm", x_scale="jac")
            else:
                sol = least_squares(lambda p: view.residuals(p, tex), p0, method="lm",
                                    x_scale="jac", diff_step=1e-7)
        except (ValueError, np.linalg.LinAlgError):
            return None
        return (float(sol.fun @ sol.fun), sol, blur) if np.all(np.isfinite(sol.x)) else None

    # the blur: solved at a middling one, then the others judged at that solution, and
    # solved again only if one fits clearly better there
    best = solve(PATTERN_BLURS_PX[len(PATTERN_BLURS_PX) // 2 - 1])
    if best is None:
        return None
    costs = {b: float(np.sum(view.residuals(best[1].x, view.textures(b)) ** 2))
             for b in PATTERN_BLURS_PX if b != best[2]}
    b = min(costs, key=costs.get)
    if costs[b] < 0.9 * best[0]:
        other = solve(b)
        if other is not None and other[0] < best[0]:
            best = other
    _, sol, blur = best
    marker_ids = [int(i) for i in marker_ids]
    others = [int(i) for i in others if int(i) not in marker_ids]
    if others:
        view, sol = _join_markers(lambda v, p: solve(blur, v, p), lum, cap, view, sol,
                                  marker_ids, others, blur, intr, max_pixels)
    s2, inflate = _pattern_noise(sol.fun, 6 + 6 * len(view.markers))
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2 * inflate
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all():
        return None
    Rn, _ = cv2.Rodrigues(sol.x[:3])
    return {"R": Rn, "t": sol.x[3:].copy(), "cov": cov, "noise": math.sqrt(s2),
            "blur_px": blur, "pixels": view.pixels, "markers": len(view.markers),
            "marker_ids": sorted(m["id"] for m in view.markers)}


def _join_markers(solve, lum: np.ndarray, cap: Capture, view: PatternView, sol,
                  detected: list[int], others: list[int], blur: float, intr: Intrinsics,
                  max_pixels: int):
    """Grow the pattern fit of the ``detected`` markers by those of ``others`` that
    show where the pose puts them (:func:`refine_pose_pattern`). A marker shows when
    its black-to-white step at the current pose is at least a quarter of the detected
    markers' (hidden, or listed where none is printed, it is near zero) and its residual
    sd within :data:`PATTERN_JOIN_LOOSE` times theirs. Each round, those that show
    with a residual within :data:`PATTERN_JOIN_FACTOR` times theirs join, or else the
    one that fits best, and the pose is solved again with them: a pose from a few near
    markers misplaces the far ones by a fraction of a cell, and each marker that joins
    brings the next into place.
    At the end every joined marker must fit within ``PATTERN_NOISE_FACTOR`` times the
    detected markers' residual. ``solve(view, p)``: (cost, solution, blur) or None.
    Returns the view and the solution."""
    joined: list[int] = []
    for _ in range(len(others)):
        rest = [i for i in others if i not in joined]
        if not rest:
            break
        trial = PatternView(lum, cap, detected + joined + rest, sol.x[:3], sol.x[3:], intr,
                            max_pixels)
        fits = {i: (sd, step) for i, sd, step in trial.marker_fits(sol.x, trial.textures(blur))}
        sd0 = float(np.median([fits[i][0] for i in detected if i in fits] or [np.inf]))
        step0 = float(np.median([fits[i][1] for i in detected if i in fits] or [np.inf]))
        shown = {i: fits[i][0] for i in rest if i in fits and fits[i][1] >= 0.25 * step0
                 and fits[i][0] <= PATTERN_JOIN_LOOSE * sd0}
        if not shown:
            break
        # those that fit well enough now, else the one that fits best
        new = [i for i in rest if shown.get(i, np.inf) <= PATTERN_JOIN_FACTOR * sd0] \
            or [min(shown, key=shown.get)]
        grown = PatternView(lum, cap, detected + joined + new, sol.x[:3], sol.x[3:], intr,
                            max_pixels)
        got = solve(grown, sol.x)
        if got is None:
            break
        joined += new
        view, sol = grown, got[1]
    if joined:
        fits = view.marker_fits(sol.x, view.textures(blur))
        sd0 = float(np.median([sd for i, sd, _ in fits if i in detected]))
        bad = [i for i, sd, _ in fits if i not in detected and sd > PATTERN_NOISE_FACTOR * sd0]
        if bad:
            keep = [i for i in joined if i not in bad]
            trimmed = PatternView(lum, cap, detected + keep, sol.x[:3], sol.x[3:], intr,
                                  max_pixels)
            got = solve(trimmed, sol.x)
            if got is not None:
                view, sol = trimmed, got[1]
    return view, sol


# The nine intrinsics the joint refinement frees, in the order of its vector
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


# pixels of all views together in the joint refinement, and per view at least and at most
PATTERN_JOINT_PIXELS = 250000


JOINT_POSE_EVALS = 12  # a view's pose follows a step of the intrinsics within a few


JOINT_TRIALS = 3  # damped steps tried per iteration before the refinement stops


PATTERN_JOINT_VIEW_PIXELS = (2000, 15000)


PATTERN_JOINT_MIN_VIEWS = 8  # fewer views leave the intrinsics to the corners


PATTERN_JOINT_MAX_VIEWS = 48  # views the joint refinement uses at most


# The intrinsics' finite differences move the image's edge by this much: the predicted
# pattern is bilinear between its samples, a few per pixel, so that smaller steps read
# the kinks of the interpolation rather than the slope of the blurred pattern
PATTERN_JOINT_STEP_PX = 0.1


PATTERN_JOINT_TOL_PX = 0.05  # the refinement stops when a step moves the edge less


# A view whose markers' pattern fits with a residual more than this many times the
# capture's median is suspect: one misidentified marker among a view's markers leaves
# about half of its cells wrong, which about doubles the residual sd.
PATTERN_NOISE_FACTOR = 1.5


# A marker the detector missed joins the pattern fit when, at the pose of the markers
# so far, its residual is within this many times theirs: a pose from a few near markers
# misplaces the far ones by a fraction of a cell, which about doubles their residual
PATTERN_JOIN_FACTOR = 3.0


PATTERN_JOIN_LOOSE = 10.0  # ... and it may join alone, as the best fit, within this


def _intrinsic_vector(intr: Intrinsics) -> np.ndarray:
    """(9,) fx, fy, cx, cy (px) and k1, k2, p1, p2, k3 of ``intr``."""
    d = np.zeros(5)
    d[:min(5, np.size(intr.dist))] = np.ravel(intr.dist)[:5]
    K = intr.K
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d]


def _with_intrinsics(intr: Intrinsics, th: np.ndarray) -> Intrinsics:
    """``intr`` with the nine intrinsics ``th`` (:func:`_intrinsic_vector`)."""
    K = np.array([[th[0], intr.K[0, 1], th[2]], [0.0, th[1], th[3]], [0.0, 0.0, 1.0]])
    return replace(intr, K=K, dist=np.asarray(th[4:9], float).copy())


def _intrinsic_steps(intr: Intrinsics, e: float = PATTERN_JOINT_STEP_PX) -> np.ndarray:
    """(9,) changes of the intrinsics that each move a point at the image's edge by
    about ``e`` px: the finite-difference steps and the solver's units."""
    f = float(intr.K[0, 0])
    r = 0.5 * max(intr.image_size) / f  # normalised radius of the image's edge
    return np.array([e / r, e / r, e, e, e / (f * r**3), e / (f * r**5),
                     e / (3 * f * r**2), e / (3 * f * r**2), e / (f * r**7)])


def _joint_view_pose(job: tuple) -> tuple[float, np.ndarray]:
    """One view's best pose at intrinsics ``th``, started from ``p``, and its sum of
    squared pattern residuals there: the poses follow each step of the intrinsics
    (variable projection), which keeps the solver out of the curved valley where
    linearised poses creep."""
    view, tex, p, th, intr = job
    view.set_intrinsics(_with_intrinsics(intr, th))
    last: dict = {}

    def both(q):
        if last.get("q") is None or not np.array_equal(last["q"], q):
            last.update(q=np.array(q, copy=True), rj=view.residuals_jacobian(q, tex))
        return last["rj"]

    try:
        sol = least_squares(lambda q: both(q)[0], p, jac=lambda q: both(q)[1], method="lm",
                            x_scale="jac", max_nfev=JOINT_POSE_EVALS)
    except (ValueError, np.linalg.LinAlgError):
        return math.inf, p
    return (float(sol.fun @ sol.fun), sol.x) if np.all(np.isfinite(sol.x)) else (math.inf, p)


def _joint_view_terms(job: tuple) -> tuple | None:
    """One view's share of the joint normal equations: (H_pp (6, 6), H_tp (9, 6),
    g_p (6,), H_tt (9, 9), g_t (9,)) with the intrinsics in units of their steps
    (:func:`_intrinsic_steps`; central differences), the pose's part analytic.
    None where the compiled kernel is missing."""
    view, tex, p, th, intr, steps = job
    view.set_intrinsics(_with_intrinsics(intr, th))
    got = view.residuals_jacobian(p, tex)
    if got is None:
        return None
    r, Jp = got
    # the rays move with the intrinsics by their analytic Jacobian; the residuals'
    # response to that is a central difference (the pattern is bilinear between samples)
    at = _with_intrinsics(intr, th)
    base = [m["nrm"] for m in view.markers]
    D = [ray_jacobian(b, at.K, at.dist) for b in base]
    Jt = np.empty((len(r), len(th)))
    for j, h in enumerate(steps):
        for m, b, d in zip(view.markers, base, D, strict=True):
            m["nrm"] = b + h * d[:, :, j]
        rp = view.residuals(p, tex)
        for m, b, d in zip(view.markers, base, D, strict=True):
            m["nrm"] = b - h * d[:, :, j]
        Jt[:, j] = 0.5 * (rp - view.residuals(p, tex))
    for m, b in zip(view.markers, base, strict=True):
        m["nrm"] = b
    return Jp.T @ Jp, Jt.T @ Jp, Jp.T @ r, Jt.T @ Jt, Jt.T @ r


def refine_intrinsics_pattern(
    intr: Intrinsics, views: list[tuple[str, PatternView, list, np.ndarray]],
    workers: int = 1, max_iter: int = 15,
) -> tuple[Intrinsics, dict, dict[str, np.ndarray]]:
    """Refine the intrinsics jointly with the poses of the captured views on their
    markers' whole pattern: a bundle adjustment on pixels, not on corners.

    Corners leave a valley along which the principal point trades against tangential
    distortion and the focal length; where a capture's corners are biased (blur, a
    filmic response, small oblique markers) the calibration slides along it and the
    view directions turn with it (pbr-tiny: principal point 1.15 px off, directions up
    to 0.065 deg off). The pattern of every marker, predicted pixel by pixel as in
    :func:`refine_pose_pattern`, fits the intrinsics and the poses together, so that
    where the valley leaves the principal point the poses stay consistent with it
    (pbr-tiny: directions within 0.04 deg of the truth).

    Levenberg-Marquardt on the nine intrinsics (:data:`INTRINSIC_NAMES`) and six pose
    parameters per view; each view's pose is eliminated from the normal equations
    (Schur complement) and each view's pose is solved again at every trial step
    (:func:`_joint_view_pose`); the intrinsics' derivatives are central differences
    (``PATTERN_JOINT_STEP_PX``). It stops when a step moves the image's edge by less
    than ``PATTERN_JOINT_TOL_PX`` or lowers the cost by less than one pixel's residual
    variance (a change the noise explains).

    Parameters
    ----------
    intr : the starting intrinsics (the corners' solution), at which ``views`` were built.
    views : (view id, :class:`PatternView`, its blurred textures, pose (rvec, tvec) (6,)).
    workers : processes that share the views.

    Returns
    -------
    The refined intrinsics (``intr`` itself when no step lowered the cost); a summary:
    ``views``, ``pixels``, ``iterations``, ``cost_before``, ``cost_after`` (sums of
    squared residuals in units of the markers' black-to-white step) and ``change``
    (refined minus starting value of each intrinsic); each view's pose (rvec, tvec) (6,)
    with them.
    """
    th0 = _intrinsic_vector(intr)
    steps = _intrinsic_steps(intr)
    pixels = max(sum(v[1].pixels for v in views), 1)
    th, ps = th0.copy(), [np.asarray(v[3], float) for v in views]
    lam, it = 1e-3, 0

    def total(ex, th, ps) -> tuple[float, list[np.ndarray]]:
        got = list(ex.map(_joint_view_pose, [(pv, tex, p, th, intr) for (_, pv, tex, _), p
                                             in zip(views, ps, strict=True)]))
        return float(sum(g[0] for g in got)), [g[1] for g in got]

    with executor(max(1, min(workers, len(views)))) as ex:
        cost0, ps = total(ex, th, ps)
        cost = cost0
        for it in range(1, max_iter + 1):
            terms = list(ex.map(_joint_view_terms, [(pv, tex, p, th, intr, steps) for
                                                    (_, pv, tex, _), p in zip(views, ps,
                                                                              strict=True)]))
            if any(t is None for t in terms):
                logger.info("calibration: no compiled pattern kernel; intrinsics left to "
                            "the corners")
                return intr, {}, {v[0]: np.asarray(v[3], float) for v in views}
            moved, before = None, cost
            for _ in range(JOINT_TRIALS):
                A, b, back = np.zeros((9, 9)), np.zeros(9), []
                for Hpp, Htp, gp, Htt, gt in terms:
                    Hi = np.linalg.inv(Hpp + lam * np.diag(np.diag(Hpp)))
                    HtpHi = Htp @ Hi
                    A += Htt - HtpHi @ Htp.T
                    b += gt - HtpHi @ gp
                    back.append((Hi, Htp, gp))
                A += lam * np.diag(np.diag(A))
                d = -np.linalg.solve(A, b)
                new_ps = [p - Hi @ (gp + Htp.T @ d) for p, (Hi, Htp, gp)
                          in zip(ps, back, strict=True)]
                new_cost, new_ps = total(ex, th + d * steps, new_ps)
                if np.isfinite(new_cost) and new_cost < cost:
                    th, ps, cost, moved = th + d * steps, new_ps, new_cost, float(np.abs(d).max())
                    lam = max(lam / 10, 1e-9)
                    break
                lam *= 10
            logger.info(f"calibration: pattern refinement step {it}: cost {cost:.3f}"
                        + ("" if moved is None else
                           f", edge moved {PATTERN_JOINT_STEP_PX * moved:.4f} px"))
            if moved is None or PATTERN_JOINT_STEP_PX * moved < PATTERN_JOINT_TOL_PX \
                    or before - cost < cost / pixels:
                break
    out = _with_intrinsics(intr, th) if cost < cost0 else intr
    return out, {"views": len(views), "pixels": int(pixels),
                 "iterations": it, "cost_before": cost0, "cost_after": min(cost, cost0),
                 "change": dict(zip(INTRINSIC_NAMES, (_intrinsic_vector(out) - th0).tolist(),
                                    strict=True))}, \
        {v[0]: p for v, p in zip(views, ps, strict=True)}
