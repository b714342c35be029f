"""The best-model stage: per texel, the model that its own observations support best
(004's outlook: try several models and keep the best per texel).

Every candidate map (``params/<model>.exr``: MH, SH, the basis materials, diffuse) is
judged at every texel by how well it predicts the texel's views it did not see: the
leave-one-view-out error (PRESS) of its fit, linearised, with the noise weights of
:func:`parammap.observation.tile_observations` (:mod:`parammap.models.selection`):

- MH: every parameter refitted (the MH fitter's own lobe choice criterion);
- the basis materials (``mh-materials``): Kd and the lobe amplitudes refitted, m, the
  colour and the directions being the material's, shared by thousands of texels;
- SH: the coefficients the texel uses (the bands its views resolve); diffuse: Kd.

A model with more freedom than the views support predicts left-out views worse, so
the criterion needs no parameter count.

Each texel then takes the choice most texels of its 3x3 neighbourhood made (a vote:
one texel's evidence is noisy, and models change in regions). The result is the map
``params/best.exr``: one channel ``choice`` indexing the candidates named in its
header (their own EXRs beside it; :func:`parammap.params.read_param_map` loads them and
:func:`parammap.render.render` draws each texel with its model), so the held-out
comparison scores it like any other map. ``metrics/best.json`` says how often each
candidate was chosen and what the map costs: the parameters stored per texel (each
texel only its own model's) against each single model.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from .errors import InputError
from .materials import MATERIALS_MODEL
from .models.mh.uncertainty import loo_error
from .models.selection import press_amplitudes, press_diffuse, press_sh
from .observation import open_observation_map, tile_observations
from .params import ParamMap, read_param_map, write_param_map
from .paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["BEST_MODEL", "press", "run_best"]

BEST_MODEL = "best"


def press(name: str, model: str, p: np.ndarray, V: np.ndarray, L: np.ndarray,
          W: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n,) leave-one-view-out error of candidate ``name`` (``model``) with parameter
    rows p at texels with observations V, L, W, weights w (inf where not fitted)."""
    if model == "diffuse":
        out = press_diffuse(np.nan_to_num(p[:, :3]), V, L, W, w)
    elif model == "sh":
        out = press_sh(p, V, L, W, w)
    elif name == MATERIALS_MODEL:  # m, colour and directions are the material's
        out = press_amplitudes(np.nan_to_num(p), V, L, W, w)
    else:
        out = loo_error(np.nan_to_num(p), V, L, W, w)
    return np.where(np.isfinite(p).all(1), out, np.inf)


def _stored(pm: ParamMap) -> int:
    """Values stored per texel of a map of this model."""
    return int(pm.params.shape[-1])


def run_best(processed: str | Path, models: list[str], config: dict[str, Any],
             figures: str | Path | None = None) -> dict[str, Any]:
    """The best-model stage (module docstring) over the exported maps of ``models``;
    ``config`` the validated workflow config (section ``best``). Returns what
    ``metrics/best.json`` holds."""
    from .metrics import write_metrics

    if len(models) < 2:
        raise InputError(f"best: needs at least two candidate models (got {models})")
    proc = Processed(processed)
    maps = {}
    for name in models:
        if not proc.params(name).is_file():
            raise InputError(f"best: {proc.params(name)} is missing (export {name} first)")
        maps[name] = read_param_map(proc.params(name))
        if maps[name].model == "best":
            raise InputError(f"best: {name} is itself a best map")
    obs = open_observation_map(proc.observation)
    T, S, N = obs["valid"].shape
    for name, pm in maps.items():
        if pm.shape != (T, S):
            raise InputError(f"best: {name} is {pm.shape[1]}x{pm.shape[0]} texels, the "
                             f"observation map {S}x{T}")
    tile = int(obs.attrs["tile"])
    flat_of = np.arange(T * S).reshape(T, S)
    B = np.full((T * S, len(maps)), np.inf)  # leave-one-view-out error (PRESS)
    for r0 in range(0, T, tile):
        for c0 in range(0, S, tile):
            rows, cols = slice(r0, min(r0 + tile, T)), slice(c0, min(c0 + tile, S))
            flat = flat_of[rows, cols].ravel()
            V, L, W, w = tile_observations(obs, rows, cols)
            for j, (name, pm) in enumerate(maps.items()):
                p = pm.params.reshape(T * S, -1)[flat].astype(float)
                B[flat, j] = press(name, pm.model, p, V, L, W, w)
    own = np.argmin(B, 1)
    pool = 2 * int(config["best"]["pool_radius"]) + 1
    votes = np.stack([uniform_filter((own == j).reshape(T, S).astype(float), pool,
                                     mode="constant").ravel() for j in range(len(maps))], 1)
    votes[np.arange(T * S), own] += 0.5 / pool**2  # a tie keeps the texel's own choice
    choice = np.argmax(votes, 1).reshape(T, S)
    any_map = next(iter(maps.values()))
    pm = ParamMap("best", choice[..., None].astype(np.float32), any_map.width_mm,
                  any_map.height_mm, attrs={"candidates": " ".join(maps)})
    write_param_map(proc.params(BEST_MODEL), pm)
    share = {name: float((choice == j).mean()) for j, name in enumerate(maps)}
    stored = np.array([_stored(m) for m in maps.values()], float)
    m = {"candidates": list(maps), "chosen_fraction": share,
         "values_per_texel": float(stored[choice].mean()),
         "values_per_texel_single": {name: int(s) for name, s in zip(maps, stored,
                                                                        strict=True)}}
    write_metrics(proc.metrics(BEST_MODEL), m)
    logger.info("best: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in share.items())
                + f" of the texels; {m['values_per_texel']:.1f} values per texel")
    if figures:
        _figure(Path(figures) / "best_choice.png", choice, list(maps), share)
    return m


def _figure(path: Path, choice: np.ndarray, names: list[str], share: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(plt.get_cmap("tab10").colors[:len(names)])
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    im = ax.imshow(choice, cmap=cmap, vmin=-0.5, vmax=len(names) - 0.5,
                   interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, ticks=range(len(names)))
    cb.ax.set_yticklabels([f"{n} ({100 * share[n]:.0f} %)" for n in names], fontsize=7)
    ax.set_title("Model chosen per texel (leave-one-view-out error, 3x3 vote)", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path
