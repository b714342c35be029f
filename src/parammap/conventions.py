"""Conventions every stage shares (``docs/reference/conventions.md``), spelled out once.

Fitters, renderer, EXR code, figures and viewer read these names instead of repeating
the numbers.
"""

from __future__ import annotations

import math
from enum import IntEnum, StrEnum
from functools import lru_cache

import numpy as np

__all__ = [
    "BEST_CHANNELS", "DIFFUSE_CHANNELS", "LUMINANCE", "MHX_KD", "MHX_LNM",
    "MHX_LOBE", "MH_HEAD",
    "MH_KD", "MH_LOBE", "MH_M", "MH_SD_LOBE", "SH_CAP_AWARE", "SH_HEMISPHERES",
    "SVBRDF_CHANNELS", "SVBRDF_MODEL", "SV_ALPHA", "SV_COAT", "SV_KD", "SV_KS", "SV_SIZE",
    "FitArray", "FitStatus", "mh_channels", "mh_dir", "mh_dir_z", "mh_ks", "mh_lobe", "mh_lobes",
    "mh_sd_channels", "mh_sd_dir", "mh_sd_size", "mh_size", "mhx_ks", "mhx_lobes", "mhx_phi",
    "mhx_size", "mhx_theta", "sd_channels", "sh_bands", "sh_channels", "sh_degree_order",
    "sh_norms",
]

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
LUMINANCE.setflags(write=False)



class FitArray(StrEnum):
    """Names of the per-texel arrays a model's tile fit returns and its fit store holds
    (``fit/<model>.zarr``, :mod:`parammap.stores.fit`)."""

    PARAMS = "params"  # MH parameter vector (MH_* layout)
    COEFFS = "coeffs"  # SH coefficients, RGB-major
    SD = "sd"  # standard deviations of the parameters (sd_channels)
    RMSE = "rmse"  # per channel
    MPR = "mpr"  # mean percentage residual per channel
    CHI2 = "chi2"  # reduced chi-square against the recorded noise
    K_USED = "k_used"  # MH lobes used
    EVALS = "evals"  # objective evaluations
    STATUS = "status"  # FitStatus
    REG = "reg"  # SH prior weight chosen
    GUARD = "guard"  # SH range-guard escalations
    BANDS = "bands"  # SH bands the texel's views resolve
    ROBUST = "robust"  # SH: share of the robust refit in the fit (stack_smoothers)
    SHRINK = "shrink"  # SH: share of the fit kept over its DC term (shrink_to_mean)
    LABEL = "label"  # basis material (0: diffuse only)
    WEIGHTS = "weights"  # BIC weight of each candidate material
    CHANGED = "changed"  # repair pass: texels it refitted (not stored)
    LOO = "loo"  # leave-one-view-out residuals for the best stage (not stored)


class FitStatus(IntEnum):
    """Per-texel status codes of every fit store (``status`` array, int8)."""

    NOT_FITTED = 0
    OK = 1
    TOO_FEW = 2  # fewer observations than the model needs
    FAILED = 3  # the optimisation or projection failed; parameters are NaN


# --- Multiple Highlight (MH) parameter vector (docs/reference/conventions.md, 000 eq. 1) ---
#: ``Kd.R Kd.G Kd.B m`` then for each lobe k ``Ks.R Ks.G Ks.B d.X d.Y d.Z``.
MH_KD = slice(0, 3)
MH_M = 3
MH_HEAD = 4  # values before the first lobe
MH_LOBE = 6  # values per lobe


def mh_size(K: int) -> int:
    """Length of a K-lobe MH parameter vector (4 + 6K)."""
    return MH_HEAD + MH_LOBE * K


def mh_lobes(n_params: int) -> int:
    """Number of lobes K of an MH parameter vector of length ``n_params``.

    Raises
    ------
    ValueError
        When ``n_params`` is not 4 + 6K for some K >= 0.
    """
    K, rest = divmod(n_params - MH_HEAD, MH_LOBE)
    if K < 0 or rest:
        raise ValueError(f"MH parameter vectors have 4 + 6K values (got {n_params})")
    return K


