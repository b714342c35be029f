"""The materials stage: a few basis materials for the whole surface (003), as an MH map.

From a finished MH fit (``materials.source``, default ``mh-auto``) and the observation
map, :mod:`parammap.models.materials` clusters the texels into basis materials, refits
each material's shininess and specular colour from all its texels' observations and
gives every texel the material (or none: diffuse only) that explains its data best.
Writes ``fit/mh-materials.zarr``: an MH fit store (``params``, ``rmse``, ``mpr``,
``status`` ... as every MH fit, so export, held-out comparison, figures and viewer
read it unchanged) plus ``label`` (T, S) (0: diffuse only, j: basis material j) and
``weights`` (T, S, 1 + M) (the BIC weight of each candidate), with the materials in
the store's ``materials`` attribute; and ``metrics/fit-mh-materials.json``.

The map is read tile by tile (one tile of the observation map at a time per worker
process), so memory is bounded by the tile and the per-material samples, not the map.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import distance_transform_edt, uniform_filter

from ..conventions import MH_M, FitArray, FitStatus, mh_dir, mh_ks, mh_lobes, mh_size
from ..models.materials import (
    adjusted_rand_index,
    assign_materials,
    choose_count,
    cluster_materials,
    fit_basis,
    material_features,
    material_params,
)
from ..models.mh.model import mh_eval
from ..models.residuals import mean_percentage_residual
from ..parallel import map_shared, progress
from ..stores.fit import (
    MATERIALS_MODEL,
    grid_attrs,
    mh_attrs,
    open_mh_source,
    write_fit_store,
)
from ..stores.metrics import write_metrics
from ..stores.observation import ObservationMap, sample_texel_observations, tile_observations
from ..stores.paths import Processed

logger = logging.getLogger(__name__)

__all__ = ["MATERIALS_MODEL", "adjusted_rand_index", "run_materials"]

CLUSTER_SAMPLE = 20000  # texels clustered at most (k-means and silhouettes need no more)


def _flat(obs: ObservationMap, rows: slice, cols: slice) -> np.ndarray:
    """Row-major texel indices (n,) of a tile."""
    return (np.arange(obs.T)[rows, None] * obs.S + np.arange(obs.S)[None, cols]).ravel()


def _bic_job(shared: tuple, tile: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
    """A tile's BIC of every candidate (:func:`assign_materials`; a worker's job)."""
    obs, Pb, basis = shared
    flat = _flat(obs, *tile)
    V, L, W, w = tile_observations(obs, *tile)
    return flat, assign_materials(*_lobes(Pb[flat]), V, L, W, w, basis)["bic"]


def _assign_job(shared: tuple, tile: tuple[slice, slice]) -> tuple:
    """A tile's weights and MH rows under the labels (a worker's job)."""
    obs, Pb, basis, label = shared
    flat = _flat(obs, *tile)
    V, L, W, w = tile_observations(obs, *tile)
    dirs, present = _lobes(Pb[flat])
    a = assign_materials(dirs, present, V, L, W, w, basis, label[flat])
    return flat, a[FitArray.WEIGHTS], material_params(a["kd"], a["s"], a[FitArray.LABEL],
                                                      dirs, basis)


def _residual_job(shared: tuple, tile: tuple[slice, slice]) -> tuple:
    """A tile's RMSE and mean percentage residual of the MH rows (a worker's job)."""
    obs, params = shared
    flat = _flat(obs, *tile)
    V, L, W, _ = tile_observations(obs, *tile)
    pred = mh_eval(params[flat], V)
    n = np.maximum(W.sum(1), 1)[:, None]
    return (flat, np.sqrt((np.where(W[..., None], pred - L, 0) ** 2).sum(1) / n),
            mean_percentage_residual(L, pred, W))


def _lobes(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lobe directions (n, K, 3) and presence (n, K) of MH rows."""
    K = mh_lobes(P.shape[1])
    dirs = np.stack([P[:, mh_dir(k)] for k in range(K)], 1)
    present = np.stack([P[:, mh_ks(k)].sum(1) > 0 for k in range(K)], 1)
    return np.nan_to_num(dirs), present & np.isfinite(P).all(1)[:, None]


