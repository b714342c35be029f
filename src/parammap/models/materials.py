"""Basis materials: a few shared MH materials for a whole surface (003, adapted to
parameter maps).

003 segments the surface into regions, fits a BRDF per region, merges regions whose
BRDFs agree into a few *basis materials*, then gives every point the basis material
that explains its photographs best (its eq. 7), or a blend of two or three. Here the
regions are the per-texel MH fits themselves:

1. **Features.** Texels whose fit has a lobe are described by what a material shares
   and a print does not: ln m and the specular colour (ln of the summed Ks luminance,
   and its chromaticity). The diffuse albedo Kd is left out on purpose: it is the
   printed texture, which varies inside one material.
2. **Clusters.** k-means on the features in units of relative change of the render
   (k given, or the largest k up to ``max_count`` whose clusters are clearly apart by
   their mean silhouette; :func:`choose_count`), on texels inside lobed regions with
   their neighbourhood's median features (the stage).
3. **Basis materials.** Each cluster's shininess m and specular chromaticity are
   refitted from the observations of (a sample of) all its texels at once, with every
   texel keeping its own Kd, lobe amplitudes and lobe directions (linear least squares
   given m); a golden-section search over ln m (001's exponent search). Thousands of
   texels share three numbers, so the shininess a single texel barely determines
   becomes stable.
4. **Assignment** (003 eq. 7): every texel is refitted with every basis material, and
   with none (diffuse only), and takes the one with the lowest BIC
   (``n ln(RSS / n) + p ln n``, so a lobe must pay for its amplitudes); then the basis
   is refitted from the texels assigned to it, twice.

Per-texel *blend weights* are the BIC model weights ``exp(-ΔBIC / 2)`` normalised over
the materials (the diffuse-only candidate first): the share of the evidence each basis
material has at that texel, 1 where the choice is clear. The rendered map uses the
chosen material: an ordinary MH map (Kd and lobe directions per texel, m and the
specular colour from the material, the lobe amplitudes per texel), so every stage that
reads MH maps renders it.

Lobe directions are the source fit's: a lobe is the mirror image of a light, which is
where it is whatever the material (a texel whose fit found no lobe borrows the lobes of
the nearest texel that did, in the stage). Pure numerics: arrays in, arrays out.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.cluster.vq import kmeans2

from ..config import default
from ..conventions import MH_KD, MH_M, FitArray, mh_dir, mh_ks, mh_lobes, mh_size
from .mh.model import M_MAX, M_MIN, mh_eval
from .mh.optim import KS_CAP

__all__ = [
    "adjusted_rand_index",
    "assign_materials",
    "choose_count",
    "cluster_materials",
    "fit_basis",
    "lobe_shapes",
    "material_features",
    "material_params",
]

GOLDEN = (math.sqrt(5) - 1) / 2


def lobe_shapes(dirs: np.ndarray, present: np.ndarray, m: np.ndarray | float,
                V: np.ndarray) -> np.ndarray:
    """Unit-amplitude lobes ``max(0, d_k . v) ** m`` of each texel (the MH model's own
    evaluation, :func:`parammap.models.mh.model.mh_eval`).

    Parameters
    ----------
    dirs : (n, K, 3) lobe directions; present : (n, K) bool, lobes the texel has
        (absent lobes are zero); m : (n,) or scalar shininess; V : (n, N, 3) directions.

    Returns
    -------
    (n, N, K)
    """
    n, K, _ = dirs.shape
    P = np.zeros((n, mh_size(1)))
    P[:, MH_M] = m
    P[:, mh_ks(0)] = 1.0
    out = np.empty(V.shape[:2] + (K,))
    for k in range(K):
        P[:, mh_dir(0)] = dirs[:, k]
        out[..., k] = mh_eval(P, V)[..., 0] * present[:, k, None]
    return out


def material_features(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Features of texels' MH parameters (n, 4 + 6K) that a material shares: ln m, ln of
    the summed Ks luminance, and the specular chromaticity (R and B over the sum).

    Returns
    -------
    (n, 4) features (NaN rows for texels without a lobe), (n,) bool: has a lobe.
    """
    P = np.asarray(P, float)
    K = mh_lobes(P.shape[1])
    ks = sum(np.clip(P[:, mh_ks(k)], 0, None) for k in range(K)) if K else np.zeros((len(P), 3))
    tot = ks.sum(1)
    has = np.isfinite(P).all(1) & (tot > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        F = np.stack([np.log(np.clip(P[:, MH_M], M_MIN, M_MAX)), np.log(tot / 3),
                      ks[:, 0] / tot, ks[:, 2] / tot], 1)
    F[~has] = np.nan
    return F, has


def _appearance_units(F: np.ndarray) -> np.ndarray:
    """Features of :func:`material_features` in units of relative change of what a
    render shows, so that k-means distances weigh them alike: the lobe's width (about
    m^-1/2 for a Phong lobe, so ln m / 2), its amplitude (ln Ks) and its colour (the
    chromaticities relative to grey's 1/3)."""
    return F * np.array([0.5, 1.0, 3.0, 3.0])


def cluster_materials(F: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """k-means labels (n,) of material features F (n, 4) (:func:`material_features`) in
    appearance units (k-means++ starts, the best of 8 runs by within-cluster sum of
    squares)."""
    Z = _appearance_units(F)
    if k <= 1 or len(Z) <= k:
        return np.zeros(len(Z), int)
    best, best_ss = None, np.inf
    rng = np.random.default_rng(seed)
    for _ in range(8):
        c, lab = kmeans2(Z, k, minit="++", seed=rng)
        ss = float(((Z - c[lab]) ** 2).sum())
        if ss < best_ss and len(np.unique(lab)) == k:
            best, best_ss = lab, ss
    return best if best is not None else np.zeros(len(Z), int)


def _silhouette(Z: np.ndarray, lab: np.ndarray) -> float:
    """Mean silhouette of labelled points Z (n, f)."""
    D = np.sqrt(((Z[:, None] - Z[None]) ** 2).sum(-1))
    ks = np.unique(lab)
    if len(ks) < 2:
        return -1.0
    mean_to = np.stack([D[:, lab == k].sum(1) / np.maximum((lab == k).sum()
                                                           - (lab == k), 1) for k in ks], 1)
    own = mean_to[np.arange(len(Z)), np.searchsorted(ks, lab)]
    other = np.where(ks[None, :] == lab[:, None], np.inf, mean_to).min(1)
    s = (other - own) / np.maximum(np.maximum(own, other), 1e-12)
    return float(np.mean(np.where(np.bincount(np.searchsorted(ks, lab))[np.searchsorted(ks, lab)]
                                  > 1, s, 0.0)))


def choose_count(F: np.ndarray, max_count: int = default("materials.max_count"),
                 min_silhouette: float = 0.5,
                 sample: int = default("materials.sample"), seed: int = 0) -> int:
    """Number of materials among texels with features F (n, 4): the largest k in 2 ..
    ``max_count`` whose clusters are all clearly apart (mean silhouette on a sample at
    least ``min_silhouette``, the usual bar for a real structure), or 1 when no k is.

    The largest rather than the best-separated k: a material costs three numbers
    against thousands of observations, a split of one true material into two is
    harmless to the renders (and its halves score a low silhouette), while two true
    materials merged into one are rendered with the wrong lobe (measured on the
    physically based captures: 8 materials predicted the held-out views better than the
    3 the best silhouette chose). A material no texel then chooses is dropped.
    """
    n = len(F)
    if n < 4:
        return 1
    rng = np.random.default_rng(seed)
    take = rng.choice(n, min(n, sample), replace=False)
    Z = _appearance_units(F)[take]
    best_k = 1
    for k in range(2, min(max_count, len(Z) - 1) + 1):
        if _silhouette(Z, cluster_materials(F[take], k, seed)) >= min_silhouette:
            best_k = k
    return best_k


def _linear_fit(L: np.ndarray, w: np.ndarray, G: np.ndarray, kappa: np.ndarray | None):
    """Per-texel least squares of ``L_vc = Kd_c + sum_k s_k kappa_c G_vk`` (``kappa``
    (n, 3) chromaticity, amplitudes s >= 0) or, with ``kappa`` None, of
    ``L_vc = Kd_c + sum_k Ks_kc G_vk`` (free colours).

    Parameters
    ----------
    L : (n, N, 3) radiance (0 where invalid); w : (n, N) weights (0 where invalid);
    G : (n, N, K) lobe shapes.

    Returns
    -------
    Kd (n, 3), amplitudes (n, K) or colours (n, K, 3), weighted RSS (n,).
    """
    n, N, K = G.shape
    sw = w.sum(1)
    if kappa is None:  # per channel: design [1, G] shared by the channels
        A = np.zeros((n, K + 1, K + 1))
        A[:, 0, 0] = sw
        wG = w[..., None] * G
        A[:, 0, 1:] = A[:, 1:, 0] = wG.sum(1)
        # batched matmuls: einsum's contractions are several times slower at these shapes
        wGt = wG.transpose(0, 2, 1)
        A[:, 1:, 1:] = np.matmul(wGt, G)
        b = np.concatenate([(w[..., None] * L).sum(1)[:, None],
                            np.matmul(wGt, L)], 1)  # (n, K+1, 3)
        A += np.eye(K + 1) * 1e-12 * np.maximum(A.trace(axis1=1, axis2=2), 1e-30)[:, None, None]
        x = np.linalg.solve(A, b)
        cap = KS_CAP * ((w[..., None] > 0) * L).max((1, 2))
        kd, ks = x[:, 0], np.clip(x[:, 1:], 0, cap[:, None, None])
        spec = np.matmul(G, ks)
        kd = (w[..., None] * (L - spec)).sum(1) / np.maximum(sw, 1e-30)[:, None]
        pred = kd[:, None] + spec
        return kd, ks, (w[..., None] * (L - pred) ** 2).sum((1, 2))
    k2 = (kappa ** 2).sum(1)
    A = np.zeros((n, 3 + K, 3 + K))
    A[:, np.arange(3), np.arange(3)] = sw[:, None]
    wG = w[..., None] * G
    cross = kappa[:, :, None] * wG.sum(1)[:, None, :]  # (n, 3, K)
    A[:, :3, 3:] = cross
    A[:, 3:, :3] = cross.transpose(0, 2, 1)
    wGt = wG.transpose(0, 2, 1)
    A[:, 3:, 3:] = np.matmul(wGt, G) * k2[:, None, None]
    b = np.concatenate([(w[..., None] * L).sum(1),
                        np.matmul(wGt, (L * kappa[:, None, :]).sum(-1)[..., None])[..., 0]], 1)
    A += np.eye(3 + K) * 1e-12 * np.maximum(A.trace(axis1=1, axis2=2), 1e-30)[:, None, None]
    x = np.linalg.solve(A, b[..., None])[..., 0]
    # as the MH fitter: a lobe whose peak no view saw cannot grow without limit
    cap = KS_CAP * ((w[..., None] > 0) * L).max((1, 2)) / np.maximum(kappa.max(1), 1e-12)
    s = np.clip(x[:, 3:], 0, cap[:, None])
    spec = np.matmul(G, s[..., None]) * kappa[:, None, :]
    kd = np.clip((w[..., None] * (L - spec)).sum(1) / np.maximum(sw, 1e-30)[:, None], 0, None)
    return kd, s, (w[..., None] * (L - kd[:, None] - spec) ** 2).sum((1, 2))


def _chromaticity(ks: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The specular colour (3,) of a material, summing to 3 (grey = 1, 1, 1): the
    weighted median over texels of their colours ``ks`` (n, 3)."""
    tot = ks.sum(1)
    ok = tot > 0
    if not ok.any():
        return np.ones(3)
    c = ks[ok] / tot[ok, None]
    wt = weight[ok]
    out = np.empty(3)
    for ch in range(3):
        o = np.argsort(c[:, ch])
        cw = np.cumsum(wt[o])
        out[ch] = c[o[np.searchsorted(cw, 0.5 * cw[-1])], ch]
    return 3 * out / max(out.sum(), 1e-12)


def fit_basis(dirs: np.ndarray, present: np.ndarray, V: np.ndarray, L: np.ndarray,
              w: np.ndarray, m0: float, iters: int = 24) -> tuple[float, np.ndarray, float]:
    """Shared shininess and specular colour of one material from its texels' data.

    Golden-section search over ln m (bracket: a factor e^2 around ``m0``, within the
    MH bounds); at each m every texel's Kd and lobe colours are solved linearly, the
    material's colour is their median chromaticity, and the criterion is the total
    weighted RSS with that colour shared.

    Returns
    -------
    m, kappa (3,), total weighted RSS.
    """
    def cost(lnm: float) -> tuple[float, np.ndarray]:
        G = lobe_shapes(dirs, present, math.exp(lnm), V)
        _, ks, _ = _linear_fit(L, w, G, None)
        kappa = _chromaticity(ks.sum(1), ks.sum((1, 2)))
        _, _, rss = _linear_fit(L, w, G, np.broadcast_to(kappa, (len(L), 3)))
        return float(rss.sum()), kappa

    lo = max(math.log(M_MIN), math.log(m0) - 2.0)
    hi = min(math.log(M_MAX), math.log(m0) + 2.0)
    a, b = lo + (1 - GOLDEN) * (hi - lo), lo + GOLDEN * (hi - lo)
    fa, fb = cost(a)[0], cost(b)[0]
    for _ in range(iters):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - GOLDEN) * (hi - lo)
            fa = cost(a)[0]
        else:
            lo, a, fa = a, b, fb
            b = lo + GOLDEN * (hi - lo)
            fb = cost(b)[0]
    lnm = a if fa <= fb else b
    rss, kappa = cost(lnm)
    return math.exp(lnm), kappa, rss


def assign_materials(dirs: np.ndarray, present: np.ndarray, V: np.ndarray, L: np.ndarray,
                     W: np.ndarray, w: np.ndarray, basis: list[tuple[float, np.ndarray]],
                     label: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Refit every texel with every basis material and with none; keep the lowest BIC
    (or the given ``label``: e.g. chosen on BIC summed over a neighbourhood).

    Parameters
    ----------
    dirs, present : (n, K, 3), (n, K) the source fit's lobes; V, L : (n, N, 3);
    W : (n, N) valid; w : (n, N) weights (mean 1 over the valid views);
    basis : (m, kappa) per material.

    Returns
    -------
    dict: ``label`` (n,) int (0: diffuse only, j + 1: basis material j), ``bic`` and
    ``weights`` (n, 1 + M) each candidate's BIC and BIC model weight, ``kd`` (n, 3),
    ``s`` (n, K) lobe amplitudes of the chosen material, ``rss`` (n,).
    """
    n = len(L)
    K = dirs.shape[1]
    nobs = np.maximum(3 * W.sum(1), 1)
    sw = np.maximum(w.sum(1), 1e-30)
    kd0 = (w[..., None] * L).sum(1) / sw[:, None]
    rss0 = (w[..., None] * (L - kd0[:, None]) ** 2).sum((1, 2))
    floor = 1e-12 * np.maximum((w[..., None] * L ** 2).sum((1, 2)), 1e-30)
    bics = [nobs * np.log(np.maximum(rss0, floor) / nobs) + 3 * np.log(nobs)]
    fits = [(kd0, np.zeros((n, K)), rss0)]
    for m, kappa in basis:
        G = lobe_shapes(dirs, present, m, V)
        kd, s, rss = _linear_fit(L, w, G, np.broadcast_to(kappa, (n, 3)))
        p = 3 + present.sum(1)
        bics.append(nobs * np.log(np.maximum(rss, floor) / nobs) + p * np.log(nobs))
        fits.append((kd, s, rss))
    B = np.stack(bics, 1)
    if label is None:
        label = np.argmin(B, 1)
    wts = np.exp(-0.5 * (B - B.min(1, keepdims=True)))
    wts /= wts.sum(1, keepdims=True)
    idx = np.arange(n)
    return {FitArray.LABEL: label, "bic": B, FitArray.WEIGHTS: wts,
            "kd": np.stack([f[0] for f in fits], 1)[idx, label],
            "s": np.stack([f[1] for f in fits], 1)[idx, label],
            "rss": np.stack([f[2] for f in fits], 1)[idx, label]}


def material_params(kd: np.ndarray, s: np.ndarray, label: np.ndarray, dirs: np.ndarray,
                    basis: list[tuple[float, np.ndarray]]) -> np.ndarray:
    """MH parameter rows (n, 4 + 6K) of assigned texels: Kd and lobe directions per
    texel, m and the specular colour from the chosen material, Ks = amplitude x colour
    (diffuse-only texels: Ks = 0, d = +z, m = 1)."""
    n, K, _ = dirs.shape
    P = np.zeros((n, mh_size(K)))
    P[:, MH_KD] = kd
    P[:, MH_M] = 1.0
    for k in range(K):
        P[:, mh_dir(k)] = [0.0, 0.0, 1.0]
    for j, (m, kappa) in enumerate(basis):
        sel = label == j + 1
        P[sel, MH_M] = m
        for k in range(K):
            on = sel & (s[:, k] > 0)
            P[on, mh_ks(k)] = s[on, k, None] * kappa
            P[on, mh_dir(k)] = dirs[on, k]
    return P


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labellings (Hubert and Arabie 1985): 1 for the same
    partition (whatever the label values), about 0 for independent ones."""
    a = np.unique(np.asarray(a).ravel(), return_inverse=True)[1]
    b = np.unique(np.asarray(b).ravel(), return_inverse=True)[1]
    C = np.zeros((a.max() + 1, b.max() + 1))
    np.add.at(C, (a, b), 1)

    def pairs(x):
        return (x * (x - 1) / 2).sum()

    sij, sa, sb, tot = pairs(C), pairs(C.sum(1)), pairs(C.sum(0)), pairs(np.array(C.sum()))
    expected = sa * sb / max(tot, 1)
    top = 0.5 * (sa + sb) - expected
    return float((sij - expected) / top) if top > 0 else 1.0
