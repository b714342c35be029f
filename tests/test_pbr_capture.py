"""The pipeline on a capture it was not built with: the physically based ``pbr-tiny``
preset (Mitsuba 3: microfacet materials, an area light, Monte Carlo noise, a filmic
response, another marker and board dictionary), against its ground truth.

Rendering takes about two minutes on two cores; the stages about one more.
"""

from __future__ import annotations

import json
import os
import shutil

import cv2
import numpy as np
import pytest
import yaml

from parammap.cli import main
from parammap.conventions import LUMINANCE
from parammap.stores.observation import open_observation_map
from parammap.synth.pbr import patch_labels, render_white_card

if os.environ.get("CI"):
    import mitsuba  # noqa: F401  (CI installs parammap[pbr]: never skip there)
else:
    pytest.importorskip("mitsuba", reason="the pbr presets need parammap[pbr] (Mitsuba 3)")


MODELS = ["--model", "mh-1", "--model", "sh-rlsop-36", "--model", "diffuse"]


@pytest.fixture(scope="module")
def pbr(tmp_path_factory):
    from parammap.synth.pbr import generate_pbr

    root = tmp_path_factory.mktemp("pbr")
    cap = generate_pbr(root / "cap", root / "truth", preset="pbr-tiny", seed=0)
    out = root / "proc"
    for stage in (["response"], ["hdr"], ["calibrate"], ["poses"], ["observe"],
                  ["fit-mh", "--lobes", "1"], ["fit-sh", "--model", "sh-rlsop-36"],
                  ["export", *MODELS], ["holdout", *MODELS]):
        assert main([stage[0], str(cap), "--out", str(out), *stage[1:]]) == 0, stage
    return cap, root / "truth", out


def test_capture_format_and_truth(pbr):
    from parammap.stores.capture import validate_capture

    cap, truth, _ = pbr
    c = validate_capture(cap)
    assert c.marker_dictionary == "DICT_5X5_250" and len(c.marker_ids) == 5
    assert c.calibration["dictionary"] == "DICT_5X5_100"
    assert len(c.views) == 33 and sum(v.holdout for v in c.views) == 3
    assert all(len(v.exposures) == 3 for v in c.views)
    for name in ("camera.yaml", "poses.npz", "response.npz", "scene.json", "generator.json"):
        assert (truth / name).is_file()
    kinds = {p["kind"] for p in json.loads((truth / "scene.json").read_text())["patches"]}
    assert kinds == {"roughplastic", "roughconductor", "principled", "diffuse"}


def test_hdr_within_oracle(pbr):
    """The recovered filmic response merges within 1.25x of an oracle merge with the
    true response, on the same pixels (issue 45; measured 1.02x at the median and the
    95th percentile, 1.35x / 1.39x before the prior followed the bracket's 2 stops)."""
    from parammap.synth.testsupport import hdr_errors

    cap, truth, out = pbr
    e = hdr_errors(cap, truth, out, ["v000", "v010", "v020", "v031"])
    assert e["median"] < 1.25 * e["oracle_median"], e
    assert e["p95"] < 1.25 * e["oracle_p95"], e


def test_views_kept_and_poses(pbr):
    """At least 98 % of the views are kept by the policy (every held-out one; issue
    14), and the poses it keeps are accurate: the marker pattern pins down the 74 deg
    view that the marker outlines left 2.3 mm off (measured: all 33 kept, centres
    within 0.23 mm median and 0.72 mm worst)."""
    from parammap.synth.testsupport import pose_errors

    _, truth, out = pbr
    m = json.loads((out / "metrics" / "poses.json").read_text())
    recs = yaml.safe_load((out / "camera" / "poses.yaml").read_text())["views"]
    assert m["kept"] >= 0.98 * m["views"], m["dropped"]
    assert all(r["kept"] for r in recs if r["holdout"])
    assert sum(r.get("pose_solution") == "pattern" for r in recs) >= 0.9 * len(recs)
    e = pose_errors(truth, out)
    kept = [v for v in e.values() if v["kept"]]
    assert np.median([v["centre_mm"] for v in kept]) < 0.5
    assert max(v["centre_mm"] for v in kept) < 1.2
    assert np.median([v["rotation_deg"] for v in kept]) < 0.2
    assert max(v["rotation_deg"] for v in kept) < 0.4


