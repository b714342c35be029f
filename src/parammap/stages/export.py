"""The export stage: parameter maps as OpenEXR (``params/<model>.exr``) from the fit
stores, and the diffuse-only baseline from the observation map."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from ..stores.params import diffuse_map, param_map_from_fit, write_param_map
from ..stores.paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["run_export"]


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