def _borrowed(P: np.ndarray, ok: np.ndarray, T: int, S: int) -> np.ndarray:
    """Source rows P (T S, 4 + 6K) in which a texel without a lobe takes the lobes of
    the nearest texel that has one: a lobe is the mirror image of a light, which moves
    slowly across the surface, so a texel whose own fit missed its highlight (a poor
    minimum, a highlight few views saw) is still judged with the lobes it should have."""
    _, present = _lobes(P)
    has = (present.any(1) & ok).reshape(T, S)
    if not has.any() or has.all():
        return P
    _, (ri, ci) = distance_transform_edt(~has, return_indices=True)
    near = (ri * S + ci).ravel()
    out = P.copy()
    lack = ~has.ravel()
    out[lack, 4:] = P[near[lack], 4:]
    out[lack, MH_M] = P[near[lack], MH_M]
    return out


def _region_cores(lobed: np.ndarray, T: int, S: int) -> np.ndarray:
    """Flat indices of texels with a lobe of which most of the 3x3 neighbourhood has one
    too: the inside of a region (003 discards regions too small to be a material; a
    lone texel whose fit gave the noise a lobe is not a material)."""
    count = uniform_filter(lobed.reshape(T, S).astype(float), 3, mode="constant") * 9
    return np.flatnonzero(lobed & (count.ravel() >= 5))


def _neighbourhood_median(F: np.ndarray, lobed: np.ndarray, idx: np.ndarray, T: int,
                          S: int) -> np.ndarray:
    """Features (len(idx), f) of texels ``idx``: the median over the lobed texels of
    their 3x3 neighbourhood (a texel's own fit is noisy, its region's less so)."""
    r, c = idx // S, idx % S
    stack = []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = np.clip(r + dr, 0, T - 1), np.clip(c + dc, 0, S - 1)
            k = rr * S + cc
            stack.append(np.where(lobed[k, None], F[k], np.nan))
    return np.nanmedian(np.stack(stack), axis=0)


def _fit_bases(obs: ObservationMap, P: np.ndarray, label: np.ndarray, count: int, S: int,
               tile: int, m0: list[float], sample: int, rng) -> list[tuple[float, np.ndarray]]:
    """Each material's (m, colour) from a sample of its texels' observations."""
    basis = []
    for j in range(count):
        members = np.flatnonzero(label == j + 1)
        if len(members) == 0:
            basis.append((m0[j], np.ones(3)))
            continue
        idx, V, L, _, w = sample_texel_observations(obs, members, S, tile, sample, rng)
        dirs, present = _lobes(P[idx])
        m, kappa, _ = fit_basis(dirs, present, V, L, w, m0[j])
        basis.append((m, kappa))
    return basis