def test_auto_resolution(pbr):
    """``texels_x: auto``: about one texel per photo pixel at the median view."""
    from parammap.geometry import project_points
    from parammap.stores.capture import load_capture

    cap_dir, truth, out = pbr
    cap = load_capture(cap_dir)
    obs = json.loads((out / "metrics" / "observation.json").read_text())
    assert obs["resolution"] == "auto"
    cam = yaml.safe_load((truth / "camera.yaml").read_text())
    P = np.load(truth / "poses.npz")
    c = np.array([[cap.width_mm / 2, cap.height_mm / 2, 0.0]])
    ppmm = []
    for k in np.flatnonzero(~P["holdout"]):
        uv = [project_points(c + d, np.array(cam["K"]), np.array(cam["dist"]), P["R"][k],
                             P["t"][k])[0] for d in ([0, 0, 0], [1, 0, 0], [0, 1, 0])]
        a, b = uv[1] - uv[0], uv[2] - uv[0]
        ppmm.append(np.sqrt(abs(a[0] * b[1] - a[1] * b[0])))
    expect = cap.width_mm * np.median(ppmm)
    assert 0.9 * expect < obs["S"] < 1.1 * expect, (obs["S"], expect)


def test_observation_directions(pbr):
    from parammap.stores.observation import open_observation_map
    from parammap.synth.testsupport import angle_deg, true_directions

    _, truth, out = pbr
    g = open_observation_map(out / "observation.zarr")
    T, S, _ = g["valid"].shape
    dt = true_directions(truth, g.attrs["view_ids"], S, T, g.attrs["width_mm"],
                         g.attrs["height_mm"])
    v = g["valid"][:]
    ang = angle_deg(g["direction"][:], dt)[v]
    # issue 14: within 0.05 deg for every observation (measured: median 0.012, max
    # 0.039 with the intrinsics refined on the markers' pattern; 0.064 from the
    # corners alone, whose principal point was 1.2 px off)
    assert np.median(ang) < 0.025 and ang.max() < 0.05, (np.median(ang), ang.max())
    m = json.loads((out / "metrics" / "calibration.json").read_text())["pattern_refinement"]
    assert m["views"] >= 25 and m["cost_after"] <= m["cost_before"], m


def test_models_beat_diffuse_on_every_held_out_view(pbr):
    """MH-1 and the default SH-36 against the clean renders of the held-out views, and
    in the held-out stage against the photos; errors per material patch too."""
    from parammap.synth.testsupport import holdout_against_truth

    cap, truth, out = pbr
    res, patches = holdout_against_truth(cap, truth, out, ["mh-1", "sh-rlsop-36", "diffuse"],
                                         per_patch=True)
    assert len(res) == 3
    for m in ("mh-1", "sh-rlsop-36"):
        assert all(r[m] < r["diffuse"] for r in res.values()), (m, res)
    # SH-36 within 1.5x of MH (issue 15)
    mean = {m: np.mean([r[m] for r in res.values()]) for m in ("mh-1", "sh-rlsop-36")}
    assert mean["sh-rlsop-36"] < 1.5 * mean["mh-1"], mean
    scene = json.loads((truth / "scene.json").read_text())["patches"]
    assert len(patches) == len(scene) and all(len(v) == 3 for v in patches.values())
    h = json.loads((out / "metrics" / "holdout.json").read_text())
    assert len(h["views"]) == 3 and not h["skipped"]
    for m in ("mh-1", "sh-rlsop-36"):
        assert all(v["models"][m]["mean_diff_8bit"] < v["models"]["diffuse"]["mean_diff_8bit"]
                   for v in h["views"].values()), m
    assert h["regions"] and all(set(v["regions"]) == set(h["models"]) for v in
                                h["views"].values())


