"""The viewer's texture layout: which layers a parameter map becomes, and what the
shader can evaluate."""

from __future__ import annotations

import numpy as np

from ..conventions import (
    MH_HEAD,
    MH_KD,
    SV_ALPHA,
    SV_COAT,
    SV_KD,
    SV_KS,
    mh_dir,
    mh_ks,
    mh_lobes,
    sh_bands,
)
from ..errors import InputError
from ..stores.params import ParamMap

__all__ = ["MH_LAYERS_PER_LOBE", "MH_MAX_LOBES", "SH_MAX_BANDS", "SV_MAX_LIGHTS",
           "layer_info", "viewer_layers"]


MH_LAYERS_PER_LOBE = 2  # texture layers per lobe: (Ks, 0) then (d, 0)


def layer_info(pm: ParamMap) -> tuple[dict, int]:
    """A map's model description for the viewer and its number of texture layers
    (:func:`viewer_layers`); refuses what the shader cannot evaluate."""
    P = pm.params.shape[-1]
    if pm.model == "mh":
        K = mh_lobes(P)
        if K > MH_MAX_LOBES:
            raise InputError(f"the viewer evaluates up to {MH_MAX_LOBES} MH lobes")
        return {"model": "mh", "lobes": K}, 1 + MH_LAYERS_PER_LOBE * K
    if pm.model == "sh":
        n = sh_bands(P // 3)
        if n > SH_MAX_BANDS:
            raise InputError(f"the viewer evaluates SH up to {SH_MAX_BANDS} bands "
                             f"({SH_MAX_BANDS ** 2} coefficients)")
        return {"model": "sh", "bands": n}, P // 3
    if pm.model == "diffuse":
        return {"model": "diffuse"}, 1
    if pm.model == "svbrdf":  # (Kd, alpha), (Ks, coat); its lights for the shader
        rig = pm.lights
        # area lights: the shader draws each at its centre (their points would outnumber
        # its lights, and a light the user moves is one lamp)
        pos, weights = pm.lamps or rig[:2]
        if len(pos) > SV_MAX_LIGHTS:
            raise InputError(f"the viewer evaluates up to {SV_MAX_LIGHTS} lights")
        return {"model": "svbrdf", "lights": np.round(pos[:, :3], 4).tolist(),
                "light_weights": np.round(weights, 6).tolist(),
                "ambient": [0.0] * 3 if rig.ambient is None
                else np.round(rig.ambient, 8).tolist()}, 2
    if pm.model == "best":  # a choice map: its candidates are models of the page too
        return {"model": "best", "parts": list(pm.parts or {})}, 1
    raise InputError(f"unknown model {pm.model!r}")


def viewer_layers(pm: ParamMap) -> tuple[np.ndarray, dict]:
    """(L, T, S, 4) float32 texture layers of a map and its model description."""
    info, _ = layer_info(pm)
    T, S, P = pm.params.shape
    p = np.nan_to_num(pm.params.astype(np.float32))
    if pm.model == "mh":
        layers = [p[..., :MH_HEAD]]
        for k in range(info["lobes"]):  # MH_LAYERS_PER_LOBE layers per lobe
            z = np.zeros((T, S, 1), np.float32)
            layers += [np.concatenate([p[..., mh_ks(k)], z], -1),  # layer 1 + 2k
                       np.concatenate([p[..., mh_dir(k)], z], -1)]  # layer 2 + 2k
    elif pm.model == "sh":
        nc = P // 3
        c = p.reshape(T, S, 3, nc).transpose(3, 0, 1, 2)
        layers = list(np.concatenate([c, np.zeros((nc, T, S, 1), np.float32)], -1))
    elif pm.model == "best":
        layers = [np.concatenate([p[..., :2], np.zeros((T, S, 2), np.float32)], -1)]
    elif pm.model == "svbrdf":
        layers = [np.concatenate([p[..., SV_KD], p[..., SV_ALPHA:SV_ALPHA + 1]], -1),
                  np.concatenate([p[..., SV_KS], p[..., SV_COAT:SV_COAT + 1]], -1)]
    else:
        layers = [np.concatenate([p[..., MH_KD], np.zeros((T, S, 1), np.float32)], -1)]
    return np.stack(layers).astype("<f4"), info


SH_MAX_BANDS = 10  # the shader's loops are unrolled up to this many bands


MH_MAX_LOBES = 8

SV_MAX_LIGHTS = 4  # the shader's lights
