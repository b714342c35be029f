"""The microfacet SVBRDF (``svbrdf-ggx``, issue 48 item 2): the per-texel fit against
known parameters, its uncertainties, the lights' positions refined and their relative
intensities, the parameter map's round trip and the stage on the tiny capture."""

from __future__ import annotations

import json

import numpy as np
import pytest

from parammap.conventions import (
    LUMINANCE,
    SV_ALPHA,
    SV_COAT,
    SV_KD,
    SV_KS,
    SV_SIZE,
    FitArray,
)
from parammap.models.svbrdf import (
    fit_svbrdf_batch,
    light_terms,
    light_weights,
    refine_lights,
    svbrdf_eval,
)
from parammap.stores.lights import light_doc


def _rig(rng, B: int, N: int, max_zenith_deg: float, width: float = 200.0):
    """B texels over a width x 0.75 width surface, each seen from the same N
    directions spread over a cap (a jittered spiral)."""
    k = np.arange(N) + 0.5
    z = 1 - (1 - np.cos(np.radians(max_zenith_deg))) * k / N
    phi = k * np.pi * (3 - np.sqrt(5)) + rng.uniform(0, 0.2, N)
    r = np.sqrt(1 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    pts = np.c_[rng.uniform(0, width, B), rng.uniform(0, 0.75 * width, B), np.zeros(B)]
    return np.broadcast_to(v, (B, N, 3)).copy(), pts


def _render(P, pts, V, lights, w):
    B, N, _ = V.shape
    return svbrdf_eval(np.repeat(P, N, 0), np.repeat(pts, N, 0), V.reshape(-1, 3), lights,
                       w).reshape(B, N, 3)


def _map_rig(S: int, T: int, W: float, H: float, N: int, max_zenith_deg: float,
             distance: float):
    """The centres (S T, 3) of an S x T texel map over a W x H mm surface and their
    directions (S T, N, 3) to N cameras ``distance`` mm from the surface's centre on a
    spiral over a cap; and that centre."""
    target = np.array([W / 2, H / 2, 0.0])
    k = np.arange(N) + 0.5
    z = 1 - (1 - np.cos(np.radians(max_zenith_deg))) * k / N
    phi = k * np.pi * (3 - np.sqrt(5))
    cams = target + distance * np.c_[np.sqrt(1 - z * z) * np.cos(phi),
                                     np.sqrt(1 - z * z) * np.sin(phi), z]
    xs, ys = (np.arange(S) + 0.5) * W / S, H - (np.arange(T) + 0.5) * H / T
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    pts = np.c_[pts, np.zeros(len(pts))]
    V = cams[None] - pts[:, None]
    return pts, V / np.linalg.norm(V, axis=-1, keepdims=True), target


@pytest.mark.parametrize(("lights", "N", "zenith", "coat_tol"), [
    ([[-100.0, 200.0, 400.0]], 80, 70.0, 0.08),
    ([[300.0, -50.0, 350.0], [-80.0, 160.0, 500.0]], 50, 60.0, 0.25),
])
def test_parameters_recovered_with_honest_sds(lights, N, zenith, coat_tol):
    """Texels rendered by the model itself, 2 % multiplicative noise: GGX alpha (0.03 to
    0.5), Kd and Ks within a few percent at the median, the coat's share (matte to
    plastic) within 0.05, and the sandwich sds calibrated (the spread of the errors
    over their sd between 0.6 and 2)."""
    rng = np.random.default_rng(1)
    B = 400
    V, pts = _rig(rng, B, N, zenith)
    lights = np.array(lights)
    w = np.ones((len(lights), 3))
    if len(lights) > 1:
        w[1] = [0.6, 0.7, 0.8]
    P = np.c_[rng.uniform(0.05, 0.5, (B, 3)), rng.uniform(0.2, 2.0, (B, 3)),
              np.exp(rng.uniform(np.log(0.03), np.log(0.5), B)), rng.uniform(0, 1, B)]
    y = _render(P, pts, V, lights, w) * (1 + 0.02 * rng.standard_normal((B, N, 3)))
    r = fit_svbrdf_batch(y, V, np.ones((B, N)), pts, lights, w, coat_choice=np.ones(B, bool))
    Q = r["estimate"]
    assert Q.shape == (B, SV_SIZE)
    rel = {k: np.median(np.abs(Q[:, s] / P[:, s] - 1)) for k, s in
           (("kd", SV_KD), ("ks", SV_KS), ("alpha", SV_ALPHA))}
    assert rel["alpha"] < 0.02 and rel["kd"] < 0.03 and rel["ks"] < 0.03, rel
    # the coat shows in the diffuse light's fall-off toward grazing: views to 70 deg
    # pin it, views to 60 deg much less (its sd says so, checked below)
    assert np.median(np.abs(Q[:, SV_COAT] - P[:, SV_COAT])) < coat_tol
    for s in (SV_KD, SV_KS, SV_ALPHA, SV_COAT):
        z = (Q[:, s] - P[:, s]) / r["stdev"][:, s]
        assert 0.6 < np.std(z) < 2.0, (s, np.std(z))


def test_ggx_albedo_against_monte_carlo():
    """GGX's directional albedo (Fresnel 1) of the table against a Monte Carlo integral
    over the hemisphere (1e6 uniform directions, 0.3 % sd): within 0.01 at grazing to
    normal views and near-mirror to rough lobes; 1 for a mirror."""
    from parammap.models.svbrdf import ggx_albedo, ggx_vis

    rng = np.random.default_rng(0)
    z, phi = rng.uniform(0, 1, 1_000_000), rng.uniform(0, 2 * np.pi, 1_000_000)
    s = np.sqrt(1 - z * z)
    for mu, alpha in ((0.95, 0.05), (0.5, 0.3), (0.9, 0.13), (0.2, 0.7), (0.35, 1.0)):
        v = np.array([np.sqrt(1 - mu * mu), 0.0, mu])
        h = np.stack([s * np.cos(phi) + v[0], s * np.sin(phi), z + mu], -1)
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        mc = 2 * np.pi * np.mean(ggx_vis(h[:, 2], mu, z, alpha) * z)
        assert abs(float(ggx_albedo(mu, alpha)) - mc) < 0.01, (mu, alpha, mc)
    assert abs(float(ggx_albedo(0.8, 0.005)) - 1) < 0.01


def test_ambient_light_kept_off_the_albedo():
    """Texels under a lamp and an even sky of a fifth of its irradiance (2 % noise):
    with the sky stated, Kd, Ks and alpha come back within a few percent, as without
    one; left out, Kd takes the sky's share (+15 % or more) and the map drawn under
    the lamp moved 150 mm in the same room misses the truth by more than the stated
    fit does."""
    from parammap.models.svbrdf import ambient_irradiance

    rng = np.random.default_rng(2)
    B, N = 300, 60
    V, pts = _rig(rng, B, N, 70.0)
    lights, w = np.array([[-100.0, 200.0, 400.0]]), np.ones((1, 3))
    sky = ambient_irradiance(0.2, np.array([100.0, 75.0, 0.0]), lights, w)
    P = np.c_[rng.uniform(0.05, 0.5, (B, 3)), rng.uniform(0.2, 2.0, (B, 3)),
              np.exp(rng.uniform(np.log(0.05), np.log(0.5), B)), np.zeros(B)]
    y = svbrdf_eval(np.repeat(P, N, 0), np.repeat(pts, N, 0), V.reshape(-1, 3), lights, w,
                    ambient=sky).reshape(B, N, 3) * (1 + 0.02 * rng.standard_normal((B, N, 3)))
    fits = {k: fit_svbrdf_batch(y, V, np.ones((B, N)), pts, lights, w, with_coat=False,
                                ambient=a)["estimate"] for k, a in (("stated", sky),
                                                                    ("left out", None))}
    Q = fits["stated"]
    rel = {k: np.median(np.abs(Q[:, s] / P[:, s] - 1)) for k, s in
           (("kd", SV_KD), ("ks", SV_KS), ("alpha", SV_ALPHA))}
    assert rel["alpha"] < 0.03 and rel["kd"] < 0.03 and rel["ks"] < 0.05, rel
    assert np.median(fits["left out"][:, SV_KD] / P[:, SV_KD]) > 1.15
    moved = lights + [150.0, -100.0, 0.0]

    def relit(p, a):
        return svbrdf_eval(np.repeat(p, N, 0), np.repeat(pts, N, 0), V.reshape(-1, 3),
                           moved, w, ambient=a)

    truth = relit(P, sky)
    err = {k: np.median(np.abs(relit(Q, a) / truth - 1)) for k, Q, a in
           (("stated", fits["stated"], sky), ("left out", fits["left out"], None))}
    assert err["stated"] < 0.02 and err["left out"] > 2 * err["stated"], err


def test_coat_kept_where_the_views_need_it():
    """The coat's F test: on matte texels (noise, 2 % per view shared by the channels,
    as one pixel's is) its mean stays under 1.5 (one parameter fitting noise gains 1);
    on coated ones (a plastic, a dielectric over a diffuse base) it is large. Over a
    map half matte, half coated, :func:`coat_regions` keeps the coat on the coated half
    alone, and the map's fit (:func:`fit_svbrdf_tile`) recovers alpha and Ks within 3 %
    and 5 %, where a matte model's lobe widens and brightens to take the diffuse
    fall-off (alpha 0.18 for 0.15, Ks 0.11 for 0.08)."""
    from parammap.geometry import texel_centres
    from parammap.models.svbrdf import coat_regions, fit_svbrdf_tile

    rng = np.random.default_rng(5)
    t, u, N = 24, 32, 60
    V1, _ = _rig(rng, 1, N, 72.0)
    pts = texel_centres(u, t, 160.0, 120.0).reshape(-1, 3)
    B = t * u
    V = np.broadcast_to(V1, (B, N, 3)).copy()
    light = np.array([[60.0, 160.0, 450.0]])
    coated = (np.arange(u)[None, :] >= u // 2).repeat(t, 0).ravel()
    # a plastic's proportions: F0 = 0.04 of the light against an albedo of 0.2-0.5
    P = np.c_[rng.uniform(0.2, 0.5, (B, 3)), np.full((B, 3), 0.08), np.full(B, 0.15),
              coated.astype(float)]
    pixel = 1 + 0.02 * rng.standard_normal((B, N, 1))  # one pixel's noise, all channels
    y = _render(P, pts, V, light, np.ones((1, 3))) * pixel
    f = fit_svbrdf_batch(y, V, np.ones((B, N)), pts, light, np.ones((1, 3)),
                         evidence=True)["coat_f"]
    assert np.mean(f[~coated]) < 1.5, np.mean(f[~coated])
    assert np.median(f[coated]) > 10, np.median(f[coated])
    keep = coat_regions(f.reshape(t, u)).ravel()
    # at most the matte column beside the edge (1 of 16) takes its neighbours' coat
    assert keep[coated].mean() > 0.95 and keep[~coated].mean() < 0.08
    out = fit_svbrdf_tile(y.reshape(t, u, N, 3), V.reshape(t, u, N, 3),
                          np.ones((t, u, N), bool), origin=(0, 0), grid=(u, t, 160.0, 120.0),
                          lights_mm=light, weights=np.ones((1, 3)))
    Q = out["params"].reshape(B, -1)
    assert (Q[~coated, SV_COAT] > 0).mean() < 0.08 and np.median(Q[coated, SV_COAT]) > 0.9
    assert np.median(np.abs(Q[:, SV_ALPHA] / 0.15 - 1)) < 0.03
    assert np.median(np.abs(Q[:, SV_KS] / 0.08 - 1)) < 0.05


def test_analytic_generator_ggx_recovered():
    """The analytic generator's own GGX patches (separable Smith masking, its own
    normalisation, no light fall-off) give the fit's alpha within 3 %: the model is the
    microfacet physics, not our code's quirks."""
    from parammap.synth.scene import _ggx

    rng = np.random.default_rng(2)
    B, N = 200, 60
    V, pts = _rig(rng, B, N, 65.0)
    light = np.array([[60.0, 250.0, 300.0]])
    alpha = rng.uniform(0.08, 0.45, B)
    l, _ = light_terms(pts, light)
    h = V + l[:, 0][:, None]
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    f = _ggx(h[..., 2], V[..., 2], l[:, 0, 2][:, None], alpha[:, None])
    y = 0.3 + 0.8 * f[..., None] * np.array([0.9, 0.75, 0.5])
    r = fit_svbrdf_batch(y, V, np.ones((B, N)), pts, light, np.ones((1, 3)))
    assert np.median(np.abs(r["estimate"][:, SV_ALPHA] / alpha - 1)) < 0.03


def test_lights_refined_and_their_intensities():
    """Two lights started 15 % of their distance off: the refined positions within 2 %
    of the truth; their relative intensities from the per-light amplitudes within 3 %."""
    rng = np.random.default_rng(3)
    B, N = 600, 60
    V, pts = _rig(rng, B, N, 70.0)
    truth = np.array([[260.0, 40.0, 380.0], [-60.0, 170.0, 450.0]])
    w = np.array([[1.0, 1.0, 1.0], [0.5, 0.6, 0.8]])
    P = np.c_[rng.uniform(0.05, 0.4, (B, 3)), rng.uniform(0.5, 2.0, (B, 3)),
              rng.uniform(0.1, 0.35, B), rng.uniform(0, 1, B)]
    y = _render(P, pts, V, truth, w) * (1 + 0.01 * rng.standard_normal((B, N, 3)))
    ctr = pts.mean(0)
    dist = np.linalg.norm(truth - ctr, axis=1)
    off = rng.standard_normal(truth.shape)
    start = truth + 0.15 * dist[:, None] * off / np.linalg.norm(off, axis=1, keepdims=True)
    found, rec = refine_lights(y, V, np.ones((B, N)), pts, start)
    err = np.linalg.norm(found - truth, axis=1) / dist
    assert np.all(err < 0.02), (err, rec)
    assert rec["final"] < rec["start"]
    r = fit_svbrdf_batch(y, V, np.ones((B, N)), pts, found, None)
    assert np.allclose(light_weights(r["ks"], r["stdev_ks"]), w, rtol=0.03)


def test_param_map_round_trip_and_render(tmp_path):
    """An svbrdf map written to EXR and read back: channels, sds and its lights in the
    header; rendered through the general evaluator like any map; a map whose header
    lost its lights refuses to render with one line."""
    from parammap.errors import InputError
    from parammap.render import evaluate
    from parammap.stores.params import ParamMap, read_param_map, write_param_map

    rng = np.random.default_rng(4)
    P = np.c_[rng.uniform(0.1, 0.5, (6, 5, 3)), rng.uniform(0.2, 1, (6, 5, 3)),
              rng.uniform(0.05, 0.5, (6, 5, 1)), rng.uniform(0, 1, (6, 5, 1))
              ].astype(np.float32)
    lights = light_doc([[10.0, 20.0, 300.0]], [[1.0, 1.0, 1.0]], ambient=[0.5, 0.6, 0.7])
    pm = ParamMap("svbrdf", P, 50.0, 60.0, attrs={"lights": json.dumps(lights)},
                  sd=np.full_like(P, 0.01))
    back = read_param_map(write_param_map(tmp_path / "svbrdf-ggx.exr", pm))
    assert back.model == "svbrdf" and np.array_equal(back.params, P)
    assert back.sd is not None and np.allclose(back.sd, 0.01)
    pos, w, irr, amb = back.lights
    assert np.allclose(pos, [[10, 20, 300]]) and np.allclose(w, 1)
    assert irr is None and np.allclose(amb, [0.5, 0.6, 0.7])
    pts = np.array([[5.0, 5.0, 0.0], [40.0, 50.0, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.3, 0.1, 0.95]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = evaluate("svbrdf", P[0, :2].reshape(2, -1), d, pts, back.lights)
    want = svbrdf_eval(P[0, :2].reshape(2, -1), pts, d, pos, w, ambient=amb)
    assert np.allclose(got, want) and (got > 0).all()
    dark = svbrdf_eval(P[0, :2].reshape(2, -1), pts, d, pos, w)
    assert (got > dark).all()
    # relit under another lamp: in the same room (the default) or a dark one
    assert np.allclose(back.relit(pos + 50.0, w).lights.ambient, amb)
    assert back.relit(pos + 50.0, w, ambient=None).lights.ambient is None
    with pytest.raises(InputError, match="lights"):
        evaluate("svbrdf", P[0, :2].reshape(2, -1), d)


def test_stage_on_the_tiny_capture(tiny_processed, tmp_path):
    """``parammap lights`` then ``parammap fit-svbrdf`` on the tiny capture (two point
    lights; Phong, Blinn and GGX patches): the lights found from mh-auto's lobes lie
    within 2 % of the truth (issue 48's bound); refined under the microfacet model they
    lower its pilot residual and stay within 25 % (this generator's lights do not fall
    off with distance and its lobes are mostly Phong ones, which no physical microfacet
    lobe under a point light matches: the residual is nearly flat along each light's
    distance, and they land 7-21 % off, depending on the MH fit they start from; on
    the physically based presets within 0.2-4 %, ``test_pbr_relight.py``),
    every texel fitted, the map exported and its
    held-out renders better than diffuse on every held-out view; without lights.yaml
    the stage says which file it lacks; with no light in it, a nominal one overhead."""
    import shutil

    from parammap.cli import main
    from parammap.synth.scene import load_scene

    cap, truth, proc = tiny_processed
    work = tmp_path / "proc"
    shutil.copytree(proc, work)
    assert main(["fit-svbrdf", "--out", str(work)]) == 2  # no lights.yaml yet
    assert main(["fit-mh", "--out", str(work), "--lobes", "auto"]) == 0
    assert main(["lights", "--out", str(work)]) == 0
    assert main(["fit-svbrdf", "--out", str(work), "--figures", str(tmp_path / "fig")]) == 0
    m = json.loads((work / "metrics" / "fit-svbrdf-ggx.json").read_text())
    assert m["failed"] == 0 and m["fitted"] == m["texels"]
    assert (tmp_path / "fig" / "svbrdf-ggx_params.png").is_file()
    scene = load_scene(truth / "scene.npz")
    found = np.array(m["light_positions"]["refined_mm"])
    centre = np.array([scene.width_mm / 2, scene.height_mm / 2, 0.0])
    start = np.array(m["light_positions"]["found_mm"])
    for L in scene.light_pos:
        scale = np.linalg.norm(L - centre)
        assert np.linalg.norm(start - L, axis=1).min() < 0.02 * scale, (start, L)
        assert np.linalg.norm(found - L, axis=1).min() < 0.25 * scale, (found, L)
    assert m["light_positions"]["final"] < m["light_positions"]["start"]
    models = ["svbrdf-ggx", "diffuse"]
    assert main(["export", "--out", str(work), *[x for k in models for x in ("--model", k)]]) == 0
    assert main(["holdout", str(cap), "--out", str(work),
                 *[x for k in models for x in ("--model", k)]]) == 0
    h = json.loads((work / "metrics" / "holdout.json").read_text())
    for v in h["views"].values():
        assert v["models"]["svbrdf-ggx"]["mean_diff_8bit"] < \
            v["models"]["diffuse"]["mean_diff_8bit"], v
    # no light found: fitted under a nominal light overhead, and said so
    from parammap.stores.lights import write_lights

    write_lights(work / "camera" / "lights.yaml", [], {"source": "mh-auto"})
    assert main(["fit-svbrdf", "--out", str(work)]) == 0
    m = json.loads((work / "metrics" / "fit-svbrdf-ggx.json").read_text())
    assert m["light_positions"]["nominal"] and m["failed"] == 0


def test_metallic_roughness_and_the_gltf_and_materialx_files(tmp_path):
    """A map of dielectric texels (grey Ks = 0.04 k) and metal ones (coloured Ks, no Kd)
    in glTF's terms: the scale k found from the dielectrics, their albedo and the
    metals' F0 as baseColor, metallic 0 and 1, roughness sqrt(alpha); the glTF file
    read back with pygltflib (its textures match within a level of 8 bits), the
    MaterialX document valid against the MaterialX standard library."""
    import cv2
    import MaterialX as mx
    import pygltflib

    from parammap.cli import main
    from parammap.models.svbrdf import metallic_roughness
    from parammap.stores.params import ParamMap, write_param_map

    rng = np.random.default_rng(5)
    T, S, k = 12, 16, 7.0
    albedo = rng.uniform(0.1, 0.8, (T, S, 3))
    f0 = np.array([1.0, 0.78, 0.34])  # gold
    metal = np.zeros((T, S), bool)
    metal[:, 12:] = True
    P = np.zeros((T, S, SV_SIZE))
    P[..., SV_KD] = np.where(metal[..., None], 0.0, albedo * k / np.pi)
    P[..., SV_KS] = np.where(metal[..., None], f0 * k, 0.04 * k)
    P[..., SV_ALPHA] = rng.uniform(0.02, 0.6, (T, S))
    mr = metallic_roughness(P)
    assert mr["scale_from"] == "dielectric" and np.isclose(mr["scale"], k)
    assert np.allclose(mr["metallic"][~metal], 0) and np.allclose(mr["metallic"][metal], 1)
    assert np.allclose(mr["base_color"][~metal], albedo[~metal], atol=1e-6)
    assert np.allclose(mr["base_color"][metal], f0, atol=1e-6)
    assert np.allclose(mr["roughness"], np.sqrt(P[..., SV_ALPHA]))

    proc = tmp_path / "proc"
    pm = ParamMap("svbrdf", P.astype(np.float32), 160.0, 120.0, attrs={"lights": json.dumps(
        light_doc([[0.0, 0.0, 300.0]], [[1.0, 1.0, 1.0]]))})
    write_param_map(proc / "params" / "svbrdf-ggx.exr", pm)
    assert main(["material", "--out", str(proc)]) == 0
    g = pygltflib.GLTF2().load(str(proc / "params" / "svbrdf-ggx.gltf"))
    mat = g.materials[0].pbrMetallicRoughness
    uri = g.images[g.textures[mat.metallicRoughnessTexture.index].source].uri
    mrt = cv2.imread(str(proc / "params" / uri), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert mrt.shape == (T, S, 3)
    assert np.abs(mrt[..., 1] / 255 - mr["roughness"]).max() <= 0.5 / 255 + 1e-9
    assert np.abs(mrt[..., 2] / 255 - mr["metallic"]).max() <= 0.5 / 255 + 1e-9
    uri = g.images[g.textures[mat.baseColorTexture.index].source].uri
    bc = cv2.imread(str(proc / "params" / uri))[..., ::-1] / 255.0
    lin = np.where(bc <= 0.04045, bc / 12.92, ((bc + 0.055) / 1.055) ** 2.4)
    assert np.abs(lin - mr["base_color"]).max() < 0.01
    pts = g.accessors[g.meshes[0].primitives[0].attributes.POSITION]
    assert np.allclose(pts.max, [0.16, 0.12, 0.0])
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(proc / "params" / "svbrdf-ggx.mtlx"))
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.setDataLibrary(lib)
    ok, msg = doc.validate()
    assert ok, msg
    assert doc.getMaterialNodes()[0].getName() == "parammap"


def test_white_card_sets_the_albedo_scale(tmp_path):
    """Plastics whose highlight is brighter than F0 = 0.04 (Ks = 0.06 k): scaled by the
    dielectrics' F0 their albedo comes out a third low; a white card of stated
    reflectance, read where its relative irradiance is 1 (the radiometry stage's mean
    over a grid of cells, here 16 x 12 with a room's light), gives k within 0.5 % and the
    albedo with it."""
    from parammap.cli import main
    from parammap.models.radiometry import Radiometry
    from parammap.models.svbrdf import card_scale, light_terms, metallic_roughness
    from parammap.stores.params import ParamMap, write_param_map
    from parammap.stores.radiometry import write_radiometry

    rng = np.random.default_rng(6)
    T, S, k, W, H = 12, 16, 5.0, 160.0, 120.0
    lights, weights = np.array([[40.0, 150.0, 350.0]]), np.ones((1, 3))
    ambient = np.array([0.05, 0.06, 0.07])
    albedo = rng.uniform(0.1, 0.8, (T, S, 3))
    P = np.zeros((T, S, SV_SIZE))
    P[..., SV_KD] = albedo * k / np.pi
    P[..., SV_KS] = 0.06 * k
    P[..., SV_ALPHA] = rng.uniform(0.05, 0.4, (T, S))
    mr = metallic_roughness(P)
    rho = mr["base_color"] * (1 - mr["metallic"])[..., None]
    assert abs(np.median(rho / albedo) - 2 / 3) < 0.01
    # the card (reflectance 0.8) at the cells' centres: L = rho / pi * k (e w + a)
    ny, nx = 12, 16
    X, Y = np.meshgrid((np.arange(nx) + 0.5) / nx * W, (np.arange(ny) + 0.5) / ny * H)
    cells = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], -1)
    card = 0.8 / np.pi * k * ((light_terms(cells, lights)[1] @ weights + ambient) @ LUMINANCE)
    scale = np.pi * card.mean() / 0.8
    assert abs(card_scale(scale, W, H, lights, weights, ambient) / k - 1) < 0.005
    proc = tmp_path / "proc"
    pm = ParamMap("svbrdf", P.astype(np.float32), W, H, attrs={"lights": json.dumps(
        light_doc(lights, weights, ambient=ambient))})
    write_param_map(proc / "params" / "svbrdf-ggx.exr", pm)
    write_radiometry(proc / "camera" / "radiometry.json", Radiometry(irradiance_scale=scale), {})
    assert main(["material", "--out", str(proc)]) == 0
    m = json.loads((proc / "metrics" / "material-svbrdf-ggx.json").read_text())
    assert m["scale_from"] == "white_card" and abs(m["albedo_scale"] / k - 1) < 0.005
    mr = metallic_roughness(P, scale=m["albedo_scale"])
    # (glTF takes a dielectric's F0 above 0.04 as a little metal: its diffuse albedo is
    # baseColor (1 - metallic))
    rho = mr["base_color"] * (1 - mr["metallic"])[..., None]
    assert np.allclose(rho, albedo, rtol=0.005)


def test_a_matte_texel_rejects_its_neighbours_lobe_only_where_its_views_see_it():
    """:func:`lobe_rejected` (the repair pass's test for texels fitted without a lobe):
    matte texels seen from 60 views to 72 deg (2 % noise, one pixel's) reject a broad
    lobe of Ks twice their Kd (pbr-bench's matte patches took such lobes from a few
    neighbours whose F test passed on noise, and their albedo came out 17-21 % low);
    texels that carry that lobe do not reject it; and a glossy lobe whose highlight
    none of a texel's views sees (the light's mirror direction outside the views' cap)
    is not rejected, so such a texel still takes its region's highlight."""
    from parammap.models.svbrdf import lobe_rejected

    rng = np.random.default_rng(7)
    B, N = 200, 60
    V, pts = _rig(rng, B, N, 72.0)
    light, w = np.array([[60.0, 160.0, 450.0]]), np.ones((1, 3))
    kd = rng.uniform(0.2, 0.5, (B, 3))
    matte = np.c_[kd, np.zeros((B, 3)), np.ones(B), np.zeros(B)]
    lobe_ks = 2 * kd
    glossy = matte.copy()
    glossy[:, SV_KS], glossy[:, SV_ALPHA] = lobe_ks, 1.0
    pixel = 1 + 0.02 * rng.standard_normal((B, N, 1))
    y_matte, y_lobe = (_render(P, pts, V, light, w) * pixel for P in (matte, glossy))
    ones = np.ones((B, N))
    one = np.ones(B)
    assert lobe_rejected(y_matte, V, ones, pts, light, w, matte, one, lobe_ks).mean() > 0.95
    assert lobe_rejected(y_lobe, V, ones, pts, light, w, matte, one, lobe_ks).mean() < 0.05
    # a near-mirror lobe of a light 70 deg from the normal, seen from a 30 deg cap: its
    # highlight (and GGX's long tail) lies outside the views
    V30, _ = _rig(rng, B, N, 30.0)
    low = np.array([[-400.0, 100.0, 150.0]])
    y30 = _render(matte, pts, V30, low, w) * pixel
    assert lobe_rejected(y30, V30, ones, pts, low, w, matte, np.full(B, 0.01),
                         np.ones((B, 3))).mean() < 0.05


@pytest.mark.parametrize(("alpha", "light"), [
    (0.02, [-90.0, 140.0, 500.0]),
    (0.1, [150.0, -60.0, 420.0]),
])
def test_a_narrow_lobe_the_texels_share_is_found_jointly(alpha, light):
    """:func:`shared_lobe_alpha` (the repair pass's prior on alpha): a 24 x 24 mm patch
    of 1 mm texels, one GGX lobe and Kd varying by texel, seen from 40 cameras 500 mm
    away over a 70 deg cap, 2 % noise. At alpha 0.02 each texel sees the highlight's
    peak in one view at most; its own fit leaves alpha undetermined (its ``Ks alpha^2``
    is what its tails show) and most texels are more than 15 % off, while every
    texel's 9 x 9 window, fitted jointly, finds alpha within 15 % (95 % of them; 5 %
    at the median). Where the texels
    determine alpha themselves (0.1) the joint fit agrees with them."""
    from parammap.models.svbrdf import lobe_profiles, shared_lobe_alpha

    rng = np.random.default_rng(3)
    n, N = 24, 40
    ys, xs = np.mgrid[0:n, 0:n]
    pts = np.c_[60 + xs.ravel(), 40 + ys.ravel(), np.zeros(n * n)].astype(float)
    k = np.arange(N) + 0.5
    z = 1 - (1 - np.cos(np.radians(70))) * k / N
    phi = k * np.pi * (3 - np.sqrt(5))
    s = np.sqrt(1 - z * z)
    cams = 500 * np.stack([s * np.cos(phi), s * np.sin(phi), z], -1) + [70.0, 50.0, 0.0]
    V = cams[None] - pts[:, None]
    V /= np.linalg.norm(V, axis=-1, keepdims=True)
    lights, w = np.array([light]), np.ones((1, 3))
    B = n * n
    P = np.zeros((B, SV_SIZE))
    P[:, SV_KD], P[:, SV_KS], P[:, SV_ALPHA] = rng.uniform(0.2, 0.6, (B, 3)), 0.1, alpha
    y = _render(P, pts, V, lights, w) * (1 + 0.02 * rng.standard_normal((B, N, 1)))
    ones = np.ones((B, N))
    own = fit_svbrdf_batch(y, V, ones, pts, lights, w)["estimate"]
    sig2 = ((y - _render(own, pts, V, lights, w)) ** 2).sum(1) / (N - 3)
    grid = np.geomspace(0.005, 1.0, 48)
    a, b, c = lobe_profiles(y, V, ones, pts, lights, w, own, grid)
    u = shared_lobe_alpha(a.reshape(n, n, 48, 3), b.reshape(n, n, 48, 3),
                          c.reshape(n, n, 3), sig2.reshape(n, n, 3), np.ones((n, n), bool),
                          grid, r=4)
    joint = np.exp(u[4:-4, 4:-4])  # the windows inside the patch
    err = np.abs(joint / alpha - 1)
    assert np.median(err) < 0.05 and np.mean(err < 0.15) > 0.95, np.quantile(err, [0.5, 0.95])
    off = np.abs(own[:, SV_ALPHA] / alpha - 1) > 0.15
    assert off.mean() > 0.5 if alpha < 0.05 else off.mean() < 0.05


def _facing_grid(centre, target, size, n=40):
    """An n x n midpoint grid over a rectangular Lambertian light facing ``target``: the
    reference integral the quadrature is checked against."""
    from parammap.models.lights import _light_frame

    nrm = (target - centre) / np.linalg.norm(target - centre)
    u, v = _light_frame(nrm)
    a = (np.arange(n) + 0.5) / n - 0.5
    A, B = np.meshgrid(a * size[0], a * size[1], indexing="ij")
    p = centre + A.reshape(-1, 1) * u + B.reshape(-1, 1) * v
    return np.c_[p, np.broadcast_to(nrm, p.shape)], np.full((n * n, 3), 1.0 / (n * n))


def test_area_light_quadrature_against_the_exact_irradiance():
    """A Lambertian disc of radius a facing a point at height h gives it
    ``h^2 / (h^2 + a^2)`` of a point light's irradiance of the same intensity; the
    quadrature's points give that within 0.5 % (a = h / 2, 26.6 deg, and h / 20) and a
    rectangle's the 40 x 40 grid's within 0.5 % at points across the surface (a light
    28 deg across, drawn by the most points a light gets), each point an equal share;
    a smaller light's points no farther apart than AREA_STEP_DEG seen from the
    target."""
    from parammap.models.lights import AREA_STEP_DEG, area_light_points, expand_lights

    h = 600.0
    for a in (h / 2, h / 20):
        pts, share = area_light_points([0.0, 0.0, h], "disc", [2 * a, 2 * a])
        assert share.sum() == pytest.approx(1.0)
        e = light_terms(np.zeros(3), pts)[1] @ share
        assert e == pytest.approx(light_terms(np.zeros(3), [[0, 0, h]])[1][0]
                                  * h * h / (h * h + a * a), rel=5e-3), (a, len(pts))
    centre, target = np.array([250.0, 175.0, 550.0]), np.array([100.0, 75.0, 0.0])
    pts, group = expand_lights(centre[None], [{"shape": "rect", "size_mm": [300, 200]}],
                               target)
    assert group.shape == (36, 1) and np.allclose(group.sum(0), 1)  # 28 deg: capped
    gap = np.radians(AREA_STEP_DEG) * np.linalg.norm(centre - target)
    for shape in ("rect", "disc"):
        small, _ = area_light_points(centre, shape, [80.0, 50.0], target_mm=target)
        d = np.linalg.norm(small[:, None, :3] - small[None, :, :3], axis=-1)
        assert 1 < len(small) < 36
        assert np.sort(d + np.eye(len(d)) * 1e9, 1)[:, 0].max() < gap, shape
    fine, wf = _facing_grid(centre, target, (300.0, 200.0))
    probe = np.array([[0.0, 0.0, 0.0], [200.0, 150.0, 0.0], [100.0, 75.0, 0.0]])
    assert np.allclose(light_terms(probe, pts)[1] @ group[:, 0],
                       light_terms(probe, fine)[1] @ wf[:, 0], rtol=5e-3)
    # a point light stays one, shining alike in every direction
    only, g1 = expand_lights([[0.0, 0.0, h]], None)
    assert only.shape == (1, 3) and np.array_equal(g1, np.eye(1))


def test_a_large_area_light_is_integrated_not_taken_for_a_point():
    """Texels under a 300 x 200 mm softbox 580 mm away (28 deg across; rendered with a
    20 x 20 grid over it, 1.5 deg apart), 1 % noise: taken for a point light at its
    centre, GGX alpha comes out 30-40 % rough and Kd 20 % off; integrated over the
    light's 36 points,
    within 2 % and 1.5 % at the median. The light's centre started 10 % of its
    distance off is refined to within 2 % with its extent (from a lab's measured centre
    too, where the found one is 40 % off), and two lights' relative
    intensities come out per light, not per point."""
    from parammap.models.lights import expand_lights

    rng = np.random.default_rng(5)
    B, N = 160, 50
    V, pts = _rig(rng, B, N, 70.0)
    target = np.array([100.0, 75.0, 0.0])
    centre = target + np.array([150.0, 100.0, 550.0])
    ext = [{"shape": "rect", "size_mm": [300.0, 200.0]}]
    fine, wf = _facing_grid(centre, target, (300.0, 200.0), 20)
    P = np.c_[rng.uniform(0.05, 0.4, (B, 3)), rng.uniform(0.5, 2.0, (B, 3)),
              np.exp(rng.uniform(np.log(0.04), np.log(0.4), B)), np.zeros(B)]
    y = _render(P, pts, V, fine, wf) * (1 + 0.01 * rng.standard_normal((B, N, 3)))
    omega = np.ones((B, N))

    def errors(lights, w):
        Q = fit_svbrdf_batch(y, V, omega, pts, lights, w, with_coat=False)["estimate"]
        return (np.median(np.abs(Q[:, SV_ALPHA] / P[:, SV_ALPHA] - 1)),
                np.median(np.abs(Q[:, SV_KD] / P[:, SV_KD] - 1)))

    a_pt, kd_pt = errors(centre[None], np.ones((1, 3)))
    assert a_pt > 0.2 and kd_pt > 0.1, (a_pt, kd_pt)
    points, group = expand_lights(centre[None], ext, target)
    a_area, kd_area = errors(points, group @ np.ones((1, 3)))
    assert a_area < 0.02 and kd_area < 0.015, (a_area, kd_area)
    dist = np.linalg.norm(centre - target)
    off = rng.standard_normal(3)
    start = centre + 0.1 * dist * off / np.linalg.norm(off)
    found, rec = refine_lights(y[:48], V[:48], omega[:48], pts[:48], start[None],
                               extents=ext, target_mm=target)
    assert np.linalg.norm(found[0] - centre) < 0.02 * dist, (found, rec)
    # a lab's measured centre 1 % off, beside a found one 40 % off: the better start
    far = centre + 0.4 * dist * off / np.linalg.norm(off)
    lab = centre + 0.01 * dist * np.array([0.6, 0.0, 0.8])
    found, rec = refine_lights(y[:48], V[:48], omega[:48], pts[:48], far[None], extents=ext,
                               target_mm=target, also_from=lab[None])
    assert rec["started_from"] == "also_from", rec
    assert np.linalg.norm(found[0] - centre) < 0.02 * dist, (found, rec)
    # a second, point light of other colour: the pilot's amplitudes per light
    both = np.vstack([centre, [-80.0, 160.0, 450.0]])
    pts2, g2 = expand_lights(both, ext + [None], target)
    w = np.array([[1.0, 1.0, 1.0], [0.5, 0.6, 0.8]])
    y2 = (_render(P, pts, V, fine, wf) + _render(P, pts, V, both[1:], w[1:])) \
        * (1 + 0.01 * rng.standard_normal((B, N, 3)))
    r = fit_svbrdf_batch(y2, V, omega, pts, pts2, None, group=g2)
    assert r["ks"].shape == (B, 2, 3)
    assert np.allclose(light_weights(r["ks"], r["stdev_ks"]), w, rtol=0.03)


def test_a_measured_area_light_through_the_stage_the_map_and_the_viewer(tmp_path):
    """A capture's measured light reaches the found light nearest it (the lights
    stage: its centre, and its shape where it has a size), the fit integrates over it
    (alpha within 3 % where a point light at its centre gives 20 % or more), the map's
    header keeps the light's points and the lamp they make, renders of the map follow
    the points, and the viewer draws the lamp at its centre."""
    from parammap.models.lights import expand_lights
    from parammap.render import evaluate
    from parammap.stages.fit import fit_svbrdf_map
    from parammap.stages.lights import match_measured
    from parammap.stores.lights import write_lights
    from parammap.stores.observation import write_observation_arrays
    from parammap.stores.params import param_map_from_fit
    from parammap.viewer.layers import layer_info

    found = [{"position_mm": [240.0, 180.0, 560.0]}, {"position_mm": [-90.0, 60.0, 500.0]}]
    measured = [{"position_mm": [250.0, 175.0, 550.0], "size_mm": [300, 200]},
                {"position_mm": [-100.0, 60.0, 480.0]}]  # a point: no size
    match_measured(found, measured)
    assert found[0]["extent"] == {"shape": "rect", "size_mm": [300.0, 200.0]}
    assert "extent" not in found[1]
    assert [lt["measured_mm"] for lt in found] == [m["position_mm"] for m in measured]

    rng = np.random.default_rng(8)
    S, T, N, W, H = 10, 8, 40, 200.0, 150.0
    centre = np.array([250.0, 175.0, 550.0])
    pts, V, target = _map_rig(S, T, W, H, N, 65.0, 600.0)
    P = np.tile([0.2, 0.25, 0.3, 1.0, 1.0, 1.0, 0.12, 0.0], (len(pts), 1))
    fine, wf = _facing_grid(centre, target, (300.0, 200.0), 20)
    y = _render(P, pts, V, fine, wf) * (1 + 0.01 * rng.standard_normal((len(pts), N, 3)))
    obs = write_observation_arrays(tmp_path / "observation.zarr", y.reshape(T, S, N, 3),
                                   V.reshape(T, S, N, 3), np.ones((T, S, N), bool), W, H,
                                   tile=4)
    cfg = {"refine_lights": False, "pool_neighbours": False}
    alphas = {}
    for name, extent in (("point", None), ("area", found[0]["extent"])):
        write_lights(tmp_path / name / "lights.yaml",
                     [{"position_mm": centre.tolist(), **({"extent": extent} if extent else {})}],
                     {"source": "measured"})
        m = fit_svbrdf_map(obs, tmp_path / name / "fit.zarr", tmp_path / name / "lights.yaml",
                           None, cfg, "synchronous", 1)
        assert m["lights"] == 1
        pm = param_map_from_fit(tmp_path / name / "fit.zarr")
        alphas[name] = float(np.median(pm.params[..., SV_ALPHA]))
    assert abs(alphas["point"] / 0.12 - 1) > 0.2 and abs(alphas["area"] / 0.12 - 1) < 0.03, alphas
    assert m["light_positions"]["area_points"] == [36]
    assert pm.lights.position_mm.shape == (36, 6) and pm.lamps[0].tolist() == [centre.tolist()]
    assert layer_info(pm)[0]["lights"] == [centre.tolist()]
    # the map's render under its header's lights is the model under the light's points
    prm = pm.params.reshape(-1, pm.params.shape[-1])[:5]
    at = np.c_[rng.uniform(0, W, 5), rng.uniform(0, H, 5), np.zeros(5)]
    d = np.array([[0.3, 0.2, 0.93]] * 5) / np.linalg.norm([0.3, 0.2, 0.93])
    points, group = expand_lights(centre[None], [found[0]["extent"]], target)
    assert np.allclose(evaluate("svbrdf", prm, d, at, pm.lights),
                       svbrdf_eval(prm, at, d, points, group @ pm.lamps[1]), rtol=1e-4)
    # relit under two new lamps (72 points): the viewer draws the two lamps
    lamps = (np.array([[-150.0, 80.0, 500.0], [300.0, 200.0, 400.0]]),
             np.array([[1.0, 0.9, 0.8], [0.5, 0.5, 0.6]]), [found[0]["extent"]] * 2)
    new, group = expand_lights(lamps[0], lamps[2], target)
    q = pm.relit(new, group @ lamps[1], lamps=lamps)
    assert q.lights.position_mm.shape == (72, 6)
    assert layer_info(q)[0]["lights"] == lamps[0].tolist()
    assert layer_info(q)[0]["light_weights"] == lamps[1].tolist()




def test_an_undetermined_lobe_takes_the_neighbours_width():
    """The repair pass (:func:`pool_svbrdf_tile`) on a uniform glossy patch (GGX alpha
    0.08, Ks 0.1, 2 % noise): a texel whose tile fit is a spike (alpha 0.008, ln alpha
    sd 0.7, Ks 2.4 with sd 3.4, as pbr-mirror's plastic had where one view caught a
    firefly) takes the neighbours' lobe, its amplitude being undetermined; the same
    spike with a determined amplitude (a scratch) keeps its own."""
    from parammap.models.svbrdf import fit_svbrdf_tile, pool_svbrdf_tile

    rng = np.random.default_rng(11)
    S = T = 16
    W = H = 48.0
    N = 60
    pts, V, target = _map_rig(S, T, W, H, N, 70.0, 500.0)
    light, w = (target + np.array([60.0, 40.0, 450.0]))[None], np.ones((1, 3))
    P = np.tile([0.3, 0.3, 0.3, 0.1, 0.1, 0.1, 0.08, 0.0], (len(pts), 1))
    y = _render(P, pts, V, light, w) * (1 + 0.02 * rng.standard_normal((len(pts), N, 1)))
    rad, dirs = y.reshape(T, S, N, 3), V.reshape(T, S, N, 3)
    valid = np.ones((T, S, N), bool)
    geom = {"origin": (0, 0), "grid": (S, T, W, H), "lights_mm": light, "weights": w}
    fields = fit_svbrdf_tile(rad, dirs, valid, **geom)
    assert np.all(np.abs(fields[FitArray.PARAMS][..., SV_ALPHA] / 0.08 - 1) < 0.2)
    spike, scratch = (5, 6), (10, 9)
    for at, sd_ks in ((spike, 3.4), (scratch, 0.05)):
        fields[FitArray.PARAMS][at][SV_KS] = 2.4
        fields[FitArray.PARAMS][at][SV_ALPHA] = 0.008
        fields[FitArray.SD][at][SV_KS] = sd_ks
        fields[FitArray.SD][at][SV_ALPHA] = 0.0056
    out = pool_svbrdf_tile(fields, rad, dirs, valid, (0, 0), **geom)
    got = out[FitArray.PARAMS]
    assert abs(got[spike][SV_ALPHA] / 0.08 - 1) < 0.1 and out[FitArray.CHANGED][spike]
    assert abs(got[spike][SV_KS] @ LUMINANCE / 0.1 - 1) < 0.1
    assert got[scratch][SV_ALPHA] == pytest.approx(0.008) and not out[FitArray.CHANGED][scratch]



def test_a_spike_through_one_view_has_honest_sds():
    """Nine texels of a uniform glossy patch (GGX alpha 0.08, Ks 0.1, 2 % noise, 60
    views to 70 deg) whose brightest view, near the light's mirror direction, reads 4x
    too bright (a glint, a Monte Carlo firefly). Each fit is a spike through that view
    (alpha 0.03-0.05, Ks 0.18-0.31), which leaves the view no residual: the sandwich
    alone stated Ks's sd as 1-3 % of its value, its error 20-230 sds. Bounded by what
    leaving that view out changes, the sds cover the errors: Ks and ln alpha within
    3 sds of the truth on at least 8 of the 9."""
    rng = np.random.default_rng(11)
    N = 60
    pts, V, target = _map_rig(16, 16, 48.0, 48.0, N, 70.0, 500.0)
    light = (target + np.array([60.0, 40.0, 450.0]))[None]
    P = np.tile([0.3, 0.3, 0.3, 0.1, 0.1, 0.1, 0.08, 0.0], (len(pts), 1))
    y = _render(P, pts, V, light, np.ones((1, 3)))
    y *= 1 + 0.02 * rng.standard_normal(y.shape[:2] + (1,))
    rows, cols = np.meshgrid(np.arange(4, 12, 3), np.arange(4, 12, 3), indexing="ij")
    spiked = (rows * 16 + cols).ravel()
    y, V, pts = y[spiked], V[spiked], pts[spiked]
    y[np.arange(9), y.mean(-1).argmax(1)] *= 4.0
    r = fit_svbrdf_batch(y, V, np.ones((9, N)), pts, light, np.ones((1, 3)))
    est, sd = r["estimate"], r["stdev"]
    assert np.all(est[:, SV_ALPHA] < 0.06) and np.all(est[:, SV_KS] @ LUMINANCE > 0.15)
    z_ks = np.abs(est[:, SV_KS] @ LUMINANCE - 0.1) / (sd[:, SV_KS] @ LUMINANCE)
    z_u = np.abs(np.log(est[:, SV_ALPHA] / 0.08)) / (sd[:, SV_ALPHA] / est[:, SV_ALPHA])
    assert (z_ks < 3).sum() >= 8 and (z_u < 3).sum() >= 8, (z_ks, z_u)
