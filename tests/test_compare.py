"""``python -m parammap.compare``: two runs' outputs compared by content (issue 18)."""

from __future__ import annotations

import json
import shutil

import numpy as np

from parammap.compare import compare_trees, main
from parammap.stores.exr import write_exr


def _tree(root, bump=0.0, pixel=False):
    import cv2
    import zarr

    (root / "metrics").mkdir(parents=True)
    (root / "metrics" / "fit.json").write_text(json.dumps(
        {"rmse": [0.1, 0.2 + bump, 0.3], "seconds": 12.0 + 100 * bump, "model": "mh-1"}))
    write_exr(root / "map.exr", {"R": np.full((4, 5), 1.0 + bump, np.float32)},
              {"software": "parammap"})
    g = zarr.open_group(root / "fit.zarr", mode="w")
    a = g.create_array("params", shape=(4, 5), dtype="float32", fill_value=np.nan)
    a[:] = np.arange(20, dtype=np.float32).reshape(4, 5)
    img = np.zeros((8, 8, 3), np.uint8)
    img[2, 3] = 255 if pixel else 0
    cv2.imwrite(str(root / "fig.png"), img)


def test_identical_trees_agree_and_timings_are_ignored(tmp_path, capsys):
    _tree(tmp_path / "a")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    data = json.loads((tmp_path / "b" / "metrics" / "fit.json").read_text())
    data["seconds"] = 99.0  # a timing: differs on every run
    (tmp_path / "b" / "metrics" / "fit.json").write_text(json.dumps(data))
    diffs, only_a, only_b = compare_trees(tmp_path / "a", tmp_path / "b")
    assert diffs == [] and only_a == [] and only_b == []
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert "4 identical" in capsys.readouterr().out


def test_a_moved_number_a_changed_pixel_and_a_missing_file_are_found(tmp_path):
    _tree(tmp_path / "a")
    _tree(tmp_path / "b", bump=1e-7, pixel=True)
    (tmp_path / "b" / "extra.csv").write_text("x\n")
    diffs, only_a, only_b = compare_trees(tmp_path / "a", tmp_path / "b")
    by = {d.path: d for d in diffs}
    assert set(by) == {"metrics/fit.json", "map.exr", "fig.png"}
    assert not by["metrics/fit.json"].exact and 0 < by["metrics/fit.json"].max_rel < 1e-6
    assert by["fig.png"].exact
    assert only_b == ["extra.csv"] and only_a == []
    # within float precision when asked, but never for a changed pixel
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--rtol", "1e-6"]) == 1
    (tmp_path / "b" / "fig.png").unlink()
    shutil.copy(tmp_path / "a" / "fig.png", tmp_path / "b" / "fig.png")
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--rtol", "1e-6"]) == 0
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 1


def test_added_metadata_counts_only_when_asked(tmp_path):
    _tree(tmp_path / "a")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    data = json.loads((tmp_path / "b" / "metrics" / "fit.json").read_text())
    data["units"] = {"rmse": "radiance"}  # metadata a newer version writes
    (tmp_path / "b" / "metrics" / "fit.json").write_text(json.dumps(data))
    (d,), _, _ = compare_trees(tmp_path / "a", tmp_path / "b")
    assert d.added == ["/units"] and not d.what
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 1
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--allow-added"]) == 0
    # removed metadata is a difference either way
    assert main([str(tmp_path / "b"), str(tmp_path / "a"), "--allow-added"]) == 1