def mh_lobe(k: int) -> slice:
    """Slice of lobe k's six values (Ks.RGB, d.XYZ); k counts from 0."""
    return slice(MH_HEAD + MH_LOBE * k, MH_HEAD + MH_LOBE * (k + 1))


def mh_ks(k: int) -> slice:
    """Slice of lobe k's specular colour Ks.R, Ks.G, Ks.B."""
    return slice(MH_HEAD + MH_LOBE * k, MH_HEAD + MH_LOBE * k + 3)


def mh_dir(k: int) -> slice:
    """Slice of lobe k's unit direction d.X, d.Y, d.Z (surface frame)."""
    return slice(MH_HEAD + MH_LOBE * k + 3, MH_HEAD + MH_LOBE * (k + 1))


def mh_dir_z(k: int) -> int:
    """Index of lobe k's d.Z (cosine of its zenith angle)."""
    return MH_HEAD + MH_LOBE * k + 5


def mh_channels(K: int) -> list[str]:
    """EXR channel names of a K-lobe MH map, lobes numbered from 1."""
    names = ["Kd.R", "Kd.G", "Kd.B", "m"]
    for k in range(1, K + 1):
        names += [f"lobe{k}.{q}" for q in ("Ks.R", "Ks.G", "Ks.B", "d.X", "d.Y", "d.Z")]
    return names


#: The fitters' free variables per texel ("x space"): ``Kd/s (3), ln m``, then per lobe
#: ``Ks/s (3), theta, phi`` (s: the texel's radiance scale) - 4 + 5K values.
MHX_KD = slice(0, 3)
MHX_LNM = 3
MHX_LOBE = 5


def mhx_size(K: int) -> int:
    """Number of free variables of a K-lobe MH fit (4 + 5K)."""
    return MH_HEAD + MHX_LOBE * K


def mhx_lobes(n_free: int) -> int:
    """Number of lobes K of an x-space vector of ``n_free`` = 4 + 5K values."""
    K, rest = divmod(n_free - MH_HEAD, MHX_LOBE)
    if K < 0 or rest:
        raise ValueError(f"MH x-space vectors have 4 + 5K values (got {n_free})")
    return K


#: Per-texel standard deviations of a K-lobe MH fit (fit store ``sd``, EXR ``sd.*``):
#: ``Kd.R Kd.G Kd.B m`` then per lobe ``Ks.R Ks.G Ks.B d`` (d: the lobe direction's
#: angular sd in degrees), 4 + 4K values in the parameters' own units.
MH_SD_LOBE = 4


def mh_sd_size(K: int) -> int:
    """Length of a K-lobe MH standard-deviation vector (4 + 4K)."""
    return MH_HEAD + MH_SD_LOBE * K


def mh_sd_dir(k: int) -> int:
    """Index of lobe k's direction sd (deg) in a standard-deviation vector."""
    return MH_HEAD + MH_SD_LOBE * k + 3


def mh_sd_channels(K: int) -> list[str]:
    """Names of the standard deviations of a K-lobe MH map (``sd.`` + parameter)."""
    names = ["sd.Kd.R", "sd.Kd.G", "sd.Kd.B", "sd.m"]
    for k in range(1, K + 1):
        names += [f"sd.lobe{k}.{q}" for q in ("Ks.R", "Ks.G", "Ks.B", "d_deg")]
    return names


def mhx_ks(k: int) -> slice:
    """Slice of lobe k's scaled Ks in x space."""
    return slice(MH_HEAD + MHX_LOBE * k, MH_HEAD + MHX_LOBE * k + 3)


def mhx_theta(k: int) -> int:
    """Index of lobe k's zenith angle (rad) in x space."""
    return MH_HEAD + MHX_LOBE * k + 3


def mhx_phi(k: int) -> int:
    """Index of lobe k's azimuth (rad) in x space."""
    return MH_HEAD + MHX_LOBE * k + 4


