"""A bracket is merged the same whatever order its photos are listed in, and photos
that contradict their exposure times are named and left out (issue 45)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import yaml

from parammap.cli import main
from parammap.stores.hdr import read_hdr


def _edit(cap, fn):
    """Rewrite ``capture.yaml`` of ``cap`` through ``fn(data)``."""
    path = cap / "capture.yaml"
    data = yaml.safe_load(path.read_text())
    fn(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def _process(cap, out, view="v000"):
    assert main(["response", str(cap), "--out", str(out)]) == 0
    assert main(["hdr", str(cap), "--out", str(out), "--view", view]) == 0
    return json.loads((out / "hdr" / f"{view}.json").read_text()), read_hdr(
        out / "hdr" / f"{view}.exr")


def test_the_order_a_bracket_is_listed_in_changes_nothing(tiny_copy, tmp_path):
    other = tmp_path / "reversed"
    shutil.copytree(tiny_copy, other)
    _edit(other, lambda d: [v.__setitem__("exposures", v["exposures"][::-1])
                            for v in d["views"]])
    stats_a, frame_a = _process(tiny_copy, tmp_path / "a")
    stats_b, frame_b = _process(other, tmp_path / "b")
    assert (tmp_path / "a" / "camera" / "response.csv").read_text().split("\n", 2)[2] == \
        (tmp_path / "b" / "camera" / "response.csv").read_text().split("\n", 2)[2]
    for a, b in zip(frame_a, frame_b, strict=True):
        np.testing.assert_array_equal(a, b)
    assert "left_out" not in stats_a and "left_out" not in stats_b


def test_two_photos_claiming_one_time_are_named_and_one_left_out(tiny_copy, tmp_path):
    def same_time(d):
        ex = d["views"][0]["exposures"]
        ex[1]["exposure_s"] = ex[0]["exposure_s"]
    _edit(tiny_copy, same_time)
    stats, frame = _process(tiny_copy, tmp_path / "p")
    files = sorted(e["file"] for e in yaml.safe_load(
        (tiny_copy / "capture.yaml").read_text())["views"][0]["exposures"])
    assert [x["file"] for x in stats["left_out"]] == [files[1].split("/")[-1]]
    assert "exposure time" in stats["left_out"][0]["reason"]
    assert np.isfinite(frame[0]).all()
    # the run's HDR metrics name it too
    from parammap.stages.hdr import gather_hdr_metrics

    m = gather_hdr_metrics([tmp_path / "p" / "hdr" / "v000.json"], tmp_path / "hdr.json")
    assert m["photos_left_out"]["v000"] == stats["left_out"]


def test_a_photo_brighter_than_a_longer_exposure_is_left_out(tiny_copy, tmp_path):
    def swapped(d):  # the two photos' times exchanged: the longer claim is the darker
        ex = d["views"][0]["exposures"]
        ex[0]["exposure_s"], ex[1]["exposure_s"] = ex[1]["exposure_s"], ex[0]["exposure_s"]
    _edit(tiny_copy, swapped)
    stats, _ = _process(tiny_copy, tmp_path / "p")
    assert len(stats["left_out"]) == 1 and "brighter than" in stats["left_out"][0]["reason"]
