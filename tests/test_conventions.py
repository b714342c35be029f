"""Facts written in more than one language (schema, Snakemake rules) must agree with
the Python source of truth (issue 18)."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
import pytest

from parammap.config import schema
from parammap.conventions import SH_BAKED
from parammap.conventions import SH_HEMISPHERES as HEMISPHERES
from parammap.stages.hdr import recover_response

ROOT = Path(__file__).resolve().parents[1]


def test_sh_hemisphere_modes_agree():
    fit = schema()["properties"]["fit"]["properties"]["sh"]["properties"]["models"]
    pattern = fit["items"]["pattern"]
    assert re.search(r"\(([a-z|]+)\)", pattern).group(1).split("|") == list(HEMISPHERES)
    smk = (ROOT / "workflow" / "rules" / "fit.smk").read_text()
    hemi = re.search(r'hemi="([a-z|]+)"', smk).group(1).split("|")
    # the projections' rule, and the bake's for SH baked from an MH fit
    assert hemi == [h for h in HEMISPHERES if h not in SH_BAKED]
    for h in SH_BAKED:
        assert f'fit/sh-{h}-{{{{nc}}}}.zarr' in smk


def test_debevec_smoothness_default_agrees():
    default = schema()["properties"]["hdr"]["properties"]["smoothness"]["default"]
    assert inspect.signature(recover_response).parameters["smoothness"].default == default


def test_stores_open_as_labelled_xarray_datasets(tmp_path):
    """Observation map and fit stores carry zarr dimension names: xarray labels them."""
    xr = pytest.importorskip("xarray")

    from parammap.stages.fit import fit_sh_map
    from parammap.stores.observation import write_observation_arrays
    from parammap.synth.cases import phong_case

    case = phong_case(texels=4, level=1, m=10)
    obs = write_observation_arrays(tmp_path / "obs.zarr", case.radiance, case.direction,
                                   case.valid, 100.0, 100.0, tile=4)
    fit_sh_map(obs, tmp_path / "sh.zarr", "rlsop", 3, {}, "synchronous", 1)
    o = xr.open_zarr(obs, consolidated=False)
    assert o["radiance"].dims == ("row", "col", "view", "channel")
    assert o["noise"].dims == ("row", "col", "view")
    assert o.sizes["view"] == case.radiance.shape[2]
    assert "radiance" in o["radiance"].attrs["units"]
    f = xr.open_zarr(tmp_path / "sh.zarr", consolidated=False)
    assert f["coeffs"].dims[:2] == ("row", "col") and f["status"].dims == ("row", "col")
    assert f.sizes["row"] == 4
    assert "FitStatus" in f["status"].attrs["units"] and f["mpr"].attrs["units"] == "percent"


def test_cli_one_line_for_bad_input_traceback_for_bugs(tmp_path, monkeypatch, capsys):
    import pytest

    import parammap.cli as cli
    from parammap.errors import InputError
    from parammap.stores.capture import CaptureError

    assert issubclass(CaptureError, InputError)
    # bad input: exit 2 and one line naming it
    assert cli.main(["summary", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]

    def bug(_):
        raise ValueError("a bug, not an input")

    monkeypatch.setitem(cli._COMMANDS, "summary", bug)
    with pytest.raises(ValueError, match="a bug"):
        cli.main(["summary", str(tmp_path / "missing"), "--out", str(tmp_path)])


# Forms the MH/SH layouts and status codes were once spelled out in, outside
# parammap.conventions (issue 18): index arithmetic, lobe counts from a length, channel
# names, the SH normalisation, the hemisphere list, and status codes as bare numbers.
_LAYOUT_PATTERNS = {
    "MH index arithmetic": r"\b\d+ \+ [56] \* \w+ ?[:\],)]",
    "lobe count from a length": r"- 4\) // 6|\b4::6\b",
    "MH channel names": r"lobe\{k|\"Kd\.R\", \"Kd\.G\"",
    "SH channel names": r"sh\.\{c\}",
    "SH normalisation": r"factorial\(",
    "SH hemisphere list": r"\"zh\", \"mirror\"",
    "status as a number": r"status\"?\]?(\[[^\]]*\])*\s*(==|!=|=)\s*[0-3]\b",
    "luminance weights": r"0\.2126",
}


def test_layouts_and_status_codes_only_in_conventions():
    hits = []
    for path in sorted((ROOT / "src" / "parammap").rglob("*.py")):
        if path.name == "conventions.py":
            continue
        text = path.read_text()
        for what, pattern in _LAYOUT_PATTERNS.items():
            for m in re.finditer(pattern, text):
                line = text.count("\n", 0, m.start()) + 1
                hits.append(f"{path.relative_to(ROOT)}:{line}: {what}: {m.group(0)!r}")
    assert not hits, "\n".join(hits)


def test_viewer_constants_are_generated_from_conventions():
    from parammap.conventions import sh_norms
    from parammap.viewer import glsl_constants
    from parammap.viewer.layers import SH_MAX_BANDS

    page = (ROOT / "src" / "parammap" / "viewer" / "index.html").read_text()
    assert "//@CONVENTIONS@" in page and "D.glsl" in page
    # nothing the Python side defines is re-derived in the page
    for derived in ("Math.PI", "factorial", "Klm", "0.2126"):
        assert derived not in page, derived
    glsl = glsl_constants()
    klm = re.search(r"KLM\[(\d+)\] = float\[\d+\]\(([^)]*)\)", glsl)
    values = np.array([float(x) for x in klm.group(2).split(",")])
    want = np.array([[sh_norms(SH_MAX_BANDS)[l, m] if m <= l else 0.0
                      for m in range(SH_MAX_BANDS)] for l in range(SH_MAX_BANDS)]).ravel()
    assert int(klm.group(1)) == SH_MAX_BANDS ** 2
    np.testing.assert_allclose(values, want, rtol=1e-8)


def test_undistortion_grid_inverts_the_python_distortion():
    import base64

    from parammap.geometry import distort_normalized
    from parammap.stages.calibration import Intrinsics
    from parammap.viewer import undistortion_grid

    K = np.array([[1800.0, 0.4, 1010.0], [0.0, 1795.0, 740.0], [0.0, 0.0, 1.0]])
    intr = Intrinsics(K, np.array([-0.21, 0.11, 0.001, -0.0007, -0.02]), (2000, 1500))
    g = undistortion_grid(intr)
    xy = np.frombuffer(base64.b64decode(g["xy"]), "<f4").reshape(g["rows"], g["cols"], 2)
    back = distort_normalized(xy.astype(float), intr.dist)
    u, v = np.meshgrid(np.linspace(0, 1999, g["cols"]), np.linspace(0, 1499, g["rows"]))
    px = np.stack([K[0, 0] * back[..., 0] + K[0, 1] * back[..., 1] + K[0, 2],
                   K[1, 1] * back[..., 1] + K[1, 2]], -1)
    assert np.abs(px - np.stack([u, v], -1)).max() < 2e-3  # pixels (float32 storage)


def test_workflow_paths_are_the_processed_layout():
    """Every processed-folder path a Snakemake rule names is one of
    :class:`parammap.stores.paths.Processed`'s (the layout is written once in Python)."""
    import inspect as ins

    from parammap.stores.paths import Processed

    proc = Processed("P")
    patterns = []
    for name, member in ins.getmembers(Processed):
        if name.startswith("_") or name == "root":
            continue
        if isinstance(member, property):
            patterns.append(re.escape(getattr(proc, name).as_posix()))
        elif callable(member):
            patterns.append(re.escape(getattr(proc, name)("\0").as_posix()).replace(
                "\0", ".+"))
    rules = "\n".join(p.read_text() for p in (ROOT / "workflow" / "rules").glob("*.smk"))
    found = re.findall(r'\{PROC\}/\{\{?(?:sid|wc\.sid)\}?\}/([^"]+)"', rules)
    assert len(found) > 20
    for rel in found:
        path = "P/" + re.sub(r"\{\{?[^{}]+\}\}?", "X", rel)
        assert any(re.fullmatch(p, path) for p in patterns), rel


