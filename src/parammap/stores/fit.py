"""Fit stores (``fit/<model>.zarr``): per-texel parameters and fit figures of one model.

One array per output of the model's tile function (``models.mh.mh_outputs``,
``models.sh.sh_outputs``), chunked in the observation map's texel tiles, with the
per-texel ``status`` (:class:`parammap.conventions.FitStatus`). Attributes: ``model``
(``mh``, ``sh``), its settings and the MH parameter layout.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

from ..conventions import FitStatus
from ..errors import InputError
from ..stores.paths import Processed
from .common import open_complete
from .observation import open_observation_map

__all__ = ["FIT_UNITS", "MATERIALS_MODEL", "FitError", "open_fit", "open_mh_source"]


# units of the fit stores' arrays (zarr attribute "units", read by xarray)
FIT_UNITS = {
    "params": "as the layout attribute: Kd, Ks in the observation map's radiance units, "
              "m 1, d unit vector (surface frame)",
    "coeffs": "the observation map's radiance units (orthonormal SH basis)",
    "rmse": "the observation map's radiance units", "mpr": "percent",
    "chi2": "1 (reduced chi-square)", "k_used": "lobes", "evals": "objective evaluations",
    "status": "parammap.conventions.FitStatus code", "reg": "1 (relative prior weight)",
    "guard": "prior escalations", "bands": "SH bands",
    "sd": "standard deviations in the parameters' units, MH lobe direction in degrees "
          "(conventions.sd_channels)",
}


class FitError(InputError):
    """A missing, incomplete or mismatched fit store, or a bad fit setting."""


def open_mh_source(processed: str | Path, model: str, setting: str,
                   ) -> tuple[zarr.Group, zarr.Group, np.ndarray, np.ndarray]:
    """A finished MH fit that a later stage builds on (``setting``: the config key that
    named it, for the error) and its observation map: (fit store, observation map,
    parameters (T S, 4 + 6K) float64, (T S,) bool fitted)."""

    proc = Processed(processed)
    src = open_fit(proc.fit(model))
    if src.attrs.get("model") != "mh":
        raise InputError(f"{setting}: {model!r} is not an MH fit")
    obs = open_observation_map(proc.observation)
    T, S, _ = obs["valid"].shape
    P = np.asarray(src["params"][:], float).reshape(T * S, -1)
    ok = (np.asarray(src["status"][:]) == FitStatus.OK).ravel()
    return src, obs, P, ok


def open_fit(path: str | Path) -> zarr.Group:
    """Open a finished fit store; refuses a missing or incomplete one."""
    return open_complete(path, FitError, "fit store")


MATERIALS_MODEL = "mh-materials"  # the model name of the stage's map (outputs.md mh-*)
