"""Printable marker and board sheets (issue 45, item 1): rasterised at 600 dpi, every
marker and board corner is found where the layout written beside the sheet says."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from parammap.cli import main
from parammap.errors import InputError
from parammap.sheets import (
    board_sheet,
    check_board,
    check_markers,
    marker_layout,
    marker_sheet,
)


@pytest.mark.parametrize("width, height, dictionary, marker, count", [
    (297.0, 210.0, "DICT_5X5_250", 42.0, 8),   # A4 poster, the defaults' marker size
    (500.0, 350.0, "DICT_4X4_50", 30.0, 12),   # a larger surface, more markers
    (150.0, 100.0, "DICT_6X6_250", 20.0, 4),   # a small swatch, corners only
])
def test_marker_sheet_shows_every_marker_at_its_layout_mm(width, height, dictionary,
                                                          marker, count):
    sheet, layout = marker_sheet(width, height, dictionary, marker, count)
    check = check_markers(sheet, layout)
    assert check["detected"] == count and not check["missing"], check
    assert check["max_corner_error_mm"] < 0.05, check  # 600 dpi: 0.042 mm a pixel
    items = layout["markers"]["items"]
    assert [it["id"] for it in items] == list(range(count))
    c = np.array([it["corners_mm"] for it in items])  # (n, 4, 2): TL, TR, BR, BL, y up
    assert np.allclose(c[:, 1, 0] - c[:, 0, 0], marker) and np.allclose(
        c[:, 0, 1] - c[:, 3, 1], marker)
    inside = (c[..., 0] > 0) & (c[..., 0] < width) & (c[..., 1] > 0) & (c[..., 1] < height)
    assert not inside.any()  # around the surface, never on it
    assert layout["surface"] == {"width_mm": width, "height_mm": height}


def test_marker_layout_puts_eight_markers_at_corners_and_midpoints():
    """Clockwise from the top left, ``gap`` outside the surface: the layout the synthetic
    generator also prints into its captures."""
    W, H, s, g = 300.0, 200.0, 40.0, 10.0
    items = marker_layout(W, H, s, g, 8)
    tl = [np.asarray(it["corners_mm"])[0] for it in items]  # each marker's top-left
    want = [(-g - s, H + g + s), ((W - s) / 2, H + g + s), (W + g, H + g + s),
            (W + g, (H + s) / 2), (W + g, -g), ((W - s) / 2, -g), (-g - s, -g),
            (-g - s, (H + s) / 2)]
    assert np.allclose(tl, want)


@pytest.mark.parametrize("args", [(7, 5, 30.0, 22.0, "DICT_4X4_50"),
                                  (10, 7, 20.0, 14.4, "DICT_5X5_100"),
                                  (5, 8, 25.0, 20.0, "DICT_6X6_250")])
def test_board_sheet_is_found_as_the_calibration_stage_finds_it(args):
    sheet, layout = board_sheet(*args)
    check = check_board(sheet, layout)
    assert check["detected"] == check["corners"] == (args[0] - 1) * (args[1] - 1), check
    assert check["max_corner_error_mm"] < 0.05, check
    assert layout["calibration"]["board"] == "charuco"


def test_cli_writes_the_sheets_and_their_layouts(tmp_path):
    assert main(["markers", "--width-mm", "200", "--height-mm", "150",
                 "--out", str(tmp_path)]) == 0
    assert main(["board", "--out", str(tmp_path)]) == 0
    for name in ("markers", "board"):
        for ext in ("pdf", "svg", "png", "yaml"):
            assert (tmp_path / f"{name}.{ext}").stat().st_size > 0
    layout = yaml.safe_load((tmp_path / "markers.yaml").read_text())
    assert layout["markers"]["dictionary"] == "DICT_5X5_250"
    assert len(layout["markers"]["items"]) == 8
    # the PDF is the page's true size: 72 points an inch
    pdf = (tmp_path / "board.pdf").read_bytes()
    box = [float(x) for x in pdf.split(b"/MediaBox [")[1].split(b"]")[0].split()]
    assert abs(box[2] / 72 * 25.4 - (7 * 30 + 30)) < 0.01  # squares + margins, mm


@pytest.mark.parametrize("call, match", [
    (lambda: marker_layout(100, 100, 20, 5, 6), "multiple of 4"),
    (lambda: marker_sheet(100, 100, "DICT_NOPE", 20), "unknown ArUco dictionary"),
    (lambda: marker_sheet(100, 100, "DICT_4X4_50", 20, 60), "has 50 markers"),
    (lambda: board_sheet(5, 4, 20.0, 25.0, "DICT_4X4_50"), "smaller than the square"),
])
def test_bad_sheet_settings_name_the_problem(call, match):
    with pytest.raises(InputError, match=match):
        call()
