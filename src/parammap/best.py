"""The best-model stage: per texel, the model that its own observations support best
(004's outlook: try several models and keep the best per texel).

Every candidate map (``params/<model>.exr``: MH, SH, the basis materials, diffuse) is
judged at every texel by how well it predicts the texel's views it did not see: each
view's leave-one-view-out prediction of its fit, linearised, with the noise weights of
:func:`parammap.observation.tile_observations` (:mod:`parammap.models.selection`):

- MH: every parameter refitted (the MH fitter's own lobe choice criterion);
- the basis materials (``mh-materials``): Kd and the lobe amplitudes refitted, m, the
  colour and the directions being the material's, shared by thousands of texels;
- SH: the projection's own leave-one-out prediction, exact for a linear smoother with
  its prior and regularisation held (the projection rerun as its fit store records
  it, :func:`parammap.models.sh.fit_sh_tile` with ``loo``); the published projections
  (``sampled_cap: false``) by a plain least-squares refit of the coefficients used;
- diffuse: Kd.

``best.criterion`` says how the left-out predictions are scored, the same for every
candidate: ``display`` (default), the mean 8-bit difference after the tone map of the
held-out comparison (:func:`parammap.models.selection.display_error`, its gamma from
the observation map's 99th percentile as the comparison takes it from the photo's),
so a model is chosen for what a render of it shows; ``press``, the noise-weighted sum
of squared radiance errors, which is ruled by the views on a highlight. A model with
more freedom than the views support predicts left-out views worse, so neither needs a
parameter count.

The map's default is the candidate with the least mean error; a texel leaves it only
for a candidate its own views say is better by more than one standard error of the
difference (``best.significance``; :func:`choose`): the least of eight noisy errors is
often least by chance, and taking it cost the demo 0.3 levels on its held-out views.
An MH map whose fit found no lobe at a texel is written there as the diffuse map (the
same model, smaller). ``best.pool_radius`` > 0 adds a neighbourhood vote (worse on
every generator capture: it overrules the minority models where they are right).
The result is the map
``params/best.exr``: one channel ``choice`` indexing the candidates named in its
header (their own EXRs beside it; :func:`parammap.params.read_param_map` loads them and
:func:`parammap.render.render` draws each texel with its model), so the held-out
comparison scores it like any other map. ``metrics/best.json`` says how often each
candidate was chosen and what the map costs: the parameters stored per texel (each
texel only its own model's) against each single model.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from .conventions import FitStatus, mh_ks, mh_lobes
from .errors import InputError
from .materials import MATERIALS_MODEL
from .models.mh.uncertainty import loo_residuals
from .models.selection import loo_amplitudes, loo_diffuse, loo_sh, view_errors
from .models.sh import fit_sh_tile
from .observation import open_observation_map, tile_observations
from .params import ParamMap, read_param_map, write_param_map
from .paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["BEST_MODEL", "CRITERIA", "choose", "display_gamma", "error_table", "identical", "loo",
           "pair_index", "run_best"]

BEST_MODEL = "best"
CRITERIA = ("display", "press")


def loo(name: str, model: str, p: np.ndarray, V: np.ndarray, L: np.ndarray,
        W: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-view-out residuals (n, N, 3) of candidate ``name`` (``model``) with
    parameter rows p at texels with observations V, L, W, weights w, and (n,) bool
    where they are undefined (a view alone determines a parameter, or not fitted)."""
    if model == "diffuse":
        e, bad = loo_diffuse(np.nan_to_num(p[:, :3]), V, L, W, w)
    elif model == "sh":
        e, bad = loo_sh(p, V, L, W, w)
    elif name == MATERIALS_MODEL:  # m, colour and directions are the material's
        e, bad = loo_amplitudes(np.nan_to_num(p), V, L, W, w)
    else:
        e, bad = loo_residuals(np.nan_to_num(p), V, L, W, w)
    return e, bad | ~np.isfinite(p).all(1)


def display_gamma(obs, samples: int = 64, seed: int = 0) -> float:
    """The held-out comparison's tone-map gamma (:func:`parammap.holdout.choose_gamma`:
    the 99th percentile at 0.95) from the valid radiance of up to ``samples`` tiles of
    the observation map, at random."""
    T, S, _ = obs["valid"].shape
    tile = int(obs.attrs["tile"])
    starts = [(r, c) for r in range(0, T, tile) for c in range(0, S, tile)]
    rng = np.random.default_rng(seed)
    vals = []
    for i in rng.permutation(len(starts))[:samples]:
        r0, c0 = starts[i]
        rows, cols = slice(r0, r0 + tile), slice(c0, c0 + tile)
        _, L, W, _ = tile_observations(obs, rows, cols)
        vals.append(L[W].ravel())
    vals = np.concatenate(vals)
    return math.log(20.0) / max(float(np.percentile(vals, 99)) if vals.size else 1.0, 1e-12)


