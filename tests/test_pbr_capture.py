"""The pipeline on a capture it was not built with: the physically based ``pbr-tiny``
preset (Mitsuba 3: microfacet materials, an area light, Monte Carlo noise, a filmic
response, another marker and board dictionary), against its ground truth.

The capture (``pbr_tiny``, conftest.py) is rendered once a run and shared with
``test_pbr_relight.py``.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import yaml

from parammap.stores.observation import open_observation_map

if os.environ.get("CI"):
    import mitsuba  # noqa: F401  (CI installs parammap[pbr]: never skip there)
else:
    pytest.importorskip("mitsuba", reason="the pbr presets need parammap[pbr] (Mitsuba 3)")


def test_capture_format_and_truth(pbr_tiny):
    from parammap.stores.capture import validate_capture

    cap, truth, _ = pbr_tiny
    c = validate_capture(cap)
    assert c.marker_dictionary == "DICT_5X5_250" and len(c.marker_ids) == 5
    assert c.calibration["dictionary"] == "DICT_5X5_100"
    assert len(c.views) == 33 and sum(v.holdout for v in c.views) == 3
    assert all(len(v.exposures) == 3 for v in c.views)
    for name in ("camera.yaml", "poses.npz", "response.npz", "scene.json", "generator.json"):
        assert (truth / name).is_file()
    kinds = {p["kind"] for p in json.loads((truth / "scene.json").read_text())["patches"]}
    assert kinds == {"roughplastic", "roughconductor", "principled", "diffuse"}


def test_hdr_within_oracle(pbr_tiny):
    """The recovered filmic response merges within 1.25x of an oracle merge with the
    true response, on the same pixels (issue 45; measured 1.02x at the median and the
    95th percentile, 1.35x / 1.39x before the prior followed the bracket's 2 stops)."""
    from parammap.synth.testsupport import hdr_errors

    cap, truth, out = pbr_tiny
    e = hdr_errors(cap, truth, out, ["v000", "v010", "v020", "v031"])
    assert e["median"] < 1.25 * e["oracle_median"], e
    assert e["p95"] < 1.25 * e["oracle_p95"], e


def test_views_kept_and_poses(pbr_tiny):
    """At least 98 % of the views are kept by the policy (every held-out one; issue
    14), and the poses it keeps are accurate: the marker pattern pins down the 74 deg
    view that the marker outlines left 2.3 mm off (measured: all 33 kept, centres
    within 0.23 mm median and 0.72 mm worst)."""
    from parammap.synth.testsupport import pose_errors

    _, truth, out = pbr_tiny
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


def test_auto_resolution(pbr_tiny):
    """``texels_x: auto``: about one texel per photo pixel at the median view."""
    from parammap.geometry import project_points
    from parammap.stores.capture import load_capture

    cap_dir, truth, out = pbr_tiny
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


def test_observation_directions(pbr_tiny):
    from parammap.synth.testsupport import angle_deg, true_directions

    _, truth, out = pbr_tiny
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


def test_models_beat_diffuse_on_every_held_out_view(pbr_tiny):
    """MH-1 and the default SH-36 against the clean renders of the held-out views, and
    in the held-out stage against the photos; errors per material patch too."""
    from parammap.synth.testsupport import holdout_against_truth

    cap, truth, out = pbr_tiny
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
