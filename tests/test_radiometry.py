"""Flat-field and colour (issue 45 item 5): the vignetting and the light's fall-off from a
white card, the colour correction from a chart, and maps whose Kd is flat over a
uniform patch when the lens vignettes and the light falls off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import yaml

from parammap.cli import main
from parammap.conventions import LUMINANCE, MH_KD, SV_KD, FitArray, FitStatus
from parammap.geometry import look_at, texel_centres, unit
from parammap.models.colour import (
    COLOUR_SPACES,
    chart_patch_means,
    chart_reference,
    fit_colour_matrix,
)
from parammap.models.radiometry import (
    COLOUR_INTEROP_IDS,
    IrradianceGrid,
    Radiometry,
    apply_colour,
    describe_radiometry,
    fit_flatfield,
    irradiance_at,
    vignetting,
)
from parammap.models.svbrdf import svbrdf_eval
from parammap.stores.capture import CaptureError, load_capture
from parammap.stores.exr import read_exr
from parammap.stores.fit import open_fit, open_mh_source
from parammap.stores.lights import light_doc, parse_light_doc
from parammap.stores.params import ParamMap, read_param_map, write_param_map
from parammap.stores.radiometry import (
    RadiometryError,
    radiometry_for,
    read_radiometry,
    write_radiometry,
)
from parammap.synth.camera_folder import write_camera_folder
from parammap.synth.chart import chart_camera_rgb, chart_shade, chart_size_mm
from parammap.synth.generate import generate, preset_with, render_radiance
from parammap.synth.scene import load_scene
from parammap.vision.chart import ChartError, detect_chart

from .conftest import poses_with_true_intrinsics


def test_flatfield_separates_lens_and_light():
    """Cells seen at several field radii: the fixed-effects fit returns the lens's
    fall-off and the light's, each within 0.3 %, whatever the light does."""
    rng = np.random.default_rng(3)
    ny, nx, views = 12, 16, 7
    yy, xx = np.mgrid[0:ny, 0:nx]
    g_true = (1 + 0.25 * (xx / nx - 0.5)) * (1 - 0.2 * ((yy / ny - 0.5) ** 2))
    cells, rho2, logy = [], [], []
    for _ in range(views):  # each view puts the surface elsewhere in the frame
        off, scale = rng.uniform(-0.25, 0.25, 2), rng.uniform(0.03, 0.05)
        r2 = ((xx - nx / 2) * scale + off[0]) ** 2 + ((yy - ny / 2) * scale + off[1]) ** 2
        v = 1 - 0.3 * r2 / 0.5  # the generator's lens, not the fit's polynomial
        cells.append((yy * nx + xx).ravel())
        rho2.append(r2.ravel())
        logy.append(np.log(v * g_true * 7.0).ravel() + 0.002 * rng.standard_normal(ny * nx))
    rho2_all = np.concatenate(rho2)
    coeffs, log_g, st = fit_flatfield(np.concatenate(cells), rho2_all, np.concatenate(logy),
                                      ny * nx)
    grid = np.linspace(0, rho2_all.max(), 50)
    np.testing.assert_allclose(vignetting(grid, coeffs), 1 - 0.3 * grid / 0.5, rtol=3e-3)
    g = np.exp(log_g).reshape(ny, nx)
    np.testing.assert_allclose(g / g.mean(), g_true / g_true.mean(), rtol=3e-3)
    assert st["residual_rms"] < 0.003 and st["cells"] == ny * nx
    # the level divided out is the card's luminance on the axis (V = 1), over the cells
    np.testing.assert_allclose(st["level"] * g, 7.0 * g_true, rtol=3e-3)


def test_irradiance_grid_interpolates_between_centres():
    grid = np.array([[1.0, 2.0], [3.0, 4.0]])  # row 0 at the top (y = height)
    x = np.array([25.0, 75.0, 50.0, 0.0])
    y = np.array([75.0, 25.0, 50.0, 100.0])
    np.testing.assert_allclose(irradiance_at(x, y, grid, 100.0, 100.0), [1.0, 4.0, 2.5, 1.0])


