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