# --- Microfacet SVBRDF (svbrdf-ggx; parammap.models.svbrdf) ---
#: ``Kd.R Kd.G Kd.B Ks.R Ks.G Ks.B alpha coat``: diffuse (at normal incidence) and
#: specular amplitudes per unit irradiance factor of the first light, GGX roughness
#: alpha (= perceptual roughness^2) and the share of the diffuse light that crosses a
#: dielectric coating (0: matte, 1: a plastic's, attenuated toward grazing).
SV_KD = slice(0, 3)
SV_KS = slice(3, 6)
SV_ALPHA = 6
SV_COAT = 7
SV_SIZE = 8
SVBRDF_CHANNELS = ("Kd.R", "Kd.G", "Kd.B", "Ks.R", "Ks.G", "Ks.B", "alpha", "coat")
#: The svbrdf model's name in the workflow (outputs.md), its map's model ``svbrdf``.
SVBRDF_MODEL = "svbrdf-ggx"

#: A diffuse-only map (the baseline): Kd alone.
DIFFUSE_CHANNELS = ("Kd.R", "Kd.G", "Kd.B")
# the best-model-per-texel map (parammap.stages.best): the indices of each texel's two models in
# the header's space-separated "parammap_candidates" (their own EXRs beside it), rendered
# as the mean of the two's radiance; partner == choice where the texel has one model
BEST_CHANNELS = ("choice", "partner")


# --- Spherical harmonics (docs/reference/conventions.md, 004 eqs. 12.1-12.5) ---
#: Hemisphere handling of an SH fit: the published zero hemisphere, mirror and
#: least-squares-optimal projection, and ours (regularised LSOP, noise-weighted LS, and
#: the MH fit's function over the sampled cap).
SH_HEMISPHERES = ("zh", "mirror", "lsop", "rlsop", "wls", "mh")
#: SH baked from an MH fit (parammap.models.sh.bake) rather than projected from the views.
SH_BAKED = ("mh",)
#: Projections that can be restricted to the sampled cap of the hemisphere.
SH_CAP_AWARE = ("lsop", "rlsop", "wls")


def sh_bands(n_coeffs: int) -> int:
    """Number of bands n of an SH vector of n^2 coefficients per channel.

    Raises
    ------
    ValueError
        When ``n_coeffs`` is not a square.
    """
    n = math.isqrt(n_coeffs)
    if n < 1 or n * n != n_coeffs:
        raise ValueError(f"SH vectors have n^2 coefficients per channel (got {n_coeffs})")
    return n


def sh_degree_order(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Degree l and order m of each coefficient i = l (l + 1) + m of n bands."""
    l_ = np.repeat(np.arange(n), 2 * np.arange(n) + 1)
    m_ = np.concatenate([np.arange(-l, l + 1) for l in range(n)])
    return l_, m_


@lru_cache(maxsize=64)
def sh_norms(n: int) -> np.ndarray:
    """(n, n) normalisation K_l^m = sqrt((2l + 1) (l - m)! / (4 pi (l + m)!)), m >= 0."""
    K = np.zeros((n, n))
    for l in range(n):
        for m in range(l + 1):
            K[l, m] = math.sqrt((2 * l + 1) * math.factorial(l - m)
                                / (4 * math.pi * math.factorial(l + m)))
    K.setflags(write=False)
    return K


def sd_channels(model: str, n_params: int) -> list[str]:
    """Names of the standard-deviation channels of a map with ``n_params`` values per
    texel: MH :func:`mh_sd_channels`; SH ``sd.`` + each coefficient's channel (NaN
    above the bands a texel's views resolve); none for other models."""
    if model == "mh":
        return mh_sd_channels(mh_lobes(n_params))
    if model == "sh":
        return [f"sd.{c}" for c in sh_channels(sh_bands(n_params // 3))]
    if model == "svbrdf":
        return [f"sd.{c}" for c in SVBRDF_CHANNELS]
    raise ValueError(f"{model} maps carry no standard deviations")


def sh_channels(n: int) -> list[str]:
    """EXR channel names of an n-band SH map: ``sh.R.00 .. sh.R.(n^2-1)``, then G, B."""
    nc = n * n
    w = max(2, len(str(nc - 1)))
    return [f"sh.{c}.{i:0{w}d}" for c in "RGB" for i in range(nc)]
