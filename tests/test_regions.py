"""Held-out errors per region of similar texels (issue 15, item 4)."""

from __future__ import annotations

import numpy as np

from parammap.stages.holdout import region_errors, texel_regions
from parammap.stores.observation import write_observation_arrays
from parammap.synth.cases import phong_case


def test_regions_separate_materials(tmp_path):
    # left half glossy red, right half matte grey (another colour and no highlight)
    gloss = phong_case(texels=8, level=2, m=20, ks=1.0)
    matte = phong_case(texels=8, level=2, colour=(90, 90, 90), ks=0.0)
    L = gloss.radiance.copy()
    L[:, 4:] = matte.radiance[:, 4:]
    obs = write_observation_arrays(tmp_path / "obs.zarr", L, gloss.direction, gloss.valid,
                                   1000.0, 1000.0, tile=4)
    labels, regions = texel_regions(obs, k=2)
    assert labels.shape == (8, 8) and len(regions) == 2
    assert len(np.unique(labels[:, :4])) == 1 and len(np.unique(labels[:, 4:])) == 1
    assert labels[0, 0] != labels[0, 7]
    glossy = regions[labels[0, 0]]["gloss_ratio"]
    assert glossy > 2 * regions[labels[0, 7]]["gloss_ratio"]
    assert sum(r["texels"] for r in regions) == 64


def test_region_errors_are_per_label_means():
    photo = np.full((4, 4, 3), 0.5)
    image = photo.copy()
    image[:, 2:] += 0.2
    regions = np.zeros((4, 4), int)
    regions[:, 2:] = 1
    regions[0, 0] = -1
    mask = np.ones((4, 4), bool)
    e = region_errors(photo, image, mask, 1.0, regions)
    assert set(e) == {"0", "1"} and e["0"]["mean_diff_8bit"] == 0
    assert e["0"]["pixels"] == 7 and e["1"]["pixels"] == 8
    assert e["1"]["mean_diff_8bit"] > 10
