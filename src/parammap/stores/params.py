"""Parameter-map EXR files: one multi-channel OpenEXR per surface and model.

Channel names and header attributes follow docs/reference/conventions.md:

- MH (K lobes): ``Kd.R Kd.G Kd.B m`` then for each lobe k = 1..K
  ``lobek.Ks.R lobek.Ks.G lobek.Ks.B lobek.d.X lobek.d.Y lobek.d.Z``;
- SH (n bands): ``sh.R.00 ... sh.R.(n^2-1)``, then G, then B (two digits at least);
- a microfacet SVBRDF (``svbrdf-ggx``): ``Kd.R Kd.G Kd.B Ks.R Ks.G Ks.B alpha coat``, its
  lights in the header (``parammap_lights``, JSON, :func:`parammap.stores.lights.light_doc`);
- a diffuse-only map (the baseline): ``Kd.R Kd.G Kd.B``.

Rows as in the texel convention (row 0 at the top edge), float32 by default (half on
request), ZIP compression. Header: ``parammap_model`` (mh, sh, svbrdf or diffuse),
``parammap_model_version``, ``parammap_layout`` (the channel names, space separated),
``parammap_hemisphere`` (SH), ``parammap_radiance_scale`` (a normalisation already
undone: 1), ``parammap_flatfield`` and ``parammap_colour`` (what the capture's white
card and colour chart divided out, :func:`parammap.models.radiometry.describe_radiometry`;
with a chart also ``parammap_colour_space`` and OpenEXR's ``colorInteropID``),
``width_mm``, ``height_mm``, ``S``, ``T`` and ``software``. An MH or SH map
may carry the per-texel standard deviations of its fit as extra channels (MH ``sd.Kd.R
... sd.m sd.lobek.Ks.R ... sd.lobek.d_deg``, SH ``sd.sh.R.00 ...``;
``parammap_sd_layout`` names them, :func:`parammap.conventions.sd_channels`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import (
    BEST_CHANNELS,
    DIFFUSE_CHANNELS,
    SVBRDF_CHANNELS,
    FitArray,
    mh_channels,
    mh_lobes,
    sd_channels,
    sh_bands,
    sh_channels,
)
from ..models.radiometry import RADIOMETRY_KEYS
from ..models.svbrdf import LightRig
from .common import HEIGHT_ATTR, S_ATTR, SOFTWARE_ATTR, T_ATTR, WIDTH_ATTR, software
from .exr import ExrError, read_exr, write_exr
from .fit import open_fit
from .lights import light_doc, parse_lamps, parse_light_doc
from .observation import open_observation_map
from .radiometry import colour_interop

__all__ = ["MODELS", "ParamMap", "ParamMapFiles", "best_shares", "channel_names",
           "param_map_from_fit", "read_param_map", "write_param_map"]

logger = logging.getLogger(__name__)

# svbrdf 2: the coat's share (version 1 had 7 channels, no coat)
MODELS = {"mh": 1, "sh": 1, "svbrdf": 2, "diffuse": 1, "best": 2}


class ParamMapError(ExrError):
    """A parameter-map EXR of an unknown model or layout."""


def channel_names(model: str, n_params: int) -> list[str]:
    """Channel names of a model's parameter vector of length ``n_params``."""
    if model == "diffuse":
        if n_params != len(DIFFUSE_CHANNELS):
            raise ParamMapError(f"diffuse maps have 3 parameters (got {n_params})")
        return list(DIFFUSE_CHANNELS)
    if model == "best":
        if n_params != len(BEST_CHANNELS):
            raise ParamMapError(f"best maps have {len(BEST_CHANNELS)} channels, "
                                 f"{', '.join(BEST_CHANNELS)} (got {n_params})")
        return list(BEST_CHANNELS)
    if model == "mh":
        try:
            K = mh_lobes(n_params)
        except ValueError as exc:
            raise ParamMapError(str(exc)) from None
        if K < 1:
            raise ParamMapError(f"MH maps have at least one lobe (got {n_params} values)")
        return mh_channels(K)
    if model == "svbrdf":
        if n_params != len(SVBRDF_CHANNELS):
            raise ParamMapError(f"svbrdf maps have {len(SVBRDF_CHANNELS)} parameters "
                                f"(got {n_params})")
        return list(SVBRDF_CHANNELS)
    if model == "sh":
        try:
            n = sh_bands(n_params // 3 if n_params % 3 == 0 else 0)
        except ValueError:
            raise ParamMapError(f"SH maps have 3 n^2 parameters (got {n_params})") from None
        return sh_channels(n)
    raise ParamMapError(f"unknown model {model!r} (known: {', '.join(MODELS)})")


@dataclass
class ParamMap:
    """A parameter map: ``params`` (T, S, P) in the model's docs/reference/conventions.md order."""

    model: str
    params: np.ndarray
    width_mm: float
    height_mm: float
    hemisphere: str | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    sd: np.ndarray | None = None  # (T, S, ...) standard deviations (sd_channels), or None
    # model "best": the candidate maps, by name, that its channels index
    parts: dict[str, ParamMap] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.params.shape[:2]

    def relit(self, position_mm: np.ndarray, intensity: np.ndarray,
              ambient: np.ndarray | None | str = "same",
              lamps: tuple[np.ndarray, np.ndarray, list] | None = None) -> ParamMap:
        """This svbrdf map under other lights: positions (J, 3) mm (or (P, 6), area
        lights' points, :func:`parammap.models.lights.expand_lights`) and relative RGB
        intensities (J, 3) in its own lights' units, in the same room (``ambient``
        "same": the room's ambient light it was fitted under stays) or another (3,)
        ambient irradiance (None: a dark room). Area lights' points name the ``lamps``
        they make (centres (L, 3) mm, RGB intensities (L, 3), extents), as the fitted
        map's header does: the viewer draws a lamp at its centre."""
        if isinstance(ambient, str):
            ambient = (self.lights or (None,) * 4)[3]
        return replace(self, attrs={**self.attrs, "lights": json.dumps(
            light_doc(position_mm, intensity, ambient=ambient, lamps=lamps))})

    @property
    def radiometry(self) -> dict[str, str]:
        """What the capture's white card and colour chart divided out of the radiance
        the map was fitted to (:func:`parammap.models.radiometry.describe_radiometry`);
        empty for maps from before it was recorded."""
        return {k: self.attrs[k] for k in RADIOMETRY_KEYS if k in self.attrs}

    @property
    def lights(self) -> LightRig | None:
        """An svbrdf map's lights from its header (``parammap_lights``,
        :func:`parammap.stores.lights.parse_light_doc`): positions, relative RGB
        intensities, the flat-field's irradiance its renders of the capture divide by
        (a relit map (:meth:`relit`) has none: its renders are the light's) and the
        room's ambient irradiance; None for other maps."""
        doc = self.attrs.get("lights")
        return None if doc is None else parse_light_doc(doc)

    @property
    def lamps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """An svbrdf map's area lights (centres (L, 3) mm, RGB intensities (L, 3)) whose
        points :attr:`lights` are (:func:`parammap.stores.lights.parse_lamps`); None for
        point lights and other maps."""
        doc = self.attrs.get("lights")
        return None if doc is None else parse_lamps(doc)


def write_param_map(path: str | Path, pm: ParamMap, half: bool = False) -> Path:
    """Write a parameter map EXR (atomically)."""
    names = channel_names(pm.model, pm.params.shape[-1])
    T, S = pm.shape
    attrs = {"parammap_model": pm.model, "parammap_model_version": MODELS[pm.model],
             "parammap_layout": " ".join(names), "parammap_radiance_scale": 1.0,
             WIDTH_ATTR: float(pm.width_mm), HEIGHT_ATTR: float(pm.height_mm),
             S_ATTR: int(S), T_ATTR: int(T), SOFTWARE_ATTR: software()}
    if pm.hemisphere:
        attrs["parammap_hemisphere"] = pm.hemisphere
    for k, v in pm.attrs.items():
        attrs[f"parammap_{k}"] = v
    attrs |= colour_interop(pm.attrs)
    chans = {n: pm.params[..., i] for i, n in enumerate(names)}
    if pm.sd is not None:
        sd_names = sd_channels(pm.model, pm.params.shape[-1])
        attrs["parammap_sd_layout"] = " ".join(sd_names)
        chans |= {n: pm.sd[..., i] for i, n in enumerate(sd_names)}
    return write_exr(path, chans, attrs, half)


def read_param_map(path: str | Path, with_sd: bool = True) -> ParamMap:
    """Read a parameter map EXR written by :func:`write_param_map`; ``with_sd=False``
    leaves its standard deviations out (``sd`` None: about half a map's memory, which a
    stage that holds many maps of a lab capture at once needs), and a best map's
    candidates (``parts``) are then read from their files when used
    (:class:`ParamMapFiles`) rather than all at once.

    Raises
    ------
    ParamMapError
        For a file of an unknown model or version, or whose channels do not follow the
        model's layout.
    """
    chans, h = read_exr(path)
    model = h.get("parammap_model")
    if model not in MODELS:
        raise ParamMapError(f"{path}: unknown parameter-map model {model!r} "
                            f"(known: {', '.join(MODELS)})")
    if h.get("parammap_model_version") != MODELS[model]:
        raise ParamMapError(f"{path}: {model} map version {h.get('parammap_model_version')!r}"
                            f" is not supported (expected {MODELS[model]}; a map of another "
                            "parammap version: rerun its fit and export)")
    layout = str(h.get("parammap_layout", "")).split()
    try:
        expected = channel_names(model, len(layout))
    except ParamMapError as exc:
        raise ParamMapError(f"{path}: {exc}") from None
    sd_layout = str(h.get("parammap_sd_layout", "")).split()
    if sd_layout and (model not in ("mh", "sh", "svbrdf")
                      or sd_layout != sd_channels(model, len(layout))):
        raise ParamMapError(f"{path}: standard deviations do not follow the {model} layout")
    if layout != expected or set(chans) != set(layout) | set(sd_layout):
        raise ParamMapError(f"{path}: channels do not follow the {model} layout "
                            f"(expected {expected[:6]}...)")
    if not with_sd:  # freed before the parameters are stacked: a lower peak
        for n in sd_layout:
            chans.pop(n, None)
    params = np.stack([chans.pop(n) for n in layout], -1).astype(np.float32, copy=False)
    if params.shape[:2] != (int(h.get(T_ATTR, -1)), int(h.get(S_ATTR, -1))):
        raise ParamMapError(f"{path}: image size does not match S, T in the header")
    extra = {k[len("parammap_"):]: v for k, v in h.items() if k.startswith("parammap_")
             and k not in ("parammap_model", "parammap_model_version", "parammap_layout",
                           "parammap_hemisphere", "parammap_sd_layout")}
    sd = np.stack([chans.pop(n) for n in sd_layout], -1).astype(np.float32, copy=False) \
        if sd_layout and with_sd else None
    del chans
    parts = None
    if model == "best":  # the candidates' own maps, beside this one
        names = str(extra.get("candidates", "")).split()
        if not names:
            raise ParamMapError(f"{path}: a best map names no candidates")
        paths = {n: Path(path).parent / f"{n}.exr" for n in names}
        # without sds (a stage holding many maps): each read from its file when used
        parts = ParamMapFiles(paths) if not with_sd else {
            n: read_param_map(p, with_sd) for n, p in paths.items()}
    return ParamMap(model, params, float(h[WIDTH_ATTR]), float(h[HEIGHT_ATTR]),
                    h.get("parammap_hemisphere"), extra, sd, parts)


class ParamMapFiles(Mapping):
    """Parameter maps by name, each read from its file when asked for and not kept
    (without its standard deviations): a stage that uses one map at a time holds one,
    where the ten maps of a lab capture's default config (and a best map's copies of
    them) are several GB."""

    def __init__(self, paths: dict[str, Path]):
        missing = [str(p) for p in paths.values() if not Path(p).is_file()]
        if missing:
            raise ParamMapError(f"no such parameter map: {', '.join(missing)}")
        self._paths = dict(paths)

    def __getitem__(self, name: str) -> ParamMap:
        return read_param_map(self._paths[name], with_sd=False)

    def __iter__(self) -> Iterator[str]:
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)