def _chart_frame(camera: str, light: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A linear frame of the chart (640 x 480, tilted, noise 0.3 %), its camera RGB."""
    rgb = chart_camera_rgb(camera, light)
    cw, ch = chart_size_mm()
    shade = chart_shade(rgb, (0.0, ch), 1.0, np.full(3, 0.5))
    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]])
    centre = np.array([cw / 2, ch / 2, 0.0])
    rng = np.random.default_rng(seed)
    R, t = look_at(centre + 700 * unit(np.r_[rng.uniform(-0.3, 0.3, 2), 1.0]), centre,
                   np.radians(rng.uniform(-10, 10)))
    frame = render_radiance(shade, (640, 480), K, np.zeros(5), R, t, ss=2)
    frame *= 1 + 0.003 * rng.standard_normal(frame.shape).astype(np.float32)
    return frame, rgb


@pytest.mark.parametrize("camera,light", [("Nikon 5100 (NPL)", "A"),
                                          ("Nikon 5100 (NPL)", "FL2"),
                                          ("Sigma SDMerill (NPL)", "A"),
                                          ("Sigma SDMerill (NPL)", "D65")])
def test_chart_recovers_reflectances(camera, light):
    """A chart rendered from its spectra under a tinted light through a real camera's
    sensitivities: found by the detector, and corrected to its reflectances within a
    mean CIEDE2000 of 2 (each patch left out of the fit in turn, seen with the frame's
    noise: within 3)."""
    frame, rgb = _chart_frame(camera, light, seed=len(camera) + len(light))
    polygons, _ = detect_chart(frame)
    assert polygons.shape == (24, 4, 2)
    means, ok = chart_patch_means(frame, np.zeros(frame.shape[:2], bool), polygons)
    assert ok.all()
    # the detector's patches are the chart's, in its order
    np.testing.assert_allclose(means / means[18].max(), rgb, rtol=0.02, atol=2e-3)
    ref = chart_reference("BabelColor Average")
    _, st = fit_colour_matrix(means, ref.rgb, ref.lab, ref.to_lab, ref.neutral, noise=0.003)
    assert st["delta_e_mean"] < 2.0 and st["delta_e_loo_mean"] < 3.0, st
    # a plain 3 x 3 is worse under the tinted light, which is why it is not the default
    _, lin = fit_colour_matrix(means, ref.rgb, ref.lab, ref.to_lab, ref.neutral, "linear")
    assert lin["delta_e_mean"] > st["delta_e_mean"]


def test_no_chart_is_one_line():
    with pytest.raises(ChartError, match="photo.exr: no MCC24 colour chart found"):
        detect_chart(np.full((120, 160, 3), 0.4, np.float32), source="photo.exr")


def test_radiometry_file_round_trip_and_errors(tmp_path):
    rad = Radiometry(np.array([-0.5, 0.1, 0.0]), np.full((3, 4), 1.0),
                     np.eye(3, 6), "srgb-linear", 0.2, "root-polynomial")
    back = read_radiometry(write_radiometry(tmp_path / "r.json", rad, {"why": 1}))
    np.testing.assert_array_equal(back.vignetting, rad.vignetting)
    np.testing.assert_array_equal(back.colour_matrix, rad.colour_matrix)
    assert back.field_max == 0.2 and back.colour_model == "root-polynomial"
    assert read_radiometry(None).identity
    doc = json.loads((tmp_path / "r.json").read_text())
    doc["colour_matrix"] = [[1, 0], [0, 1]]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(RadiometryError, match="bad.json: colour_matrix must have 3 rows"):
        read_radiometry(tmp_path / "bad.json")
    (tmp_path / "junk.json").write_text("{")
    with pytest.raises(RadiometryError, match="junk.json: not valid JSON"):
        read_radiometry(tmp_path / "junk.json")


@pytest.mark.parametrize("space", sorted(COLOUR_SPACES))
def test_parameter_map_header_names_its_colour_space(space, tmp_path):
    """A map made from colour-corrected frames says so in its header, with OpenEXR's
    own colorInteropID for the space (consistent colour metadata by OpenEXR's check);
    one from camera RGB claims no colour space."""
    assert set(COLOUR_INTEROP_IDS) == set(COLOUR_SPACES)
    params = np.zeros((2, 3, 3), np.float32)
    corrected = Radiometry(np.array([-0.3, 0.0, 0.0]), np.ones((2, 2)), np.eye(3), space,
                           0.2, "linear")
    for rad, interop in ((corrected, COLOUR_INTEROP_IDS[space]), (Radiometry(), None)):
        desc = describe_radiometry(rad)
        path = write_param_map(tmp_path / "d.exr",
                               ParamMap("diffuse", params, 10, 5, attrs=desc))
        _, header = read_exr(path)
        assert header.get("colorInteropID") == interop
        assert OpenEXR.checkColorMetadata(header) == OpenEXR.ColorMetadataWarning.OK
        back = read_param_map(path).attrs
        assert {k: back[k] for k in desc} == desc
    assert back["flatfield"].startswith("none") and back["colour"].startswith("camera RGB")


@pytest.fixture(scope="module")
def vignetted(tmp_path_factory):
    """The tiny preset with a 30 % vignetting lens, a light gradient of 30 % across the
    surface, six white-card views and a chart photo (Nikon under tungsten), through
    response, HDR and poses."""
    root = tmp_path_factory.mktemp("vignetted")
    preset = preset_with("tiny", vignetting=0.3, light_gradient=0.3, card_views=6,
                         chart_camera="Nikon 5100 (NPL)", exposures=3)
    cap = generate(root / "cap", root / "truth", preset=preset, seed=1, workers=2)
    out = root / "proc"
    poses_with_true_intrinsics(cap, root / "truth", out)
    return cap, root / "truth", out


def _kd_trend(cap: Path, out: Path, truth: Path, *settings: str) -> dict[str, float]:
    """Radiometry, observation map and mh-1 with ``settings``; per diffuse patch the
    change of Kd over albedo across the patch (a plane fitted to its inner 6 x 6
    texels, relative: the outer ring's reads take in the neighbouring patch or paper)."""
    sets = ["observation.texels_x=24", "observation.tile=8", *settings]
    args = [x for s in sets for x in ("--set", s)]
    assert main(["radiometry", str(cap), "--out", str(out), *args]) == 0
    assert main(["observe", str(cap), "--out", str(out), *args]) == 0
    assert main(["fit-mh", str(out), "--out", str(out), "--lobes", "1", *args]) == 0
    _, _, P, _ = open_mh_source(out, "mh-1", "test")
    sc = load_scene(truth / "scene.npz")
    T, S = sc.shape
    ctr = texel_centres(S, T, sc.width_mm, sc.height_mm)
    irr = sum(i * np.clip(unit(p - ctr)[..., 2], 0, None)
              for p, i in zip(sc.light_pos, sc.light_int, strict=True))
    ratio = (P[:, MH_KD].reshape(T, S, 3) @ LUMINANCE) / ((sc.kd / irr[..., None]) @ LUMINANCE)
    trend = {}
    for name, (r0, c0) in {"top-left": (1, 1), "bottom-right": (17, 17)}.items():
        z = ratio[r0:r0 + 6, c0:c0 + 6]
        yy, xx = np.mgrid[0:6, 0:6]
        A = np.c_[np.ones(36), xx.ravel(), yy.ravel()]
        a, *_ = np.linalg.lstsq(A, z.ravel(), rcond=None)
        trend[name] = float((abs(a[1]) + abs(a[2])) * 5 / a[0])
    return trend


def test_flatfield_flattens_kd(vignetted):
    """With the card the Kd of each uniform patch is flat within 1 % across it; without,
    the lens and the light tilt it by several per cent."""
    cap, truth, out = vignetted
    flat = _kd_trend(cap, out, truth, "radiometry.colour=false")
    said = open_fit(out / "fit" / "mh-1.zarr").describe()
    assert said["flatfield"].startswith("lens vignetting") and "colour_space" not in said
    rad = read_radiometry(out / "camera" / "radiometry.json")
    assert rad.vignetting is not None and rad.irradiance is not None
    metrics = json.loads((out / "metrics" / "radiometry.json").read_text())["flatfield"]
    assert len(metrics["card_views"]) == 6
    raw = _kd_trend(cap, out, truth, "radiometry.colour=false", "radiometry.flatfield=false")
    assert max(flat.values()) < 0.01, flat
    assert min(raw.values()) > 0.04, raw


def test_chart_in_a_capture(vignetted):
    """The chart's bracket of a capture, merged with the views' response: its colour
    correction recorded and within a mean CIEDE2000 of 2."""
    cap, _, out = vignetted
    assert main(["radiometry", str(cap), "--out", str(out)]) == 0
    rad = read_radiometry(out / "camera" / "radiometry.json")
    assert rad.colour_matrix.shape == (3, 6) and rad.colour_space == "srgb-linear"
    colour = json.loads((out / "metrics" / "radiometry.json").read_text())["colour"]
    assert colour["patches"] == 24 and colour["delta_e_mean"] < 2.0, colour
    # merged frames are camera RGB, and say how they are corrected when read
    _, header = read_exr(out / "hdr" / f"{load_capture(cap).views[0].id}.exr")
    assert header["parammap_flatfield"].startswith("not applied: divided out as")
    assert header["parammap_colour"].startswith("camera RGB: corrected as")
    assert "colorInteropID" not in header
    figs = out / "figures"
    assert main(["figures", "radiometry", str(cap), "--out", str(out), "--figures",
                 str(figs)]) == 0
    assert (figs / "radiometry.png").stat().st_size > 10_000


def test_capture_with_card_needs_its_radiometry(vignetted, tmp_path):
    """A stage that reads frames of a capture with a card refuses to read them
    uncorrected; a chart type the detector does not know is named."""
    cap, _, _ = vignetted
    with pytest.raises(RadiometryError, match="radiometry.json: missing; the capture has"):
        radiometry_for(load_capture(cap), tmp_path / "elsewhere")
    doc = yaml.safe_load((cap / "capture.yaml").read_text())
    bad = tmp_path / "bad"
    bad.mkdir()
    for change, message in (
            (lambda d: d["colour_chart"].update(chart="SG140"),
             "colour_chart.chart: must be MCC24"),
            (lambda d: d["flatfield"].update(views=d["flatfield"]["views"][:1]),
             "flatfield.views: must list at least two of the card's views"),
            (lambda d: d["flatfield"].update(reflectance=1.2),
             r"flatfield.reflectance: must be a number in \(0, 1\]")):
        broken = yaml.safe_load(yaml.safe_dump(doc))
        change(broken)
        (bad / "capture.yaml").write_text(yaml.safe_dump(broken))
        with pytest.raises(CaptureError, match=message):
            load_capture(bad)


def test_relightable_map_puts_the_fall_off_back(vignetted):
    """With the light's fall-off divided out of the observations, the relightable map
    puts it back (its lights fall off themselves): its parameters match those fitted
    where only the lens was corrected, and its lights carry the irradiance its renders
    of the capture divide by."""
    cap, _, out = vignetted
    base = ["observation.texels_x=24", "observation.tile=8", "radiometry.colour=false",
            "lights.source=mh-1", "fit.svbrdf.refine_lights=false"]
    kd = {}
    for falloff in ("false", "true"):
        args = [x for s in [*base, f"radiometry.light_falloff={falloff}"] for x in ("--set", s)]
        assert main(["radiometry", str(cap), "--out", str(out), *args]) == 0
        assert main(["observe", str(cap), "--out", str(out), *args]) == 0
        if falloff == "false":
            assert main(["fit-mh", str(out), "--out", str(out), "--lobes", "1", *args]) == 0
            assert main(["lights", str(out), "--out", str(out), *args]) == 0
        assert main(["fit-svbrdf", str(out), "--out", str(out), *args]) == 0
        g = open_fit(out / "fit" / "svbrdf-ggx.zarr")
        ok = np.asarray(g[FitArray.STATUS][:]) == FitStatus.OK
        kd[falloff] = np.where(ok, np.asarray(g[FitArray.PARAMS][:], float)[..., SV_KD]
                               @ LUMINANCE, np.nan)
        assert (g.lights.irradiance is not None) == (falloff == "true")
    ratio = kd["true"] / kd["false"]
    assert np.nanmedian(np.abs(ratio / np.nanmedian(ratio) - 1)) < 0.005
    assert abs(np.nanmedian(ratio) - 1) < 0.02
    # its renders of the capture are in the corrected frames' units
    lights = g.lights
    pts = np.array([[10.0, 10.0, 0.0], [80.0, 80.0, 0.0]])
    p = np.tile(np.asarray(g[FitArray.PARAMS][0, 0], float), (2, 1))
    d = np.tile([0.0, 0.0, 1.0], (2, 1))
    np.testing.assert_allclose(svbrdf_eval(p, pts, d, *lights) * lights[2](pts)[:, None],
                               svbrdf_eval(p, pts, d, *lights[:2]), rtol=1e-9)


def test_colour_correction_keeps_the_exposure_scale():
    """Both colour models scale with the exposure (a frame's scale is the merge's), and
    the lights of a relightable map keep a flat-field's irradiance through their JSON."""
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.01, 1.0, (50, 3))
    M = rng.normal(size=(3, 6))
    np.testing.assert_allclose(apply_colour(7.5 * rgb, M, "root-polynomial"),
                               7.5 * apply_colour(rgb, M, "root-polynomial"), rtol=1e-12)
    np.testing.assert_allclose(apply_colour(rgb, np.eye(3), "linear"), rgb)
    grid = IrradianceGrid(np.array([[0.9, 1.1], [1.0, 1.0]]), 50.0, 40.0)
    back = parse_light_doc(json.dumps(light_doc(np.ones((1, 3)), np.ones((1, 3)), grid)))
    assert back.irradiance is not None and back.ambient is None
    pts = np.array([[12.5, 30.0, 0.0], [37.5, 10.0, 0.0]])
    np.testing.assert_allclose(back[2](pts), grid(pts))
    np.testing.assert_allclose(grid(pts), [0.9, 1.0])


def test_import_takes_the_card_and_the_chart(vignetted, tmp_path):
    """A camera folder with the white card's and the chart's photos in their own folders
    imports to a capture with its flat-field (and the card's stated reflectance) and
    colour chart, photos in place."""
    cap, _, _ = vignetted
    w = write_camera_folder(cap, tmp_path / "camera")
    assert main(["import", str(w["photos"]), "--layout", str(w["layout"]), "--board",
                 str(w["board"]), "--flatfield", str(w["flatfield"]), "--chart",
                 str(w["chart"]), "--card-reflectance", "0.8",
                 "--out", str(tmp_path / "imported")]) == 0
    got, want = load_capture(tmp_path / "imported"), load_capture(cap)
    # (the tiny preset's 320 x 240 board photos are too small for the board to be told
    # apart every time: one may join the views)
    assert len(got.flatfield) == len(want.flatfield) and len(got.views) >= len(want.views)
    assert all(len(v.exposures) == len(want.flatfield[0].exposures) for v in got.flatfield)
    assert got.chart is not None and got.chart_type == "MCC24"
    assert got.card_reflectance == want.card_reflectance == (0.8, 0.8, 0.8)
    assert sorted(e.exposure_s for e in got.chart.exposures) == pytest.approx(
        sorted(e.exposure_s for e in want.chart.exposures), rel=1e-4)
