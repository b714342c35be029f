"""Fit stores (``fit/<model>.zarr``): per-texel parameters and fit figures of one model.

One array per output of the model's tile function (``models.mh.mh_outputs``,
``models.sh.sh_outputs``; names :class:`parammap.conventions.FitArray`), chunked in
texel tiles, with the per-texel ``status`` (:class:`parammap.conventions.FitStatus`).
Attributes: ``model`` (``mh``, ``sh``), its settings and parameter layout, and the map's
grid. The store is written under a temporary name and renamed once complete; a fit
that was killed keeps its partial store with the key of the fit that wrote it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from ..conventions import SVBRDF_CHANNELS, FitArray, FitStatus
from ..errors import InputError
from ..models.radiometry import RADIOMETRY_KEYS, IrradianceGrid
from ..models.svbrdf import LightRig
from .common import (
    COMPLETE_ATTR,
    HEIGHT_ATTR,
    S_ATTR,
    SOFTWARE_ATTR,
    T_ATTR,
    TILE_ATTR,
    UNITS_ATTR,
    WIDTH_ATTR,
    MapStore,
    open_complete,
    software,
)
from .lights import light_doc, parse_light_doc
from .observation import ObservationMap, open_observation_map
from .paths import Processed

__all__ = ["FIT_UNITS", "MATERIALS_MODEL", "MH_LAYOUT", "SH_LAYOUT", "FitError", "FitStore",
           "TileArrays", "create_partial", "finish", "grid_attrs", "mh_attrs",
           "open_fit", "open_mh_source", "partial_key", "sh_attrs", "svbrdf_attrs", "tile_arrays",
           "write_fit_store"]

# the model name of the materials stage's map (docs/reference/outputs.md)
MATERIALS_MODEL = "mh-materials"

# the parameter layouts a store states (``layout`` attribute)
MH_LAYOUT = ("Kd.R Kd.G Kd.B m (lobeK.Ks.R lobeK.Ks.G lobeK.Ks.B lobeK.d.X lobeK.d.Y "
             "lobeK.d.Z)*K")
SH_LAYOUT = "sh.R.00 .. sh.R.(n^2-1), then G, then B; index l(l+1)+m"

# units of the fit stores' arrays (zarr attribute "units", read by xarray)
FIT_UNITS = {
    FitArray.PARAMS: "as the layout attribute: Kd, Ks in the observation map's radiance "
                     "units, m 1, d unit vector (surface frame); svbrdf alpha 1",
    FitArray.COEFFS: "the observation map's radiance units (orthonormal SH basis)",
    FitArray.RMSE: "the observation map's radiance units", FitArray.MPR: "percent",
    FitArray.CHI2: "1 (reduced chi-square)", FitArray.K_USED: "lobes",
    FitArray.EVALS: "objective evaluations",
    FitArray.STATUS: "parammap.conventions.FitStatus code",
    FitArray.REG: "1 (relative prior weight)", FitArray.GUARD: "range-guard escalations",
    FitArray.BANDS: "SH bands",
    FitArray.ROBUST: "1 (share of the robust refit)",
    FitArray.SHRINK: "1 (share of the fit kept over its DC term)",
    FitArray.SD: "standard deviations in the parameters' units, MH lobe direction in "
                 "degrees (conventions.sd_channels)",
}
# the materials stage's extra arrays say what they hold in place of units
_MATERIAL_UNITS = {FitArray.LABEL: "basis material (0: diffuse only)",
                   FitArray.WEIGHTS: "BIC weight of each candidate (diffuse only, then the "
                                     "materials)"}

_RESUME_ATTR = "parammap_resume_key"  # the key of the fit that wrote a partial store
_MODEL, _LAYOUT, _LIGHTS = "model", "layout", "lights"
_DISPLAY_GAMMA = "display_gamma"


class FitError(InputError):
    """A missing, incomplete or mismatched fit store, or a bad fit setting."""


def _compressor():
    return zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


# ---------------------------------------------------------------------------------
# Attributes


def mh_attrs(K: int | str, K_max: int, **settings: Any) -> dict[str, Any]:
    """The attributes that describe an MH fit: lobes asked for (``K``), the most stored
    (``K_max``), the layout, and ``settings`` (``fit``, ``repair``; the materials
    stage's ``source`` and ``materials``)."""
    return {_MODEL: "mh", "model_version": 1, "lobes": str(K), "K_max": K_max,
            _LAYOUT: MH_LAYOUT, **settings}


def sh_attrs(hemisphere: str, n: int, sampled_cap: bool, solid_angles: str,
             regularisation: float | str | None, shrink: bool = False,
             robust: bool = False, display_gamma: float | None = None) -> dict[str, Any]:
    """The attributes that describe an SH fit of ``n`` bands (``robust``: stacked with a
    robust refit, ``shrink``: blended with its DC term per texel, ``display_gamma``: the
    tone map whose shown values it fitted, None: the radiance; see
    :func:`parammap.models.sh.fit_sh_tile`)."""
    # "bands": the store's n (its array of that name: the bands each texel resolves)
    return {_MODEL: "sh", "model_version": 2, "hemisphere": hemisphere, FitArray.BANDS: n,
            "coefficients": n * n, "sampled_cap": sampled_cap, "solid_angles": solid_angles,
            "regularisation": regularisation, "shrunk_to_mean": shrink, "robust_refit": robust,
            _DISPLAY_GAMMA: None if display_gamma is None else float(display_gamma),
            _LAYOUT: SH_LAYOUT}


SVBRDF_LAYOUT = " ".join(SVBRDF_CHANNELS)


def svbrdf_attrs(lights_mm: np.ndarray, weights: np.ndarray,
                 irradiance: IrradianceGrid | None = None, ambient: np.ndarray | None = None,
                 lamps: tuple | None = None, **settings: Any) -> dict[str, Any]:
    """The attributes that describe an svbrdf fit: the lights it was fitted under
    (``lights``: ``position_mm`` (J, 3) (or (P, 6), area lights' points and ``lamps``),
    ``weights`` (J, 3) relative RGB intensities,
    the flat-field's ``irradiance`` it put back, the room's ``ambient`` irradiance,
    :func:`parammap.stores.lights.light_doc`) and ``settings`` (where the lights came
    from)."""
    # version 2: the coat's share (a plastic's diffuse light dimmed toward grazing)
    return {_MODEL: "svbrdf", "model_version": 2, _LAYOUT: SVBRDF_LAYOUT,
            _LIGHTS: light_doc(lights_mm, weights, irradiance, ambient, lamps), **settings}


def grid_attrs(obs: ObservationMap, tile: int, provenance: bool = True) -> dict[str, Any]:
    """The map's grid and the flat-field and colour of its radiance, copied from the
    observation map the fit read, its tile and (with ``provenance``) the version that
    wrote the store."""
    return {S_ATTR: obs.S, T_ATTR: obs.T, TILE_ATTR: tile, WIDTH_ATTR: obs.width_mm,
            HEIGHT_ATTR: obs.height_mm, "observation_views": len(obs.view_ids),
            **obs.radiometry, **({SOFTWARE_ATTR: software()} if provenance else {})}


# ---------------------------------------------------------------------------------
# Reading


class FitStore(MapStore):
    """A finished fit store opened for reading.

    Arrays are named by :class:`parammap.conventions.FitArray` (``store[FitArray.RMSE]``,
    or :meth:`get` for one a model may not have written); the attributes that stages
    read are properties. (T, S, ...) zarr arrays, read lazily.
    """

    def get(self, name: FitArray) -> zarr.Array | None:
        """The array ``name``, or None where this store has none (e.g. ``chi2`` of a fit
        without recorded noise, ``sd`` of an older store)."""
        return self.group[name] if name in self.group else None

    @property
    def model(self) -> str:
        """``mh``, ``sh`` or ``svbrdf``."""
        return self.group.attrs[_MODEL]

    @property
    def lobes(self) -> str | None:
        """MH lobes asked for: ``"1"``, ``"2"``, ``"auto"``, ..."""
        return self.group.attrs.get("lobes")

    @property
    def K_max(self) -> int | None:
        """Most lobes an MH store holds per texel."""
        return self.group.attrs.get("K_max")

    @property
    def hemisphere(self) -> str | None:
        """The SH hemisphere handling (``zh``, ``mirror``, ``lsop``, ``rlsop``, ``wls``)."""
        return self.group.attrs.get("hemisphere")

    @property
    def n_bands(self) -> int | None:
        """SH bands n of the store (n^2 coefficients per channel)."""
        return self.group.attrs.get(FitArray.BANDS)

    @property
    def coefficients(self) -> int | None:
        """SH coefficients per channel (n^2)."""
        return self.group.attrs.get("coefficients")

    @property
    def sampled_cap(self) -> bool:
        """Whether the SH fit was restricted to the sampled cap."""
        return bool(self.group.attrs.get("sampled_cap"))

    @property
    def solid_angles(self) -> str:
        """SH quadrature weights (``spherical`` in stores from before it was recorded)."""
        return self.group.attrs.get("solid_angles", "spherical")

    @property
    def shrink(self) -> bool:
        """Whether each texel's SH fit was blended with its DC term (False in stores from
        before it was recorded)."""
        return bool(self.group.attrs.get("shrunk_to_mean", False))

    @property
    def robust(self) -> bool:
        """Whether each texel's SH fit was stacked with a robust refit (False in stores
        from before it was recorded)."""
        return bool(self.group.attrs.get("robust_refit", False))

    @property
    def display_gamma(self) -> float | None:
        """The tone map's gamma an SH fit weighted its views by (the shown values'
        error), None where it fitted the radiance (and in stores from before)."""
        g = self.group.attrs.get(_DISPLAY_GAMMA)
        return None if g is None else float(g)

    @property
    def regularisation(self) -> float | str | None:
        return self.group.attrs.get("regularisation")

    def describe(self) -> dict[str, Any]:
        """The model settings a parameter map carries into its EXR header."""
        keys = ("lobes", "K_max", FitArray.BANDS, "coefficients", "regularisation",
                "shrunk_to_mean", "robust_refit", _DISPLAY_GAMMA, *RADIOMETRY_KEYS)
        out = {k: self.group.attrs[k] for k in keys if self.group.attrs.get(k) is not None}
        if _LIGHTS in self.group.attrs:  # an EXR header holds strings, not mappings
            out[_LIGHTS] = json.dumps(self.group.attrs[_LIGHTS])
        return out

    @property
    def lights(self) -> LightRig | None:
        """An svbrdf fit's lights (:func:`parse_light_doc`); None for other fits."""
        doc = self.group.attrs.get(_LIGHTS)
        return None if doc is None else parse_light_doc(doc)


def open_fit(path: str | Path) -> FitStore:
    """Open a finished fit store; refuses a missing or incomplete one."""
    return FitStore(open_complete(path, FitError, "fit store"), path)


def open_mh_source(processed: str | Path, model: str, setting: str,
                   ) -> tuple[FitStore, ObservationMap, np.ndarray, np.ndarray]:
    """A finished MH fit that a later stage builds on (``setting``: the config key that
    named it, for the error) and its observation map: (fit store, observation map,
    parameters (T S, 4 + 6K) float64, (T S,) bool fitted)."""
    proc = Processed(processed)
    src = open_fit(proc.fit(model))
    if src.model != "mh":
        raise InputError(f"{setting}: {model!r} is not an MH fit")
    obs = open_observation_map(proc.observation)
    P = np.asarray(src[FitArray.PARAMS][:], float).reshape(obs.T * obs.S, -1)
    ok = (np.asarray(src[FitArray.STATUS][:]) == FitStatus.OK).ravel()
    return src, obs, P, ok


# ---------------------------------------------------------------------------------
# Writing


class TileArrays:
    """A store's arrays, each opened (its metadata read from disk) on first use."""

    def __init__(self, path: str, mode: str):
        self.group = zarr.open_group(path, mode=mode)
        self.arrays: dict[str, zarr.Array] = {}

    def __getitem__(self, name: str) -> zarr.Array:
        if name not in self.arrays:
            self.arrays[name] = self.group[name]
        return self.arrays[name]

    def __contains__(self, name: str) -> bool:
        try:
            self[name]
        except KeyError:
            return False
        return True


_OPENED: dict[tuple[str, str], TileArrays] = {}


def tile_arrays(path: str, token: str) -> TileArrays:
    """The store at ``path``, opened once per process and ``token`` (the fit's resume key:
    a store of another fit at the same path is opened anew; "": read only). Opening an
    array reads its metadata from disk, a third of a small tile's I/O."""
    key = (path, token)
    if key not in _OPENED:
        if len(_OPENED) > 8:
            _OPENED.clear()
        _OPENED[key] = TileArrays(path, "r+" if token else "r")
    return _OPENED[key]


def partial_key(tmp: Path) -> str | None:
    """The key of the fit that wrote the partial store ``tmp`` (None: none readable)."""
    try:
        return zarr.open_group(tmp, mode="r").attrs.get(_RESUME_ATTR)
    except Exception:  # noqa: BLE001 - an unreadable partial store is started afresh
        return None


def create_partial(tmp: Path, key: str, outputs: dict[str, tuple[tuple[int, ...], str, Any]],
                   grid: tuple[int, int, int], attrs: dict[str, Any]) -> None:
    """A new partial store: one array per output (name -> trailing shape, dtype, fill)
    over the (T, S) grid in tiles of ``tile``, the fit's ``key`` and ``attrs``."""
    T, S, tile = grid
    g = zarr.open_group(tmp, mode="w")
    comp = _compressor()
    for name, (shape, dtype, fill) in outputs.items():
        # dimension names let xarray.open_zarr label the maps
        dims = ("row", "col") + tuple(f"{name}_{k}" for k in range(len(shape)))
        g.create_array(name, shape=(T, S) + tuple(shape), chunks=(tile, tile) + tuple(shape),
                       dtype=dtype, compressors=comp, fill_value=fill, dimension_names=dims,
                       attributes={UNITS_ATTR: FIT_UNITS.get(name, "")})
    g.attrs.update({**attrs, _RESUME_ATTR: key})


def finish(tmp: Path, out_path: Path) -> None:
    """Mark a partial store complete and move it to ``out_path`` (replacing it)."""
    g = zarr.open_group(tmp, mode="r+")
    if _RESUME_ATTR in g.attrs:
        del g.attrs[_RESUME_ATTR]
    g.attrs[COMPLETE_ATTR] = True
    if out_path.exists():
        shutil.rmtree(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp.rename(out_path)


def write_fit_store(path: Path, arrays: dict[str, tuple[np.ndarray, str, Any]], tile: int,
                    attrs: dict[str, Any]) -> None:
    """Write a whole fit store from in-memory (T, S, ...) arrays (name -> array, dtype,
    fill value), under a temporary name, then renamed."""
    tmp = path.with_name(f".{path.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    g = zarr.open_group(tmp, mode="w")
    comp = _compressor()
    for name, (arr, dtype, fill) in arrays.items():
        a = g.create_array(name, shape=arr.shape, chunks=(tile, tile) + arr.shape[2:],
                           dtype=dtype, compressors=comp, fill_value=fill,
                           attributes={UNITS_ATTR: FIT_UNITS.get(name,
                                                              _MATERIAL_UNITS.get(name, ""))})
        a[...] = arr.astype(dtype)
    g.attrs.update(attrs)
    finish(tmp, path)