def _sh_loo(g, obs, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray] | None:
    """Exact leave-one-out residuals of an SH fit on the sampled cap (store ``g``):
    the projection rerun on the tile with ``loo`` (None for the published ones)."""
    a = dict(g.attrs)
    if not a.get("sampled_cap"):
        return None
    kw = {"noise": obs["noise"][rows, cols]} if "noise" in obs else {}
    out = fit_sh_tile(obs["radiance"][rows, cols], obs["direction"][rows, cols],
                      obs["valid"][rows, cols], int(a["bands"]), str(a["hemisphere"]),
                      a.get("regularisation") or "auto", sampled_cap=True,
                      areas=a.get("solid_angles", "spherical"), loo=True, **kw)
    e = out["loo"].reshape(-1, *out["loo"].shape[2:])
    fitted = out["status"].ravel() == FitStatus.OK
    W = np.isfinite(e).all(-1)
    bad = ~fitted | (np.isinf(e).any(-1)).any(1)
    return np.where(np.isfinite(e), e, 0.0), bad | ~W.any(1)


def _fit_store(path: Path):
    """The finished fit store at ``path``, or None when there is none."""
    from .stores import open_complete

    try:
        return open_complete(path, InputError, "fit store")
    except InputError:
        return None


def _stored(pm: ParamMap) -> int:
    """Values stored per texel of a map of this model."""
    return int(pm.params.shape[-1])


def error_table(proc: Processed, maps: dict[str, ParamMap], obs,
                criterion: str = "display") -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-view-out error of every candidate at every texel by ``criterion``
    (module docstring), row-major texels, candidates in the order of ``maps``.

    Returns
    -------
    B : (T S, J) the error (display: weighted mean over the views; press: weighted sum;
        inf where undefined or not fitted).
    SE : (T S, J (J - 1) / 2) float32 standard error of the difference ``B_a - B_b``
        for every pair a > b (:func:`pair_index`), from the spread of the per-view
        differences (how far the texel's views can tell two candidates apart; inf where
        either is undefined). Each pair once: 29 MB at 512 x 512 with eight candidates,
        where the full (J, J) table took 67 MB.
    """
    if criterion not in CRITERIA:
        raise InputError(f"best.criterion: {criterion!r} is not one of {', '.join(CRITERIA)}")
    T, S, _ = obs["valid"].shape
    J = len(maps)
    stores = {name: _fit_store(proc.fit(name)) for name, pm in maps.items()
              if pm.model == "sh"}
    for name, g in stores.items():
        if g is None or not g.attrs.get("sampled_cap"):
            logger.warning(f"best: {name} is judged by a plain least-squares refit of its "
                           f"coefficients ({proc.fit(name)}: no fit store on the sampled "
                           "cap to rerun), which overstates its error at the cap's edge")
    gamma = display_gamma(obs) if criterion == "display" else None
    tile = int(obs.attrs["tile"])
    flat_of = np.arange(T * S).reshape(T, S)
    B = np.full((T * S, J), np.inf)
    SE = np.full((T * S, J * (J - 1) // 2), np.inf, np.float32)
    for r0 in range(0, T, tile):
        for c0 in range(0, S, tile):
            rows, cols = slice(r0, min(r0 + tile, T)), slice(c0, min(c0 + tile, S))
            flat = flat_of[rows, cols].ravel()
            V, L, W, w = tile_observations(obs, rows, cols)
            E = np.empty((len(flat), J, W.shape[1]))
            for j, (name, pm) in enumerate(maps.items()):
                e = _sh_loo(stores[name], obs, rows, cols) if stores.get(name) else None
                if e is None:
                    p = pm.params.reshape(T * S, -1)[flat].astype(float)
                    e = loo(name, pm.model, p, V, L, W, w)
                E[:, j] = view_errors(e, L, W, gamma)
            B[flat], SE[flat] = _aggregate(E, W, w, criterion)
    return B, SE


def pair_index(a: int, b: int) -> int:
    """Column of the pair of candidates (a, b), a != b, in :func:`error_table`'s SE."""
    a, b = max(a, b), min(a, b)
    return a * (a - 1) // 2 + b