def _merge_materials(obs: ObservationMap, P: np.ndarray, label: np.ndarray,
                     basis: list[tuple[float, np.ndarray]], S: int, tile: int, sample: int,
                     rng) -> tuple[np.ndarray, list[tuple[float, np.ndarray]]]:
    """003's material merging: the two materials whose lobes look most alike are
    merged while one shared material explains their texels' observations as well by
    BIC (three parameters fewer; a sample of each), and so on."""
    def sample_of(j):
        members = np.flatnonzero(label == j + 1)
        idx, V, L, _, w = sample_texel_observations(obs, members, S, tile, sample // 2, rng)
        return (*_lobes(P[idx]), V, L, w)

    while len(basis) > 1:
        feats = np.array([[0.5 * np.log(m), *(k / 3)] for m, k in basis])
        D = np.linalg.norm(feats[:, None] - feats[None], axis=-1) + np.eye(len(basis)) * 1e9
        i, j = sorted(np.unravel_index(np.argmin(D), D.shape))
        a, b = sample_of(i), sample_of(j)
        _, _, rss_a = fit_basis(*a[:2], a[2], a[3], a[4], basis[i][0])
        _, _, rss_b = fit_basis(*b[:2], b[2], b[3], b[4], basis[j][0])
        both = [np.concatenate([x, y]) for x, y in zip(a, b, strict=True)]
        m_u, k_u, rss_u = fit_basis(*both[:2], both[2], both[3], both[4],
                                    math.sqrt(basis[i][0] * basis[j][0]))
        n = 3 * float((both[4] > 0).sum())
        if n * math.log(rss_u / max(rss_a + rss_b, 1e-300)) - 3 * math.log(n) >= 0:
            break
        logger.info(f"materials: merging materials of m {basis[i][0]:.1f} and "
                    f"{basis[j][0]:.1f} (one shared material is as good by BIC)")
        label = np.where(label == j + 1, i + 1, label)
        label = np.where(label > j + 1, label - 1, label)
        basis = [*basis[:i], (m_u, k_u), *basis[i + 1:j], *basis[j + 1:]]
    return label, basis


def run_materials(source: str | Path, processed: str | Path, config: dict[str, Any],
                  workers: int | None = None) -> dict[str, Any]:
    """The materials stage (module docstring); ``config`` the validated workflow config
    (section ``materials``); its passes over the map's tiles on ``workers`` processes
    (default the config's ``workers``). Returns the figures written to
    ``metrics/fit-mh-materials.json``."""
    workers = workers or config["workers"]
    src, proc = Processed(source), Processed(processed)
    cfg = config["materials"]
    _, obs, P, ok = open_mh_source(src.root, cfg["source"], "materials.source")
    T, S, N = obs.shape
    tile = obs.tile
    t0 = time.perf_counter()
    K = mh_lobes(P.shape[1])
    F, has = material_features(P)
    rng = np.random.default_rng(int(cfg["seed"]))
    core = _region_cores(ok & has, T, S)
    if len(core) > CLUSTER_SAMPLE:
        core = np.sort(rng.choice(core, CLUSTER_SAMPLE, replace=False))
    Fc = _neighbourhood_median(F, ok & has, core, T, S)
    count = cfg["count"]
    if len(core) == 0:
        count = 0
    elif count == "auto":  # as many as are clearly apart, then merged by BIC (003)
        count = choose_count(Fc, int(cfg["max_count"]), seed=int(cfg["seed"]))
    count = int(count)
    logger.info(f"materials: {count} basis material(s) with lobes from {cfg['source']} "
                f"({int((ok & has).sum())} of {T * S} texels have a lobe, {len(core)} "
                "inside lobed regions clustered)")
    label = np.zeros(T * S, int)
    m0 = []
    if count:
        lab = cluster_materials(Fc, count, int(cfg["seed"]))
        label[core] = lab + 1
        m0 = [float(np.exp(np.median(Fc[lab == j, 0]))) for j in range(count)]
    Pb = _borrowed(P, ok, T, S)
    basis = _fit_bases(obs, P, label, count, S, tile, m0, int(cfg["sample"]), rng)
    if cfg["count"] == "auto" and count > 1:
        label, basis = _merge_materials(obs, P, label, basis, S, tile, int(cfg["sample"]), rng)
        count = len(basis)
    pool = 2 * int(cfg["pool_radius"]) + 1
    for rnd in range(int(cfg["rounds"]) + 1):
        # BIC of every candidate at every texel; each texel then takes the choice most
        # texels of its neighbourhood made: a material is a region (003), and one
        # texel's evidence is noisy (a vote, not a sum: a strong highlight next door
        # must not outvote a diffuse texel's own weak evidence)
        B = np.zeros((T * S, count + 1))
        for flat, bic in progress(map_shared(_bic_job, obs.tiles(), workers, (obs, Pb, basis)),
                                  len(obs.tiles()), f"materials: round {rnd + 1}, choices",
                                  logger):
            B[flat] = bic
        own = np.where(ok, np.argmin(B, 1), -1)
        votes = np.stack([uniform_filter((own == j).reshape(T, S).astype(float), pool,
                                         mode="constant").ravel() for j in range(count + 1)], 1)
        votes[np.arange(T * S), np.maximum(own, 0)] += 0.5 / pool**2  # a tie keeps its own
        label = np.argmax(votes, 1)
        # a material no region chose (e.g. a cluster of texels whose fit gave noise a
        # lobe) is dropped
        used = [j for j in range(count) if (label == j + 1).any()]
        if len(used) < count:
            remap = np.zeros(count + 1, int)
            remap[[j + 1 for j in used]] = np.arange(1, len(used) + 1)
            label = remap[label]
            basis = [basis[j] for j in used]
            logger.info(f"materials: {count - len(used)} material(s) chosen by no texel "
                        "dropped")
            count = len(used)
        out = {FitArray.LABEL: label, FitArray.WEIGHTS: np.zeros((T * S, count + 1)),
               FitArray.PARAMS: np.full((T * S, mh_size(K)), np.nan)}
        for flat, wts, params in progress(
                map_shared(_assign_job, obs.tiles(), workers, (obs, Pb, basis, label)),
                len(obs.tiles()), f"materials: round {rnd + 1}, amplitudes", logger):
            out[FitArray.WEIGHTS][flat] = wts
            out[FitArray.PARAMS][flat] = params
        logger.info(f"materials: round {rnd + 1}: " + ", ".join(
            f"material {j + 1} m {m:.1f} ({int((label == j + 1).sum())} texels)"
            for j, (m, _) in enumerate(basis)) + f"; diffuse only {int((label == 0).sum())}")
        if rnd < int(cfg["rounds"]):
            basis = _fit_bases(obs, P, label, count, S, tile, [m for m, _ in basis],
                               int(cfg["sample"]), rng)
    m = _write_store(proc.fit(MATERIALS_MODEL), obs, out, ok, basis, cfg, T, S, tile, K,
                     workers)
    seconds = time.perf_counter() - t0
    m.update(seconds=seconds, texels_per_second=T * S / seconds, source=cfg["source"],
             model=MATERIALS_MODEL, count=count,
             materials=[{"m": b[0], "specular_colour": np.asarray(b[1]).tolist(),
                         "texels": int((label == j + 1).sum())}
                        for j, b in enumerate(basis)],
             diffuse_only_texels=int((label == 0).sum()))
    write_metrics(proc.metrics(f"fit-{MATERIALS_MODEL}"), m)
    return m


def _write_store(path: Path, obs: ObservationMap, out: dict, ok: np.ndarray, basis: list,
                 cfg: dict, T: int, S: int, tile: int, K: int, workers: int,
                 ) -> dict[str, Any]:
    """Write the MH fit store of the material map (temporary name, then renamed) and
    return its residual figures."""
    rmse = np.full((T * S, 3), np.nan)
    mpr = np.full((T * S, 3), np.nan)
    for flat, r, q in map_shared(_residual_job, obs.tiles(), workers,
                                 (obs, out[FitArray.PARAMS])):
        rmse[flat], mpr[flat] = r, q
    status = np.where(ok, FitStatus.OK, FitStatus.NOT_FITTED).astype(np.int8)
    out[FitArray.PARAMS][~ok] = np.nan
    rmse[~ok] = mpr[~ok] = np.nan
    M = len(basis)
    P = out[FitArray.PARAMS]
    arrays = {
        FitArray.PARAMS: (out[FitArray.PARAMS].reshape(T, S, -1), "float32", np.nan),
        FitArray.RMSE: (rmse.reshape(T, S, 3), "float32", np.nan),
        FitArray.MPR: (mpr.reshape(T, S, 3), "float32", np.nan),
        FitArray.K_USED: ((np.isfinite(P) & (P > 0))[:, [mh_ks(k).start for k in range(K)]]
                          .sum(1).reshape(T, S), "int8", 0),
        FitArray.EVALS: (np.zeros((T, S)), "int32", 0),
        FitArray.STATUS: (status.reshape(T, S), "int8", int(FitStatus.NOT_FITTED)),
        FitArray.LABEL: (np.where(ok, out[FitArray.LABEL], -1).reshape(T, S), "int16", -1),
        FitArray.WEIGHTS: (out[FitArray.WEIGHTS].reshape(T, S, M + 1), "float32", np.nan),
    }
    write_fit_store(path, arrays, tile, {
        **mh_attrs(K, K, source=cfg["source"],
                   materials=[{"m": float(m), "specular_colour": np.asarray(k).tolist()}
                              for m, k in basis]),
        **grid_attrs(obs, tile, provenance=False)})
    good = status == FitStatus.OK
    return {"texels": T * S, "fitted": int(good.sum()), "failed": 0,
            "too_few_observations": int((~good).sum()),
            "mean_percentage_residual": np.nanmean(mpr[good], 0).tolist() if good.any()
            else None,
            "median_percentage_residual": np.nanmedian(mpr[good], 0).tolist() if good.any()
            else None,
            FitArray.RMSE: np.nanmean(rmse[good], 0).tolist() if good.any() else None}
