"""Every capture error of capture-format.md: one line naming file and key, exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from parammap.cli import main


def _edit(cap, fn):
    y = cap / "capture.yaml"
    data = yaml.safe_load(y.read_text())
    fn(data)
    y.write_text(yaml.safe_dump(data, sort_keys=False))


def _run(cap, capsys):
    before = sorted(p.name for p in cap.rglob("*"))
    rc = main(["validate-capture", str(cap)])
    out, err = capsys.readouterr()
    assert sorted(p.name for p in cap.rglob("*")) == before, "validation wrote files"
    return rc, out, err


def _del_surface_width(d):
    del d["surface"]["width_mm"]


def _bad_dict(d):
    d["markers"]["dictionary"] = "DICT_9X9_7"


def _missing_file(d):
    d["views"][1]["exposures"][0]["file"] = "views/nope.png"


def _outside(d):
    d["views"][0]["exposures"][1]["file"] = "../outside.png"


def _neg_exposure(d):
    d["views"][2]["exposures"][0]["exposure_s"] = -0.5


def _zero_exposure(d):
    d["views"][2]["exposures"][1]["exposure_s"] = 0


def _few_markers(d):
    d["markers"]["items"] = d["markers"]["items"][:3]


def _bad_corners(d):
    d["markers"]["items"][0]["corners_mm"] = [[0, 0], [1, 1]]


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (_del_surface_width, "surface.width_mm", "missing key"),
        (_bad_dict, "markers.dictionary", "unknown ArUco dictionary"),
        (_missing_file, "views[1].exposures[0].file", "does not exist"),
        (_outside, "views[0].exposures[1].file", "leaves the capture directory"),
        (_neg_exposure, "views[2].exposures[0].exposure_s", "must be positive"),
        (_zero_exposure, "views[2].exposures[1].exposure_s", "must be positive"),
        (_few_markers, "markers.items", "at least 4 markers"),
        (_bad_corners, "markers.items[0].corners_mm", "4 corners"),
    ],
)
def test_yaml_errors(tiny_copy, capsys, edit, key, words):
    if edit is _outside:
        (tiny_copy.parent / "outside.png").write_bytes(
            (tiny_copy / "views" / "v000_0.png").read_bytes())
    _edit(tiny_copy, edit)
    rc, out, err = _run(tiny_copy, capsys)
    assert rc == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert "capture.yaml" in lines[0] and key in lines[0] and words in lines[0]


def test_mismatched_image_size(tiny_copy, capsys):
    import cv2

    p = tiny_copy / "views" / "v003_1.png"
    img = cv2.imread(str(p))
    cv2.imwrite(str(p), img[:-10])
    rc, _, err = _run(tiny_copy, capsys)
    assert rc == 2
    assert "views[3].exposures[1].file" in err and "differs" in err and len(err.splitlines()) == 1
    assert "views/v003_1.png" in err  # the file, not only its key


def test_unreadable_image(tiny_copy, capsys):
    p = tiny_copy / "views" / "v004_0.png"
    p.write_bytes(p.read_bytes()[:200])
    rc, _, err = _run(tiny_copy, capsys)
    assert rc == 2
    assert "views[4].exposures[0].file" in err and "v004_0.png" in err
    assert len(err.splitlines()) == 1


def test_not_yaml(tiny_copy, capsys):
    (tiny_copy / "capture.yaml").write_text("surface: [unclosed\n")
    rc, _, err = _run(tiny_copy, capsys)
    assert rc == 2 and "not valid YAML" in err


def test_good_capture_cli_exit_zero(tiny_capture):
    r = subprocess.run([sys.executable, "-m", "parammap", "validate-capture",
                        str(tiny_capture[0])], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout


def _str_width(d):
    d["surface"]["width_mm"] = "wide"


def _yes_holdout(d):
    d["views"][3]["holdout"] = "yes"


def _no_exposures(d):
    d["views"][1]["exposures"] = []


def _bool_exposure(d):
    d["views"][0]["exposures"][0]["exposure_s"] = True


def _missing_file_key(d):
    del d["views"][4]["exposures"][1]["file"]


def _ambient_all(d):
    d["ambient"] = {"share": 1.0}


def _ambient_rgb(d):
    d["ambient"] = {"share": [0.1, 0.2]}


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (_str_width, "surface.width_mm", "must be a number (got 'wide')"),
        (_ambient_all, "ambient.share", "must be a number in [0, 1) or three (R, G, B)"),
        (_ambient_rgb, "ambient.share", "must be a number in [0, 1) or three (R, G, B)"),
        (_yes_holdout, "views[3].holdout", "must be true or false"),
        (_no_exposures, "views[1].exposures", "no exposures"),
        (_bool_exposure, "views[0].exposures[0].exposure_s", "must be a number"),
        (_missing_file_key, "views[4].exposures[1].file", "missing key"),
    ],
)
def test_capture_schema_names_the_key(tiny_copy, capsys, edit, key, words):
    """capture.yaml is checked against schemas/capture.schema.yaml before anything
    else; each broken value is named by its key path."""
    _edit(tiny_copy, edit)
    rc, out, err = _run(tiny_copy, capsys)
    assert rc == 2 and out == ""
    line = err.strip()
    assert "\n" not in line and f"capture.yaml: {key}: {words}" in line, line