def test_svbrdf_relit_from_its_lights(pbr, tmp_path):
    """The microfacet SVBRDF on a capture whose materials are microfacet ones: the light
    (an area light 90 x 60 mm) placed within 2 % of its distance (measured 0.4 %), the
    held-out views against the clean renders closer than MH-1's on every view (measured
    5.7 / 5.8 / 5.0 against 6.5 / 11.3 / 8.3), its highlights no more speckled than
    1.5x the truth's, and relit under other lights (issue 48 item 4)."""
    import shutil

    from parammap.synth.testsupport import highlight_speckle, holdout_against_truth

    cap, truth, out = pbr
    work = tmp_path / "proc"
    shutil.copytree(out, work)
    assert main(["lights", "--out", str(work), "--set", "lights.source=mh-1"]) == 0
    assert main(["fit-svbrdf", "--out", str(work)]) == 0
    assert main(["export", "--out", str(work), "--model", "svbrdf-ggx"]) == 0
    m = json.loads((work / "metrics" / "fit-svbrdf-ggx.json").read_text())
    scene = json.loads((truth / "scene.json").read_text())
    c = yaml.safe_load((cap / "capture.yaml").read_text())["surface"]
    centre = np.array([c["width_mm"] / 2, c["height_mm"] / 2, 0.0])
    light = centre + np.array(scene["lights"][0]["position_mm"])
    found = np.array(m["light_positions"]["refined_mm"][0])
    assert np.linalg.norm(found - light) < 0.02 * np.linalg.norm(light - centre), found
    res = holdout_against_truth(cap, truth, work, ["svbrdf-ggx", "mh-1", "diffuse"])
    assert all(r["svbrdf-ggx"] < r["mh-1"] for r in res.values()), res
    sp = highlight_speckle(cap, truth, work, ["svbrdf-ggx"])
    assert sp["svbrdf-ggx"]["ratio"] < 1.5, sp
    # under lights the capture never had (the first turned 120 deg, a disc added): the
    # relightable map follows them (measured 8.4, 1.5x its captured figure; the rest is
    # the scene's sky, which it cannot tell from its lamps), MH and SH cannot (40-56)
    from parammap.synth.pbr import render_relit
    from parammap.synth.testsupport import relit_against_truth

    relit_truth = tmp_path / "truth"
    shutil.copytree(truth, relit_truth)
    render_relit(relit_truth)
    rel = relit_against_truth(cap, relit_truth, work, ["svbrdf-ggx", "mh-1", "sh-rlsop-36"])
    mean = {m: np.mean([r[m] for r in rel.values()]) for m in ("svbrdf-ggx", "mh-1",
                                                                "sh-rlsop-36")}
    captured = np.mean([r["svbrdf-ggx"] for r in res.values()])
    assert mean["svbrdf-ggx"] < 2 * captured, (mean, captured)
    assert mean["svbrdf-ggx"] < 0.5 * min(mean["mh-1"], mean["sh-rlsop-36"]), mean


def _diffuse_patch_tilt(out, truth) -> float:
    """How much the matte patch's mean radiance in near-frontal views, over its true
    albedo, changes across the patch (a plane fitted to its inner texels, relative)."""
    obs = open_observation_map(out / "observation.zarr")
    L, W = np.asarray(obs.radiance[:], float), np.asarray(obs.valid[:], bool)
    frontal = W & (np.asarray(obs.direction[:], float)[..., 2] > np.cos(np.radians(40)))
    mean = np.nanmean(np.where(frontal, L @ LUMINANCE, np.nan), -1)
    albedo = cv2.resize(np.load(truth / "albedo.npz")["albedo"].astype(np.float32),
                        (obs.S, obs.T), interpolation=cv2.INTER_AREA) @ LUMINANCE
    kinds = [p["kind"] for p in json.loads((truth / "scene.json").read_text())["patches"]]
    lab = patch_labels(truth, obs.S, obs.T, obs.width_mm, obs.height_mm)
    inner = cv2.erode((lab == kinds.index("diffuse")).astype(np.uint8),
                      np.ones((5, 5), np.uint8)) > 0
    yy, xx = np.nonzero(inner)
    z = (mean / albedo)[inner]
    ok = np.isfinite(z)
    a, *_ = np.linalg.lstsq(np.c_[np.ones(ok.sum()), xx[ok], yy[ok]], z[ok], rcond=None)
    return float((abs(a[1]) * np.ptp(xx) + abs(a[2]) * np.ptp(yy)) / a[0])


def test_white_card_flattens_the_area_light(pbr, tmp_path):
    """A white card rendered under the capture's area light (its real fall-off, Monte
    Carlo noise, no vignetting: a pinhole): the matte patch's radiance, which the light
    tilts by several per cent across it, is flat to within what the merge's response
    leaves (the merged frames are ~2 % off linear between the card's and the patch's
    brightness)."""
    cap0, truth, out0 = pbr
    cap, out = tmp_path / "cap", tmp_path / "proc"
    shutil.copytree(cap0, cap)
    cards = render_white_card(cap, truth, views=6)
    out.mkdir()
    shutil.copytree(out0 / "camera", out / "camera")
    shutil.copytree(out0 / "hdr", out / "hdr")
    for v in cards:
        assert main(["-q", "hdr", str(cap), "--out", str(out), "--view", v]) == 0
    tilt = {}
    for flat in ("false", "true"):
        sets = ["--set", f"radiometry.flatfield={flat}", "--set", "observation.texels_x=96"]
        assert main(["-q", "radiometry", str(cap), "--out", str(out), *sets]) == 0
        assert main(["-q", "observe", str(cap), "--out", str(out), *sets]) == 0
        tilt[flat] = _diffuse_patch_tilt(out, truth)
    rec = json.loads((out / "metrics" / "radiometry.json").read_text())["flatfield"]
    assert rec["card_views"] == cards and rec["vignetting_at_field_max"] < 0.02
    assert tilt["false"] > 0.05 and tilt["true"] < 0.3 * tilt["false"], tilt
