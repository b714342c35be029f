"""Facts written in more than one language (schema, Snakemake rules) must agree with
the Python source of truth (issue 18)."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

from parammap.config import schema
from parammap.hdr import recover_response
from parammap.models.sh import HEMISPHERES

ROOT = Path(__file__).resolve().parents[1]


def test_sh_hemisphere_modes_agree():
    fit = schema()["properties"]["fit"]["properties"]["sh"]["properties"]["models"]
    pattern = fit["items"]["pattern"]
    assert re.search(r"\(([a-z|]+)\)", pattern).group(1).split("|") == list(HEMISPHERES)
    smk = (ROOT / "workflow" / "rules" / "fit.smk").read_text()
    hemi = re.search(r'hemi="([a-z|]+)"', smk).group(1).split("|")
    assert hemi == list(HEMISPHERES)


def test_debevec_smoothness_default_agrees():
    default = schema()["properties"]["hdr"]["properties"]["smoothness"]["default"]
    assert inspect.signature(recover_response).parameters["smoothness"].default == default


def test_stores_carry_dimension_names(tmp_path):
    import zarr

    from parammap.models.sh import fit_sh_map
    from parammap.observation import write_observation_arrays
    from parammap.synth.cases import phong_case

    case = phong_case(texels=4, level=1, m=10)
    obs = write_observation_arrays(tmp_path / "obs.zarr", case.radiance, case.direction,
                                   case.valid, 100.0, 100.0, tile=4)
    fit_sh_map(obs, tmp_path / "sh.zarr", "rlsop", 3, {}, "synchronous", 1,
               log=lambda *_: None)
    o = zarr.open_group(obs, mode="r")
    assert o["radiance"].metadata.dimension_names == ("row", "col", "view", "channel")
    assert o["noise"].metadata.dimension_names == ("row", "col", "view")
    f = zarr.open_group(tmp_path / "sh.zarr", mode="r")
    assert f["coeffs"].metadata.dimension_names[:2] == ("row", "col")


def test_cli_one_line_for_bad_input_traceback_for_bugs(tmp_path, monkeypatch, capsys):
    import pytest

    import parammap.cli as cli
    from parammap.capture import CaptureError
    from parammap.errors import InputError

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
