"""The best-model stage: per texel, the model that its own observations support best
(004's outlook: try several models and keep the best per texel).

Every candidate map (``params/<model>.exr``: MH, SH, the basis materials, diffuse) is
judged at every texel by how well it predicts the texel's views it did not see: each
view's leave-one-view-out prediction of its fit, linearised, with the noise weights of
:func:`parammap.stages.observation.tile_observations` (:mod:`parammap.models.selection`):

- MH: every parameter refitted (the MH fitter's own lobe choice criterion);
- the basis materials (``mh-materials``): Kd, the lobe amplitudes and directions (the
  texel's own, from the source fit) refitted, m and the colour being the material's,
  shared by thousands of texels;
- SH: the projection's own leave-one-out prediction, exact for a linear smoother with
  its prior and regularisation held (the projection rerun as its fit store records
  it, :func:`parammap.models.sh.fit_sh_tile` with ``loo``, its coefficients read from
  the store a tile at a time rather than held whole); the published projections
  (``sampled_cap: false``) by a plain least-squares refit of the coefficients used;
- diffuse: Kd.

Every candidate is judged on the same views of a texel: those on which no candidate's
fit leans, a view whose left-out residual is more than twice its in-sample one
(leverage above one half, :func:`parammap.models.selection.influential`) being left
out of the comparison. Leaving out such a view measures what a fit loses without it (a
lobe that only that view saw), not how the fit predicts a new direction, and it
penalises the models that resolve each texel against the smoother ones (on the demo,
0.2 % of the views decided for the basis materials over mh-auto, which predicts new
directions better).

``best.criterion`` says how the left-out predictions are scored, the same for every
candidate: ``display`` (default), the mean 8-bit difference after the tone map of the
held-out comparison (:func:`parammap.models.selection.display_error`, its gamma from
the observation map's 99th percentile as the comparison takes it from the photo's),
so a model is chosen for what a render of it shows; ``press``, the noise-weighted sum
of squared radiance errors, which is ruled by the views on a highlight. A model with
more freedom than the views support predicts left-out views worse, so neither needs a
parameter count.

With ``best.blend`` (default) a texel's candidates are every model alone and the mean
of every two (stacking, Wolpert 1992 / Breiman 1996, with weights of one half): the
left-out prediction of the mean of two fits is the mean of their left-out predictions,
so it is judged exactly like a model. Where neither model is the true one their errors
partly cancel: on a physically based capture with two area lights, MH overshoots the
highlights that SH smooths, and their mean beat both on every held-out view.

The map's default is the candidate with the least mean error (over a sample of up to 16
tiles); a texel leaves it only for a candidate its own views say is better by more than
z standard errors of the difference (``best.significance``; :func:`choose`), z the
one-sided tail of one standard error shared among the other candidates
(:func:`significance_z`, Bonferroni): the least of many noisy errors is often least by
chance, and a render shows the texel's true error, not its luckiest estimate.
An MH map whose fit found no lobe at a texel stores only Kd there (counted as three
values; it is not swapped for the diffuse baseline, whose plain mean differs from the
fit's noise-weighted one). ``best.pool_radius`` > 0 adds a neighbourhood vote (worse on
every generator capture: it overrules the minority models where they are right).
The result is the map ``params/best.exr``: channels ``choice`` and ``partner``
indexing the candidates named in its header (their own EXRs beside it; equal where a
texel has one model; :func:`parammap.stores.params.read_param_map` loads them and
:func:`parammap.render.render` draws each texel as the mean of its two, and interpolates
between texels as for any map), so the held-out comparison scores it like any other
map. ``metrics/best.json`` says how often each choice was taken and what the map costs:
the parameters stored per texel (each texel only its own models') against each single
model.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.stats import norm

from ..config import default
from ..conventions import SH_BAKED, FitArray, FitStatus, mh_ks, mh_lobes
from ..errors import InputError
from ..geometry import texel_centres
from ..models.mh.uncertainty import loo_residuals
from ..models.selection import (
    influential,
    loo_amplitudes,
    loo_diffuse,
    loo_sh,
    loo_svbrdf,
    predict,
    view_errors,
)
from ..models.sh import fit_sh_tile
from ..parallel import map_shared, progress
from ..stores.fit import MATERIALS_MODEL, open_fit
from ..stores.metrics import write_metrics
from ..stores.observation import open_observation_map, tile_observations
from ..stores.params import ParamMap, read_param_map, write_param_map
from ..stores.paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["BEST_MODEL", "CRITERIA", "candidates", "choose", "error_table",
           "loo", "resolve", "run_best", "significance_z", "tile_errors",
           "values_stored"]

BEST_MODEL = "best"
CRITERIA = ("display", "press")
#: tiles of the sample that picks the default candidate
DEFAULT_SAMPLE_TILES = 16
#: most bytes of per-view errors a map no bigger than the sample keeps for the full pass
KEEP_BYTES = 512 * 2 ** 20
#: one-sided tail of one standard error of a normal difference
ONE_SE_TAIL = float(norm.sf(1.0))


def loo(name: str, model: str, p: np.ndarray, V: np.ndarray, L: np.ndarray,
        W: np.ndarray, w: np.ndarray, points: np.ndarray | None = None,
        lights: tuple[np.ndarray, np.ndarray] | None = None,
        ) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-view-out residuals (n, N, 3) of candidate ``name`` (``model``) with
    parameter rows p at texels with observations V, L, W, weights w, and (n,) bool
    where they are undefined (a view alone determines a parameter, or not fitted); an
    svbrdf map at its texels' centres ``points`` (n, 3) under its ``lights``."""
    if model == "svbrdf":
        e, bad = loo_svbrdf(p, V, L, W, w, points, lights)
    elif model == "diffuse":
        e, bad = loo_diffuse(np.nan_to_num(p[:, :3]), V, L, W, w)
    elif model == "sh":
        e, bad = loo_sh(p, V, L, W, w)
    elif name == MATERIALS_MODEL:  # m, colour and directions are the material's
        e, bad = loo_amplitudes(np.nan_to_num(p), V, L, W, w)
    else:
        e, bad = loo_residuals(np.nan_to_num(p), V, L, W, w)
    return e, bad | ~np.isfinite(p).all(1)