def test_hdr_frames_carry_provenance(tiny_processed):
    """Every merged frame names the software and digests of its config and response."""
    from parammap.config import validate_config
    from parammap.stores.exr import read_exr
    from parammap.stores.hdr import load_response
    from parammap.stores.metrics import digest
    from parammap.stores.paths import Processed

    _, _, out = tiny_processed
    proc = Processed(out)
    _, header = read_exr(proc.hdr("v000"))
    assert header["software"].startswith("parammap ")
    assert header["config_digest"] == digest(validate_config({"captures": {"x": "."}})["hdr"])
    assert header["response_digest"] == digest(load_response(proc.response_csv))
    assert digest({"a": 1, "b": [1.0, 2.0]}) == digest({"b": np.array([1.0, 2.0]), "a": 1})
    assert digest({"a": 1}) != digest({"a": 2})


def test_models_are_pure_numerics():
    """parammap.models: no storage, scheduling, plotting or paths (issue 18)."""
    forbidden = re.compile(r"^\s*(import|from)\s+(zarr|dask|matplotlib|pathlib|yaml)\b"
                           r"|^\s*from\s+\.\.(\.)?(fitting|observation|report|figures|paths|"
                           r"params|cli)\b", re.M)
    for path in (ROOT / "src" / "parammap" / "models").rglob("*.py"):
        hit = forbidden.search(path.read_text())
        assert hit is None, f"{path.relative_to(ROOT)}: {hit.group(0).strip()}"
