"""Basis materials (issue 20, 003): bands of known Phong materials over a printed albedo
are found as materials, their shininess recovered from all their texels, the labels
match the bands, and the material map predicts the truth at least as well as the
per-texel fit it started from."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from parammap.config import validate_config
from parammap.conventions import MH_M
from parammap.errors import InputError
from parammap.models.materials import adjusted_rand_index
from parammap.models.mh import MhFitConfig, fit_mh_tile, mh_eval, mh_outputs
from parammap.stages.fit import fit_map
from parammap.stages.materials import run_materials
from parammap.stores.fit import MATERIALS_MODEL, open_fit
from parammap.stores.observation import write_observation_arrays
from parammap.synth.cases import patches_case
from parammap.synth.scene import true_radiance

MATERIALS = ((1.0, 1.0, 1.0, 8.0), (1.2, 0.9, 0.5, 25.0), (0.8, 0.8, 0.8, 80.0))


def test_adjusted_rand_index():
    a = np.array([0, 0, 1, 1, 2, 2])
    assert adjusted_rand_index(a, a) == 1.0
    assert adjusted_rand_index(a, (a + 1) % 3 * 7) == 1.0  # labels are names only
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 4, 4000), rng.integers(0, 4, 4000)
    assert abs(adjusted_rand_index(x, y)) < 0.01
    assert 0 < adjusted_rand_index(np.array([0, 0, 0, 1, 1, 1]),
                                   np.array([0, 0, 1, 1, 1, 1])) < 1


@pytest.fixture(scope="module")
def materials_run(tmp_path_factory):
    case, label = patches_case(MATERIALS, texels=12, noise=0.02, seed=1)
    proc = tmp_path_factory.mktemp("materials")
    write_observation_arrays(proc / "observation.zarr", case.radiance, case.direction,
                             case.valid, 1000.0, 1000.0, tile=6)
    fit_map(proc / "observation.zarr", proc / "fit" / "mh-1.zarr",
            partial(fit_mh_tile, K=1, cfg=MhFitConfig(), K_max=1), mh_outputs(1),
            {"model": "mh", "lobes": "1"}, "synchronous", 1)
    cfg = validate_config({"captures": {"x": "."},
                           "materials": {"source": "mh-1", "count": "auto"}})
    m = run_materials(proc, proc, cfg)
    return case, label, proc, m


def test_materials_match_the_bands_and_recover_shininess(materials_run):
    case, label, proc, m = materials_run
    g = open_fit(proc / "fit" / f"{MATERIALS_MODEL}.zarr")
    assert m["count"] == len(MATERIALS)  # chosen automatically
    assert adjusted_rand_index(g["label"][:], label) > 0.95
    found = sorted(x["m"] for x in m["materials"])
    for got, true in zip(found, sorted(x[3] for x in MATERIALS), strict=True):
        assert abs(got / true - 1) < 0.05, (found, true)
    # the per-texel fit's shininess scatters more than the materials' within a band
    src = open_fit(proc / "fit" / "mh-1.zarr")["params"][:]
    for j, true in enumerate(x[3] for x in MATERIALS):
        per_texel = src[label == j + 1][:, MH_M]
        assert np.max(np.abs(per_texel / true - 1)) > abs(
            g["params"][:][label == j + 1][0, MH_M] / true - 1)
    w = g["weights"][:]
    assert np.allclose(w.sum(-1), 1, atol=1e-6) and w.shape[-1] == len(MATERIALS) + 1


def test_materials_on_two_workers_match_one(materials_run, tmp_path):
    import shutil

    _, _, proc, m = materials_run
    shutil.copytree(proc / "observation.zarr", tmp_path / "observation.zarr")
    shutil.copytree(proc / "fit" / "mh-1.zarr", tmp_path / "fit" / "mh-1.zarr")
    cfg = validate_config({"captures": {"x": "."},
                           "materials": {"source": "mh-1", "count": "auto"}})
    m2 = run_materials(tmp_path, tmp_path, cfg, workers=2)
    assert m2["materials"] == m["materials"]
    one = open_fit(proc / "fit" / f"{MATERIALS_MODEL}.zarr")
    two = open_fit(tmp_path / "fit" / f"{MATERIALS_MODEL}.zarr")
    for k in ("params", "label", "weights", "rmse"):
        assert np.array_equal(one[k][:], two[k][:], equal_nan=True), k


def test_material_map_predicts_the_truth(materials_run):
    case, label, proc, _ = materials_run
    T, S, N, _ = case.radiance.shape
    rows = np.repeat(np.arange(T), S * N)
    cols = np.tile(np.repeat(np.arange(S), N), T)
    truth = true_radiance(case.scene, rows, cols,
                          case.direction.reshape(-1, 3).astype(float)).reshape(T, S, N, 3)

    def error(store):
        p = open_fit(store)["params"][:].astype(float)
        return float(np.sqrt(((mh_eval(p, case.direction.astype(float)) - truth) ** 2).mean()))

    per_texel = error(proc / "fit" / "mh-1.zarr")
    materials = error(proc / "fit" / f"{MATERIALS_MODEL}.zarr")
    assert materials <= per_texel
    assert (open_fit(proc / "fit" / f"{MATERIALS_MODEL}.zarr")["label"][:][label == 0]
            == 0).mean() > 0.9  # the diffuse band is diffuse only


def test_source_must_be_an_mh_fit(materials_run, tmp_path):
    _, _, proc, _ = materials_run
    cfg = validate_config({"captures": {"x": "."}, "materials": {"source": "mh-7"}})
    with pytest.raises(InputError, match="mh-7"):
        run_materials(proc, proc, cfg)