def candidates(J: int, blend: bool = default("best.blend")) -> list[tuple[int, int]]:
    """The choices a texel has among J models: each alone, ``(j, j)``, then with
    ``blend`` the mean of every two, ``(a, b)`` with a < b."""
    return [(j, j) for j in range(J)] + ([(a, b) for a in range(J) for b in range(a + 1, J)]
                                         if blend else [])


def significance_z(n_candidates: int) -> float:
    """How many standard errors better than the default a texel's own views must find
    another candidate: one standard error's one-sided tail (15.9 %) shared among the
    ``n_candidates - 1`` others (Bonferroni), so that the chance that noise alone moves a
    texel stays that of one comparison at one standard error however many there are."""
    return float(norm.isf(ONE_SE_TAIL / max(n_candidates - 1, 1)))


def _sh_loo(g, obs, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray] | None:
    """Exact leave-one-out residuals of an SH fit on the sampled cap (store ``g``):
    the projection rerun on the tile with ``loo`` (None for the published ones)."""
    if not g.sampled_cap:
        return None
    kw = {"noise": obs.noise[rows, cols]} if obs.noise is not None else {}
    out = fit_sh_tile(obs.radiance[rows, cols], obs.direction[rows, cols],
                      obs.valid[rows, cols], int(g.n_bands), str(g.hemisphere),
                      g.regularisation or "auto", sampled_cap=True, areas=g.solid_angles,
                      loo=True, shrink=g.shrink, robust=g.robust,
                      display_gamma=g.display_gamma, **kw)
    e = out[FitArray.LOO].reshape(-1, *out[FitArray.LOO].shape[2:])
    fitted = out[FitArray.STATUS].ravel() == FitStatus.OK
    W = np.isfinite(e).all(-1)
    bad = ~fitted | (np.isinf(e).any(-1)).any(1)
    return np.where(np.isfinite(e), e, 0.0), bad | ~W.any(1)


def _fit_store(path: Path):
    """The finished fit store at ``path``, or None when there is none."""
    try:
        return open_fit(path)
    except InputError:
        return None


def _stored(pm: ParamMap) -> int:
    """Values stored per texel of a map of this model."""
    return int(pm.params.shape[-1])