def best_shares(params: np.ndarray, n_candidates: int) -> np.ndarray:
    """(..., J) weight of each candidate in a best map's texels (params (..., 2):
    ``choice``, ``partner``; conventions.py ``BEST_CHANNELS``): half each where the two
    differ, all of one where they are the same."""
    idx = np.rint(np.nan_to_num(np.asarray(params, float)[..., :2])).astype(int)
    j = np.arange(n_candidates)
    return 0.5 * ((idx[..., :1] == j).astype(np.float32) + (idx[..., 1:2] == j))


def param_map_from_fit(fit_path: str | Path) -> ParamMap:
    """The parameter map of a finished fit store (``fit/<model>.zarr``)."""
    g = open_fit(fit_path)
    key = FitArray.COEFFS if g.model == "sh" else FitArray.PARAMS
    sd = g.get(FitArray.SD)
    return ParamMap(g.model, g[key][:], g.width_mm, g.height_mm, g.hemisphere, g.describe(),
                    sd[:] if sd is not None else None)


def diffuse_map(obs_path: str | Path) -> ParamMap:
    """The diffuse-only baseline: each texel's mean radiance over its valid
    observations (tile by tile)."""
    g = open_observation_map(obs_path)
    return ParamMap("diffuse", g.mean_radiance(), g.width_mm, g.height_mm,
                    attrs=g.radiometry)