def _aggregate(E: np.ndarray, W: np.ndarray, w: np.ndarray,
               criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel error (n, J) and the standard error of pairwise differences
    (n, J (J - 1) / 2, :func:`pair_index`) from per-view errors E (n, J, N): the weighted
    mean (display) or sum (press) of the valid views, the standard error of that
    statistic for the differences."""
    ww = np.where(W, w, 0.0)
    sw = ww.sum(1)
    scale = np.ones(len(E)) if criterion == "display" else W.sum(1).astype(float)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        X = np.where(W[:, None], E, 0.0)
        mean = (ww[:, None] * X).sum(2) / sw[:, None]
        B = np.where(np.isfinite(mean), mean * scale[:, None], np.inf)
        # effective number of views of the weighted mean (Kish)
        neff = sw ** 2 / np.maximum((ww ** 2).sum(1), 1e-300)
        J = B.shape[1]
        se = np.full((len(B), J * (J - 1) // 2), np.inf)
        fin = np.isfinite(B)
        for a in range(J):
            for b in range(a):
                d = X[:, a] - X[:, b]
                md = (ww * d).sum(1) / sw
                vd = (ww * (d - md[:, None]) ** 2).sum(1) / sw
                v = np.sqrt(vd / np.maximum(neff - 1, 1)) * scale
                ok = fin[:, a] & fin[:, b] & np.isfinite(v)
                se[:, pair_index(a, b)] = np.where(ok, v, np.inf)
    return B, se.astype(np.float32)


def choose(B: np.ndarray, SE: np.ndarray | None, pool_radius: int,
           shape: tuple[int, int], same: np.ndarray | None = None) -> np.ndarray:
    """(T, S) index of the candidate each texel takes.

    From errors B (T S, J) and the standard errors of their differences SE
    (T S, J (J - 1) / 2, by :func:`pair_index`; :func:`error_table`):

    1. the default is the candidate with the least mean error over the map;
    2. a texel takes another only where its own views say that one is better by more
       than one standard error of the difference (with eight candidates and a few
       dozen views, the least of eight noisy errors is often least by chance, and a
       render shows the texel's true error, not its luckiest estimate); among those,
       the least error. Where the default's error is undefined (one view alone
       determines its lobe, which leaving that view out cannot judge) the texel keeps
       the default, as the MH fitter keeps such a lobe. Without SE: the least error;
    3. ``same`` (T S, J): per texel, the index of the smallest candidate identical to
       each there (an MH map whose fit found no lobe is the diffuse one), taken instead;
    4. with ``pool_radius`` > 0, the choice most texels of the (2 r + 1)^2
       neighbourhood made.
    """
    T, S = shape
    n, J = B.shape
    rows = np.arange(n)
    fin = np.isfinite(B).all(1)
    if SE is not None and fin.any():
        default = int(np.argmin(B[fin].mean(0)))
        col = np.zeros(B.shape, np.float32)
        for j in range(J):
            if j != default:
                col[:, j] = SE[:, pair_index(j, default)]
        better = B + col < B[:, [default]]
        better[:, default] = True
        own = np.argmin(np.where(better, B, np.inf), 1)
        own = np.where(np.isfinite(B[:, default]), own, default)
    else:
        own = np.argmin(B, 1)
    if same is not None:
        own = same[rows, own]
    pool = 2 * pool_radius + 1
    if pool == 1:
        return own.reshape(T, S)
    votes = np.stack([uniform_filter((own == j).reshape(T, S).astype(float), pool,
                                     mode="constant").ravel() for j in range(J)], 1)
    votes[rows, own] += 0.5 / pool**2  # a tie keeps the texel's own choice
    return np.argmax(votes, 1).reshape(T, S)


def identical(maps: dict[str, ParamMap]) -> np.ndarray:
    """(T S, J) for choose: per texel, each candidate's own index, or the diffuse
    candidate's where an MH candidate has no lobe there (the same model, smaller)."""
    names = list(maps)
    first = next(iter(maps.values()))
    n = first.shape[0] * first.shape[1]
    same = np.broadcast_to(np.arange(len(names)), (n, len(names))).copy()
    diffuse = [j for j, m in enumerate(maps.values()) if m.model == "diffuse"]
    if not diffuse:
        return same
    for j, m in enumerate(maps.values()):
        if m.model == "mh":
            P = m.params.reshape(n, -1)
            K = mh_lobes(P.shape[1])
            ks = sum(np.nan_to_num(P[:, mh_ks(k)]).sum(1) for k in range(K))
            same[(ks <= 0) & np.isfinite(P).all(1), j] = diffuse[0]
    return same


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
    criterion = config["best"].get("criterion", "display")
    B, SE = error_table(proc, maps, obs, criterion)
    stored = np.array([_stored(m) for m in maps.values()], float)
    choice = choose(B, SE if config["best"].get("significance", True) else None,
                    int(config["best"]["pool_radius"]), (T, S), identical(maps))
    any_map = next(iter(maps.values()))
    pm = ParamMap("best", choice[..., None].astype(np.float32), any_map.width_mm,
                  any_map.height_mm, attrs={"candidates": " ".join(maps)})
    write_param_map(proc.params(BEST_MODEL), pm)
    share = {name: float((choice == j).mean()) for j, name in enumerate(maps)}
    fin = np.isfinite(B).all(1)
    m = {"candidates": list(maps), "criterion": criterion,
         # the leave-one-out error of each candidate and of the map (texels where
         # every candidate is defined): the saving the choice predicts
         "loo_error_median": {name: float(np.median(B[fin, j])) if fin.any() else None
                              for j, name in enumerate(maps)}
         | {BEST_MODEL: float(np.median(B[fin, choice.ravel()[fin]])) if fin.any()
            else None},
         "chosen_fraction": share,
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
    ax.set_title("Model chosen per texel (leave-one-view-out error)", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path