def error_table(proc: Processed, maps: dict[str, ParamMap], obs,
                criterion: str = default("best.criterion"), cands: list[tuple[int,
                                                                              int]] | None = None,
                default: int | None = None,
                tiles: list[tuple[slice, slice]] | None = None,
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """Leave-one-view-out error of every candidate at every texel by ``criterion``
    (module docstring), row-major texels.

    ``cands``: the candidates, pairs of indices into ``maps`` (:func:`candidates`; default
    each model alone); a pair's left-out prediction is the mean of its two models' (the
    left-out prediction of the mean of two fits, exactly). ``tiles``: only these tiles
    (default all; the other texels inf).

    Returns
    -------
    B : (T S, C) float32 the error (display: weighted mean over the views; press:
        weighted sum; inf where undefined or not fitted).
    SE : (T S, C) float32 standard error of the difference ``B_c - B_default`` from the
        spread of the per-view differences (how far the texel's views can tell the two
        apart; inf where either is undefined, 0 for the default itself); None without
        ``default``.
    """
    T, S, _ = obs.shape
    cands = cands or candidates(len(maps), blend=False)
    B = np.full((T * S, len(cands)), np.inf, np.float32)
    SE = None if default is None else np.full(B.shape, np.inf, np.float32)
    for flat, b, se in tile_errors(proc, maps, obs, criterion, cands, default, tiles):
        B[flat] = b
        if SE is not None:
            SE[flat] = se
    return B, SE


def tile_errors(proc: Processed, maps: dict[str, ParamMap], obs, criterion: str,
                cands: list[tuple[int, int]], default: int | None = None,
                tiles: list[tuple[slice, slice]] | None = None, workers: int = 1,
                keep: bool = False):
    """:func:`error_table` a tile at a time: yields (row-major texel indices (n,), B
    (n, C), SE (n, C) or None), so that a big map's stage holds one tile's table;
    ``workers`` processes share the tiles (each inherits ``maps``). With ``keep``,
    each also carries the tile's per-view errors (:func:`_view_errors`) to aggregate
    again with another default."""
    if criterion not in CRITERIA:
        raise InputError(f"best.criterion: {criterion!r} is not one of {', '.join(CRITERIA)}")
    stores = {name: _fit_store(proc.fit(name)) for name, pm in maps.items()
              if pm.model == "sh"}
    for name, g in stores.items():
        if g is None or not g.sampled_cap:
            logger.warning(f"best: {name} is judged by a plain least-squares refit of its "
                           f"coefficients ({proc.fit(name)}: no fit store on the sampled "
                           "cap to rerun), which overstates its error at the cap's edge")
    gamma = obs.display_gamma() if criterion == "display" else None
    shared = (maps, obs, stores, gamma, criterion, cands, default, keep)
    yield from map_shared(_tile_job, tiles or obs.tiles(), workers, shared)


def _tile_job(shared: tuple, tile: tuple[slice, slice]) -> tuple:
    """One tile of :func:`tile_errors` (a worker's job)."""
    maps, obs, stores, gamma, criterion, cands, default, keep = shared
    flat, E, Wc, w = _view_errors(maps, obs, stores, gamma, cands, *tile)
    b, se = _aggregate(E, Wc, w, criterion, default)
    return (flat, b.astype(np.float32), None if se is None else se.astype(np.float32)) \
        + ((E, Wc, w) if keep else ())


def _view_errors(maps: dict[str, ParamMap], obs, stores: dict, gamma: float | None,
                 cands: list[tuple[int, int]], rows: slice, cols: slice,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Row-major texel indices (n,) of a tile, each candidate's left-out error at each
    of their views E (n, C, N) float32, the views judged Wc (n, N) and their weights w
    (n, N)."""
    T, S, _ = obs.shape
    flat = (np.arange(T)[rows, None] * S + np.arange(S)[None, cols]).ravel()
    V, L, W, w = tile_observations(obs, rows, cols)
    pts = texel_centres(S, T, obs.width_mm, obs.height_mm, np.arange(T)[rows],
                        np.arange(S)[cols]).reshape(-1, 3)
    res = []
    swayed = np.zeros(W.shape, bool)
    for name, pm in maps.items():
        g = stores.get(name)
        e = _sh_loo(g, obs, rows, cols) if g else None
        if e is not None:  # the map's coefficients are its fit store's
            p = np.asarray(g[FitArray.COEFFS][rows, cols], float).reshape(len(flat), -1)
        else:
            p = pm.params.reshape(T * S, -1)[flat].astype(float)
            e = loo(name, pm.model, p, V, L, W, w, pts, pm.lights)
        r = np.where(W[..., None], predict(pm.model, p, V, pts, pm.lights) - L, 0.0)
        swayed |= influential(e[0], r, W) & ~e[1][:, None]
        res.append(e)
    # every candidate is judged on the same views: those no fit leans on (module
    # docstring)
    Wc = W & ~swayed
    E = np.empty((len(flat), len(cands), W.shape[1]), np.float32)
    for c, (a, b) in enumerate(cands):
        e = res[a] if a == b else (0.5 * (res[a][0] + res[b][0]), res[a][1] | res[b][1])
        E[:, c] = view_errors(e, L, Wc, gamma)
    return flat, E, Wc, w


def _reaggregate(kept: tuple, criterion: str, default: int) -> tuple:
    """A tile of :func:`tile_errors` run with ``keep``, as it would be with ``default``."""
    flat, b, _, E, Wc, w = kept
    return flat, b, _aggregate(E, Wc, w, criterion, default)[1].astype(np.float32)


def _aggregate(E: np.ndarray, W: np.ndarray, w: np.ndarray, criterion: str,
               default: int | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-texel error (n, C) from per-view errors E (n, C, N): the weighted mean
    (display) or sum (press) of the valid views; with ``default``, the standard error
    (n, C) of that statistic for each candidate's difference from the default."""
    ww = np.where(W, w, 0.0)
    sw = ww.sum(1)
    scale = np.ones(len(E)) if criterion == "display" else W.sum(1).astype(float)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        X = np.where(W[:, None], E, 0.0)
        mean = (ww[:, None] * X).sum(2) / sw[:, None]
        B = np.where(np.isfinite(mean), mean * scale[:, None], np.inf)
        if default is None:
            return B, None
        # effective number of views of the weighted mean (Kish)
        neff = sw ** 2 / np.maximum((ww ** 2).sum(1), 1e-300)
        d = X - X[:, default:default + 1]
        md = (ww[:, None] * d).sum(2) / sw[:, None]
        vd = (ww[:, None] * (d - md[..., None]) ** 2).sum(2) / sw[:, None]
        v = np.sqrt(vd / np.maximum(neff - 1, 1)[:, None]) * scale[:, None]
    ok = np.isfinite(B) & np.isfinite(B[:, default:default + 1]) & np.isfinite(v)
    se = np.where(ok, v, np.inf)
    se[:, default] = 0.0
    return B, se


def choose(B: np.ndarray, SE: np.ndarray | None, default: int, pool_radius: int,
           shape: tuple[int, int], z: float = 1.0) -> np.ndarray:
    """(T, S) index of the candidate each texel takes.

    From errors B (T S, C) and the standard errors SE (T S, C) of their differences
    from the candidate ``default`` (:func:`error_table`):

    1. the default is the candidate with the least mean error over the map;
    2. a texel takes another only where its own views say that one is better by more
       than ``z`` standard errors of the difference (:func:`significance_z`: the least
       of many noisy errors is often least by chance, and a render shows the texel's
       true error, not its luckiest estimate); among those, the least error. Where the
       default's error is undefined (one view alone determines its lobe, which leaving
       that view out cannot judge) the texel keeps the default, as the MH fitter keeps
       such a lobe. Without SE: the least error;
    3. with ``pool_radius`` > 0, the choice most texels of the (2 r + 1)^2
       neighbourhood made.
    """
    return _pool(_own_choice(B, SE, default, z), B.shape[1], pool_radius, shape)


def _own_choice(B: np.ndarray, SE: np.ndarray | None, default: int, z: float) -> np.ndarray:
    """(n,) each texel's own choice (:func:`choose`, steps 1-2)."""
    if SE is None:
        return np.argmin(B, 1)
    better = B + z * SE < B[:, [default]]
    better[:, default] = True
    own = np.argmin(np.where(better, B, np.inf), 1)
    return np.where(np.isfinite(B[:, default]), own, default)


def _pool(own: np.ndarray, C: int, pool_radius: int, shape: tuple[int, int]) -> np.ndarray:
    """(T, S) the choice most texels of each (2 r + 1)^2 neighbourhood made."""
    T, S = shape
    pool = 2 * pool_radius + 1
    if pool == 1:
        return own.reshape(T, S)
    votes = np.stack([uniform_filter((own == j).reshape(T, S).astype(float), pool,
                                     mode="constant").ravel() for j in range(C)], 1)
    votes[np.arange(len(own)), own] += 0.5 / pool**2  # a tie keeps the texel's own choice
    return np.argmax(votes, 1).reshape(T, S)


def resolve(cands: list[tuple[int, int]], chosen: np.ndarray,
            same: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The two models, ``choice`` <= ``partner`` (equal for one model), of the chosen
    candidates (T, S); ``same`` (T S, J) per texel a model to take instead of each
    (default: each itself)."""
    ab = np.asarray(cands)[chosen.ravel()]
    if same is not None:
        rows = np.arange(len(ab))
        ab = np.stack([same[rows, ab[:, 0]], same[rows, ab[:, 1]]], 1)
    return ab.min(1).reshape(chosen.shape), ab.max(1).reshape(chosen.shape)


def values_stored(maps: dict[str, ParamMap]) -> np.ndarray:
    """(T S, J) values each candidate map stores per texel: its channels, or Kd's three
    where an MH map has no lobe (a diffuse texel, whichever map it is read from: the
    MH fit's Kd, noise-weighted, is kept rather than the diffuse baseline's plain mean,
    which a render would show)."""
    first = next(iter(maps.values()))
    n = first.shape[0] * first.shape[1]
    out = np.empty((n, len(maps)))
    for j, m in enumerate(maps.values()):
        out[:, j] = m.params.shape[-1]
        if m.model == "mh":
            out[~_has_lobe(m.params.reshape(n, -1)), j] = 3
    return out


def _has_lobe(P: np.ndarray) -> np.ndarray:
    """(n,) bool: MH parameter rows (n, 4 + 6K) with a lobe (NaN rows: not fitted, True)."""
    K = mh_lobes(P.shape[1])
    ks = sum(np.nan_to_num(P[:, mh_ks(k)]).sum(1) for k in range(K))
    return (ks > 0) | ~np.isfinite(P).all(1)


def _label(names: list[str], a: int, b: int) -> str:
    return names[a] if a == b else f"{names[a]}+{names[b]}"


def run_best(source: str | Path, processed: str | Path, config: dict[str, Any], *,
             models: list[str], figures: str | Path | None = None,
             workers: int | None = None) -> dict[str, Any]:
    """The best-model stage (module docstring) over the exported maps of ``models``;
    ``config`` the validated workflow config (section ``best``; ``workers`` processes
    unless given). Returns what ``metrics/best.json`` holds."""
    workers = workers or config["workers"]
    if len(models) < 2:
        raise InputError(f"best: needs at least two candidate models (got {models})")
    src, proc = Processed(source), Processed(processed)
    maps = {}
    for name in models:
        if not src.params(name).is_file():
            raise InputError(f"best: {src.params(name)} is missing (export {name} first)")
        # without their sds: nine maps of a 1.1-million-texel lab map held 3.6 GB
        pm = read_param_map(src.params(name), with_sd=False)
        if pm.model == "best":
            raise InputError(f"best: {name} is itself a best map")
        if pm.model == "sh" and pm.hemisphere in SH_BAKED:
            # its views' errors are its MH source's, re-encoded: not a choice of its own
            logger.info(f"best: {name} is baked from an MH fit; left out")
            continue
        g = _fit_store(src.fit(name)) if pm.model == "sh" else None
        if g is not None and g.sampled_cap \
                and tuple(g[FitArray.COEFFS].shape) == pm.params.shape:
            # judged tile by tile from its fit store, which holds its coefficients: not
            # held whole (a lab map's three SH maps are 1.2 GB of its nine's 1.6)
            pm = replace(pm, params=np.broadcast_to(np.float32(np.nan), pm.params.shape))
        maps[name] = pm
    if len(maps) < 2:
        raise InputError(f"best: needs at least two candidate models (got {list(maps)})")
    obs = open_observation_map(src.observation)
    T, S, N = obs.shape
    for name, pm in maps.items():
        if pm.shape != (T, S):
            raise InputError(f"best: {name} is {pm.shape[1]}x{pm.shape[0]} texels, the "
                             f"observation map {S}x{T}")
    cfg = config["best"]
    criterion = cfg["criterion"]
    names = list(maps)
    cands = candidates(len(maps), cfg["blend"])
    labels = [_label(names, a, b) for a, b in cands]
    # the default from a sample of tiles (16 x 1024 texels pin the map's mean), so that
    # the full pass keeps each candidate's difference from it alone
    sample = obs.sample_tiles(DEFAULT_SAMPLE_TILES)
    tiles = obs.tiles()
    # a map no bigger than the sample: its per-view errors are kept, not computed again
    keep = len(sample) == len(tiles) and T * S * len(cands) * N * 4 <= KEEP_BYTES
    first = list(tile_errors(src, maps, obs, criterion, cands, tiles=sample,
                             workers=workers, keep=keep))
    B0 = np.concatenate([t[1] for t in first])
    fin0 = np.isfinite(B0).all(1)
    default = int(np.argmin(B0[fin0].mean(0))) if fin0.any() else 0
    logger.info(f"best: default {labels[default]} (least mean leave-one-out error of "
                f"{len(cands)} candidates over {int(fin0.sum())} sampled texels)")
    significance = cfg.get("significance", True)
    z = significance_z(len(cands)) if significance else None
    # a tile at a time: each texel's own choice, its error and each model's alone
    own = np.zeros(T * S, np.int64)
    B = np.full((T * S, len(maps) + 1), np.inf, np.float32)
    done = (_reaggregate(t, criterion, default) for t in first) if keep else \
        tile_errors(src, maps, obs, criterion, cands, default, workers=workers)
    for flat, b, se in progress(done, len(tiles), "best: tiles", logger):
        own[flat] = _own_choice(b, se if significance else None, default, z or 1.0)
        B[flat, :-1] = b[:, :len(maps)]
        B[flat, -1] = b[np.arange(len(flat)), own[flat]]
    chosen = _pool(own, len(cands), int(cfg["pool_radius"]), (T, S))
    choice, partner = resolve(cands, chosen)
    any_map = next(iter(maps.values()))
    pm = ParamMap("best", np.stack([choice, partner], -1).astype(np.float32),
                  any_map.width_mm, any_map.height_mm,
                  attrs={"candidates": " ".join(maps), **any_map.radiometry})
    write_param_map(proc.params(BEST_MODEL), pm)
    stored = np.array([_stored(m) for m in maps.values()], float)
    per = values_stored(maps)
    rows = np.arange(T * S)
    c, p = choice.ravel(), partner.ravel()
    kept = [_label(names, a, b) for a, b in zip(c, p, strict=True)]
    flat = (per[rows, c] == 3) & (per[rows, p] == 3)
    tally = dict(zip(*np.unique(kept, return_counts=True), strict=True))
    share = {k: float(v / (T * S)) for k, v in sorted(tally.items(), key=lambda kv: -kv[1])}
    fin = np.isfinite(B).all(1)
    m = {"candidates": names, "criterion": criterion, "default": labels[default],
         "blend": bool(cfg.get("blend", True)), "significance_z": z,
         # the leave-one-out error of each model alone and of the map (texels where
         # every candidate is defined): the saving the choice predicts
         "loo_error_median": {name: float(np.median(B[fin, j])) if fin.any() else None
                              for j, name in enumerate(names)}
         | {BEST_MODEL: float(np.median(B[fin, -1])) if fin.any() else None},
         "chosen_fraction": share,
         # texels drawn without a lobe (diffuse, or an MH fit that found none; the mean
         # of two such is one Kd)
         "diffuse_fraction": float(flat.mean()),
         "values_per_texel": float(np.where(flat, 3, per[rows, c] + np.where(
             c != p, per[rows, p], 0)).mean()),
         "values_per_texel_single": {name: int(s) for name, s in zip(maps, stored,
                                                                        strict=True)}}
    write_metrics(proc.metrics(BEST_MODEL), m)
    logger.info("best: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in share.items())
                + f" of the texels; {m['values_per_texel']:.1f} values per texel")
    if figures:
        _figure(Path(figures) / "best_choice.png", kept, (T, S), share)
    return m


def _figure(path: Path, kept: list[str], shape: tuple[int, int], share: dict,
            shown: int = 9) -> Path:
    """The choice map: the ``shown`` most frequent choices, the rest as one colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    top = list(share)[:shown]
    cats = top + (["other"] if len(share) > shown else [])
    index = {k: i for i, k in enumerate(top)}
    img = np.array([index.get(k, len(top)) for k in kept]).reshape(shape)
    frac = {k: share[k] for k in top} | {"other": 1 - sum(share[k] for k in top)}
    cmap = ListedColormap(plt.get_cmap("tab10").colors[:len(cats)])
    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    im = ax.imshow(img, cmap=cmap, vmin=-0.5, vmax=len(cats) - 0.5, interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, ticks=range(len(cats)))
    cb.ax.set_yticklabels([f"{n} ({100 * frac[n]:.0f} %)" for n in cats], fontsize=7)
    ax.set_title("Model chosen per texel (leave-one-view-out error; a+b: their mean)",
                 fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path
