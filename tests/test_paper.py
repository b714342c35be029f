"""004's experiments under the published conditions (issue 16): 289 icosahedron views,
8-bit renders clipped at 255, the published lights and colour; ``parammap paper
--quick`` as the suite runs it. Values 004 leaves unstated are listed in
``reports/paper/README.md``; the assertions are on what does not depend on them."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from parammap.cli import main


def _table(path):
    with path.open() as f:
        rows = list(csv.DictReader(f))
    num = (lambda s: np.array([float(x) for x in s.split()]) if s else None)  # noqa: E731
    return {r["case"]: {k: num(r[k]) if k in ("published", "ours_published_method",
                                               "ours_defaults") else r[k]
                        for k in r} for r in rows}


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    assert main(["paper", "--out", str(out), "--quick"]) == 0
    return out


def test_published_conditions_are_stated(paper):
    text = (paper / "README.md").read_text()
    assert "289 icosahedron directions" in text and "8 bits" in text
    for unstated in ("ks, m", "camera distance", "area light", "second light"):
        assert f"- {unstated}:" in text


def test_one_lobe_on_one_light_fits_to_the_8_bit_floor(paper):
    t = _table(paper / "point_area.csv")
    for case in ("point light [8, 8]", "point light [14, 14]", "area light [8, 8]"):
        ours = t[case]["ours_published_method"]
        # G and B sit at level 15: half a level of quantisation is 3.3 %
        assert ours[0] < 2.0 and (ours[1:] < 4.0).all(), (case, ours)
        assert t[case]["published"] is not None


def test_second_light_needs_a_second_lobe(paper):
    """004 ch. 11.3.2: one lobe leaves 10-22 % in G and B (red clipped: 0); two lobes
    and auto (ours, not published) reach the 8-bit floor."""
    t = _table(paper / "second_light.csv")
    for xy in ("[450, 450]", "[-450, -450]", "[-1500, -1500]"):
        one = t[f"second light at {xy}, K = 1"]
        assert one["ours_published_method"][0] == 0.0 and one["published"][0] == 0.0
        assert 5.0 < one["ours_published_method"][1] < 40.0
        for K in ("2", "auto"):
            assert (t[f"second light at {xy}, K = {K}"]["ours_defaults"] < 1.5).all()
    near = t["second light at [450, 450], K = 1"]["ours_published_method"][1]
    far = t["second light at [-1500, -1500], K = 1"]["ours_published_method"][1]
    assert far > near  # as published: merged when close, the weak one lost when apart


def test_sh_sweep_reproduces_the_published_projections(paper):
    """004 ch. 12.5 at 100 coefficients: ZH [7.67, 16.72] and LSOP's overshoot near the
    equator (about 0.55 against 0.4 measured); our sampled-cap projection fits the
    same data better and follows the measured values there."""
    t = _table(paper / "sh_sweep.csv")
    zh = t["sh-zh-100"]["ours_published_method"]
    assert abs(zh[0] - 7.67) < 3 and abs(zh[1] - 16.72) < 5
    lsop = t["sh-lsop-100"]
    note = lsop["note"]
    measured = float(note.split("measured ")[1].split(",")[0])
    lsop_eq = float(note.split("lsop ")[1].split(",")[0])
    ours_eq = float(note.split("sampled cap) ")[1].split(" ")[0])
    assert lsop_eq > 1.5 * measured and abs(ours_eq - measured) < 0.05 * measured
    for hemi in ("zh", "lsop"):
        for nc in (16, 100):
            row = t[f"sh-{hemi}-{nc}"]
            assert (row["ours_defaults"][1:] < row["ours_published_method"][1:]).all()


def test_sizes_follow_the_published_formulas(paper):
    for case, row in _table(paper / "sizes.csv").items():
        np.testing.assert_allclose(row["ours_published_method"], row["published"],
                                   atol=0.011, err_msg=case)


def test_published_sampling_schemes(paper):
    t = _table(paper / "sampling.csv")
    assert t["latitude-longitude (113)"]["ours_published_method"][0] == 113
    assert t["icosahedron level 3 to 85 deg (289)"]["ours_published_method"][0] == 289
    for fig in ("sampling", "point_area", "second_light", "sh_sweep", "shininess"):
        assert (paper / f"{fig}.png").stat().st_size > 10_000, fig


def test_shininess_limit_of_lsop_36_as_published(paper):
    """004 ch. 13.1: LSOP-36 follows a highlight up to a shininess of about 15; MH all
    eight bands."""
    t = _table(paper / "shininess.csv")
    assert 10 <= t["highest m followed, sh-lsop-36"]["ours_published_method"][0] <= 25
    assert t["highest m followed, sh-lsop-16"]["ours_published_method"][0] < 15
    assert t["highest m followed, mh-1"]["ours_published_method"][0] == 200


def test_more_views_help_sh_more_than_mh(paper):
    """004 ch. 13.2: MH from 73 views is close to 305; SH-36 needs the views (17 < 73 <
    305) everywhere on the hemisphere."""
    t = _table(paper / "view_count.csv")
    assert (t["MH-1 from 73 views against 305"]["ours_published_method"][:3] < 5).all()
    e = {n: t[f"SH-36 from {n} views"]["ours_published_method"] for n in ("17", "73", "305")}
    assert (e["305"] < e["73"]).all() and (e["73"] < e["17"]).all()


def test_greedy_virtual_lights_start_near_the_optimum(paper):
    """001's procedure (our initialiser) starts far closer than 004's guess and reaches
    the same optimum in no more evaluations (two lobes from either start can take the
    same count: which one is fewer there depends on the last bit of the arithmetic)."""
    t = _table(paper / "initialisers.csv")
    for scene in ("point light, K = 1", "second light at [-1500, -1500], K = 2"):
        start = t[f"{scene}, start: median mean % residual"]
        fit = t[f"{scene}, fit: median mean % residual"]
        evals = t[f"{scene}, fit: mean evaluations"]
        assert (start["ours_defaults"][1:] < 0.3 * start["ours_published_method"][1:]).all()
        np.testing.assert_allclose(fit["ours_defaults"], fit["ours_published_method"],
                                   atol=0.05)
        assert evals["ours_defaults"][0] <= evals["ours_published_method"][0]


def test_held_out_tables_in_the_layout_of_004_ch16(tiny_processed, tmp_path):
    """004 ch. 16 on one of our captures: mean and sd of the 8-bit difference per
    held-out view (``--quick``: Phong and SHZH16 as published, our sh-rlsop-36; make
    paper adds SHZH64, SHLSOP16/64 and our mh-auto)."""
    from parammap.stores.camera import read_poses
    from parammap.stores.paths import Processed

    cap, _, out = tiny_processed
    assert main(["paper", "--out", str(tmp_path), "--experiment", "sizes", "--capture",
                 str(cap), "--processed", str(out), "--workers", "1", "--quick"]) == 0
    with (tmp_path / "holdout.csv").open() as f:
        rows = list(csv.DictReader(f))
    held = [r["id"] for r in read_poses(Processed(out).poses)["views"]
            if r.get("holdout") and r.get("kept")]
    ours = [r for r in rows if r["view"].split(" ")[0] in held]
    assert len(ours) == len(held) > 0
    cols = ("Phong", "SHZH16", "ours sh-rlsop-36")  # --quick: the published ones in make paper
    for r in ours:
        values = np.array([float(r[c]) for c in cols])
        assert np.isfinite(values).all() and (values >= 0).all() and (values < 128).all()
    assert sum(r["view"].startswith("published") for r in rows) == 4
    with (tmp_path / "sizes_measured.csv").open() as f:
        sizes = {r["item"]: r for r in csv.DictReader(f)}
    obs = sizes["observation map (zarr)"]
    assert 0 < float(obs["bytes_per_texel"]) < 3 * float(obs["formula_bytes_per_texel"])


def test_planar_voronoi_areas_as_published():
    """004's quadrature: planar Voronoi cells in the unit disc divided by cos(theta);
    they cover the hemisphere (2 pi) when the views reach the equator, and differ from
    the spherical cells most near the equator."""
    from parammap.models.sh.basis import planar_solid_angles, solid_angles
    from parammap.synth.sampling import icosahedron

    d = icosahedron(3, 90.0)
    planar, spherical = planar_solid_angles(d), solid_angles(d)
    assert abs(planar.sum() / (2 * np.pi) - 1) < 0.03
    low, high = d[:, 2] < 0.2, d[:, 2] > 0.8
    rel = np.abs(planar / spherical - 1)
    assert rel[high].mean() < 0.1 and rel[low].mean() > rel[high].mean()
