"""The export stage: parameter maps as OpenEXR (``params/<model>.exr``) from the fit
stores, and the diffuse-only baseline from the observation map; a relightable map as
glTF 2.0 and MaterialX for renderers (:func:`run_material`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..conventions import SVBRDF_MODEL
from ..errors import InputError
from ..models.svbrdf import card_scale, metallic_roughness
from ..stores.material import write_gltf, write_materialx
from ..stores.metrics import write_metrics
from ..stores.params import diffuse_map, param_map_from_fit, read_param_map, write_param_map
from ..stores.paths import Processed
from ..stores.radiometry import read_radiometry

logger = logging.getLogger(__name__)

__all__ = ["run_export", "run_material"]


def run_export(source: str | Path, processed: str | Path, config: dict[str, Any], *,
               models: list[str], half: bool = False) -> list[Path]:
    """The export stage: ``params/<model>.exr`` from each finished fit store
    ``fit/<model>.zarr`` of ``source``; ``diffuse`` is the mean-radiance baseline of the
    observation map. ``half``: half floats instead of float32. ``config`` holds no
    setting of this stage (one signature for every stage)."""
    src, proc = Processed(source), Processed(processed)
    paths = []
    for name in models:
        pm = (diffuse_map(src.observation) if name == "diffuse"
              else param_map_from_fit(src.fit(name)))
        paths.append(write_param_map(proc.params(name), pm, half=half))
        logger.info(f"export: {paths[-1]} ({pm.params.shape[-1]} channels, "
                    f"{'half' if half else 'float32'})")
    return paths


def _card_scale(src: Processed, pm) -> float | None:
    """The albedo's scale from the capture's white card, where its reflectance was
    stated (``camera/radiometry.json``); None otherwise."""
    path = src.radiometry
    rad = read_radiometry(path if Path(path).is_file() else None)
    rig = pm.lights
    if rad.irradiance_scale is None or rig is None:
        return None
    return card_scale(rad.irradiance_scale, pm.width_mm, pm.height_mm, rig.position_mm,
                      rig.intensity, rig.ambient)


def run_material(source: str | Path, processed: str | Path, config: dict[str, Any], *,
                 model: str = SVBRDF_MODEL) -> dict[str, Any]:
    """A relightable map for renderers: ``params/<model>.gltf`` (glTF 2.0, textured quad)
    and ``params/<model>.mtlx`` (MaterialX standard_surface) with their PNG textures,
    from ``params/<model>.exr`` in glTF's metallic-roughness terms
    (:func:`parammap.models.svbrdf.metallic_roughness`); ``metrics/material-<model>.json``
    says how the albedo's scale was set. ``config`` holds no setting of this stage."""
    src, proc = Processed(source), Processed(processed)
    pm = read_param_map(src.params(model))
    if pm.model != "svbrdf":
        raise InputError(f"{src.params(model)}: a {pm.model} map has no material for "
                         f"renderers; only {SVBRDF_MODEL} is relightable")
    mr = metallic_roughness(pm.params, pm.sd, _card_scale(src, pm))
    extras = {"model": model, "albedo_scale": mr["scale"], "scale_from": mr["scale_from"]}
    gltf = write_gltf(proc.gltf(model), mr["base_color"], mr["metallic"],
                      mr["roughness"], pm.width_mm, pm.height_mm, extras)
    mtlx = write_materialx(proc.mtlx(model), mr["base_color"], mr["metallic"],
                           mr["roughness"])
    m = {**extras, "gltf": str(gltf), "mtlx": str(mtlx),
         "metallic_median": float(np.median(mr["metallic"])),
         "roughness_median": float(np.median(mr["roughness"]))}
    write_metrics(proc.metrics(f"material-{model}"), m)
    logger.info(f"material: {gltf} and {mtlx} (albedo scale from {mr['scale_from']})")
    return m
