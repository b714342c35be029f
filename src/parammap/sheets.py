"""Printable sheets: the ArUco markers that go around a surface and a ChArUco
calibration board, at true scale (PDF and SVG, PNG preview), each with a scale bar and
its layout in the capture format (``docs/reference/capture-format.md``): the markers'
corners in mm in the surface frame, the board's squares and dictionary.

A sheet is checked by rasterising it (600 dpi) and detecting what it shows: every
marker found, its corners where the layout says (:func:`check_markers`,
:func:`check_board`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from .errors import InputError
from .stores.capture import aruco_dictionary

logger = logging.getLogger(__name__)

__all__ = ["Sheet", "board_sheet", "check_board", "check_markers", "marker_layout",
           "marker_sheet", "rasterise"]

MM_PER_INCH = 25.4
MARGIN_MM = 15.0  # white paper around what is printed (printers do not print to the edge)
CHECK_DPI = 600


@dataclass
class Sheet:
    """A drawn sheet: the figure (page ``width_mm`` x ``height_mm``, axes in page mm,
    origin bottom-left) and where the surface frame's origin lies on the page."""

    figure: Any
    width_mm: float
    height_mm: float
    origin_mm: tuple[float, float]


def marker_layout(width_mm: float, height_mm: float, marker_mm: float, gap_mm: float,
                  count: int = 8) -> list[dict]:
    """``count`` markers (a multiple of 4) on a ring around the surface ``gap_mm`` from
    its edges: the four corners, then evenly along each side, clockwise from the top
    left. Each item: ``id`` and ``corners_mm`` (top-left, top-right, bottom-right,
    bottom-left, surface frame: origin bottom-left, y up)."""
    if count < 4 or count % 4:
        raise InputError(f"markers: --count must be a multiple of 4, at least 4 (got {count})")
    if marker_mm <= 0 or gap_mm < 0:
        raise InputError("markers: marker size must be positive and the gap not negative")
    s, g, W, H = marker_mm, gap_mm, width_mm, height_mm
    lo_x, hi_x, lo_y, hi_y = -g - s, W + g, -g - s, H + g
    per_side = count // 4
    origins = []
    for f in np.arange(per_side) / per_side:
        origins.append((lo_x + f * (hi_x - lo_x), hi_y, 0))  # top, left to right
    for f in np.arange(per_side) / per_side:
        origins.append((hi_x, hi_y - f * (hi_y - lo_y), 1))  # right, top to bottom
    for f in np.arange(per_side) / per_side:
        origins.append((hi_x - f * (hi_x - lo_x), lo_y, 2))  # bottom, right to left
    for f in np.arange(per_side) / per_side:
        origins.append((lo_x, lo_y + f * (hi_y - lo_y), 3))  # left, bottom to top
    items = []
    for k, (x0, y0, _) in enumerate(origins):
        corners = [[x0, y0 + s], [x0 + s, y0 + s], [x0 + s, y0], [x0, y0]]
        items.append({"id": k, "corners_mm": [[round(float(a), 4), round(float(b), 4)]
                                              for a, b in corners]})
    return items


def _page(width_mm: float, height_mm: float) -> tuple[Any, Any]:
    # a Figure of its own (no pyplot): Agg canvas, nothing global
    fig = Figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, width_mm)
    ax.set_ylim(0, height_mm)
    ax.set_axis_off()
    return fig, ax


SEAM_MM = 0.25  # rows overlap by this much: coincident edges show as hairlines


def _black_runs(ax, bits: np.ndarray, x0: float, y_top: float, cell: float) -> None:
    """Black cells of a bit image (row 0 on top) as one rectangle per run in a row,
    each reaching ``SEAM_MM`` into the row below but the last (the marker's outline)."""
    for r, row in enumerate(bits):
        seam = SEAM_MM if r + 1 < len(bits) else 0.0
        c = 0
        while c < len(row):
            if row[c]:
                c0 = c
                while c < len(row) and row[c]:
                    c += 1
                ax.add_patch(Rectangle((x0 + c0 * cell, y_top - (r + 1) * cell - seam),
                                       (c - c0) * cell, cell + seam, facecolor="black",
                                       edgecolor="none", linewidth=0, snap=False))
            else:
                c += 1


def _marker_bits(dictionary, marker_id: int) -> np.ndarray:
    """(n + 2, n + 2) bool black cells of a marker, its one-cell black border included."""
    n = dictionary.markerSize + 2
    img = cv2.aruco.generateImageMarker(dictionary, int(marker_id), n, borderBits=1)
    return img < 128


def _scale_bar(ax, x: float, y: float, length_mm: float) -> None:
    ax.add_patch(Rectangle((x, y), length_mm, 1.0, facecolor="black", edgecolor="none"))
    for k in range(int(length_mm // 10) + 1):
        ax.add_patch(Rectangle((x + 10 * k - 0.15, y), 0.3, 3.0 if k % 5 == 0 else 2.0,
                               facecolor="black", edgecolor="none"))
    ax.text(x, y + 4.0, f"{length_mm:g} mm: print at 100 % (actual size)",
            fontsize=7, va="bottom", ha="left")


def marker_sheet(width_mm: float, height_mm: float, dictionary: str, marker_mm: float,
                 count: int = 8, gap_mm: float | None = None,
                 ) -> tuple[Sheet, dict[str, Any]]:
    """The marker sheet of a ``width_mm`` x ``height_mm`` surface and its layout (the
    ``surface`` and ``markers`` sections of ``capture.yaml``). ``gap_mm`` (default a
    quarter of the marker size) between the surface's edge and the markers."""
    if width_mm <= 0 or height_mm <= 0:
        raise InputError("markers: the surface's width and height must be positive")
    d = aruco_dictionary(dictionary)
    if count > len(d.bytesList):
        raise InputError(f"markers: {dictionary} has {len(d.bytesList)} markers, "
                         f"{count} asked for")
    gap = 0.25 * marker_mm if gap_mm is None else float(gap_mm)
    items = marker_layout(width_mm, height_mm, marker_mm, gap, count)
    pts = np.array([c for it in items for c in it["corners_mm"]])
    lo, hi = pts.min(0), pts.max(0)
    bar = 100.0 if hi[0] - lo[0] >= 120 else 50.0
    origin = (MARGIN_MM - lo[0], MARGIN_MM + 12.0 - lo[1])  # room below for the bar
    page_w = float(hi[0] - lo[0] + 2 * MARGIN_MM)
    page_h = float(hi[1] - lo[1] + 2 * MARGIN_MM + 12.0)
    fig, ax = _page(page_w, page_h)
    ox, oy = origin
    ax.add_patch(Rectangle((ox, oy), width_mm, height_mm, facecolor="none",
                           edgecolor="0.6", linewidth=0.5, linestyle=(0, (4, 4))))
    ax.text(ox + width_mm / 2, oy + height_mm / 2,
            f"surface {width_mm:g} x {height_mm:g} mm\n(origin: bottom-left corner)",
            fontsize=8, color="0.5", ha="center", va="center")
    for it in items:
        c = np.asarray(it["corners_mm"])
        bits = _marker_bits(d, it["id"])
        cell = marker_mm / len(bits)
        _black_runs(ax, bits, ox + c[0, 0], oy + c[0, 1], cell)
        ax.text(ox + c[3, 0], oy + c[3, 1] - 1.0, f"{it['id']}", fontsize=5, va="top",
                color="0.4")
    _scale_bar(ax, MARGIN_MM, MARGIN_MM, bar)
    ax.text(page_w - MARGIN_MM, MARGIN_MM, f"{dictionary}, markers {marker_mm:g} mm",
            fontsize=7, ha="right", va="bottom")
    layout = {"surface": {"width_mm": float(width_mm), "height_mm": float(height_mm)},
              "markers": {"dictionary": dictionary, "items": items}}
    return Sheet(fig, page_w, page_h, origin), layout


def _charuco(squares_x: int, squares_y: int, square_mm: float, marker_mm: float,
             dictionary: str):
    if squares_x < 3 or squares_y < 3:
        raise InputError("board: at least 3 x 3 squares")
    if not 0 < marker_mm < square_mm:
        raise InputError("board: the marker must be smaller than the square")
    return cv2.aruco.CharucoBoard((int(squares_x), int(squares_y)), float(square_mm),
                                  float(marker_mm), aruco_dictionary(dictionary))


def board_sheet(squares_x: int, squares_y: int, square_mm: float, marker_mm: float,
                dictionary: str) -> tuple[Sheet, dict[str, Any]]:
    """A ChArUco board sheet (OpenCV's pattern, as the calibration stage builds it) and
    its layout (the ``calibration`` section of ``capture.yaml``)."""
    board = _charuco(squares_x, squares_y, square_mm, marker_mm, dictionary)
    bw, bh = squares_x * square_mm, squares_y * square_mm
    bar = 100.0 if bw >= 120 else 50.0
    page_w, page_h = bw + 2 * MARGIN_MM, bh + 2 * MARGIN_MM + 12.0
    fig, ax = _page(page_w, page_h)
    ox, oy = MARGIN_MM, MARGIN_MM + 12.0
    # board frame: x right, y down from its top-left corner; the page's y goes up
    # markers sit in the white squares: the first one's square gives the parity
    centre = np.asarray(board.getObjPoints()[0])[:, :2].mean(0)
    white = int(centre[0] // square_mm + centre[1] // square_mm) % 2
    for j in range(squares_y):
        for i in range(squares_x):
            if (i + j) % 2 != white:
                ax.add_patch(Rectangle((ox + i * square_mm, oy + bh - (j + 1) * square_mm),
                                       square_mm, square_mm, facecolor="black",
                                       edgecolor="none", linewidth=0, snap=False))
    d = board.getDictionary()
    for mid, obj in zip(board.getIds().ravel(), board.getObjPoints(), strict=True):
        tl = np.asarray(obj)[0]
        bits = _marker_bits(d, int(mid))
        _black_runs(ax, bits, ox + tl[0], oy + bh - tl[1], marker_mm / len(bits))
    _scale_bar(ax, MARGIN_MM, MARGIN_MM, bar)
    ax.text(page_w - MARGIN_MM, MARGIN_MM, f"ChArUco {squares_x} x {squares_y}, "
            f"{square_mm:g} / {marker_mm:g} mm, {dictionary}", fontsize=7, ha="right",
            va="bottom")
    layout = {"calibration": {"board": "charuco", "squares_x": int(squares_x),
                              "squares_y": int(squares_y), "square_mm": float(square_mm),
                              "marker_mm": float(marker_mm), "dictionary": dictionary}}
    return Sheet(fig, page_w, page_h, (ox, oy + bh)), layout


def rasterise(sheet: Sheet, dpi: int = CHECK_DPI) -> np.ndarray:
    """(H, W) uint8 gray raster of a sheet at ``dpi``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = sheet.figure
    fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return cv2.cvtColor(np.ascontiguousarray(rgba[..., :3]), cv2.COLOR_RGB2GRAY)


def _page_mm(uv: np.ndarray, sheet: Sheet, shape: tuple[int, int]) -> np.ndarray:
    """Image coordinates (pixel centres at integers) of a raster of ``shape`` -> page mm
    (y up); the raster spans the page (its size in pixels is rounded)."""
    uv = np.asarray(uv, float) + 0.5
    return np.stack([uv[..., 0] * sheet.width_mm / shape[1],
                     sheet.height_mm - uv[..., 1] * sheet.height_mm / shape[0]], -1)


def _detector(dictionary) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(dictionary, params)


def check_markers(sheet: Sheet, layout: dict[str, Any], dpi: int = CHECK_DPI,
                  ) -> dict[str, Any]:
    """Rasterise the marker sheet and detect its markers: ids missing, and the largest
    distance (mm) of a detected corner from the layout's."""
    img = rasterise(sheet, dpi)
    d = aruco_dictionary(layout["markers"]["dictionary"])
    corners, ids, _ = _detector(d).detectMarkers(img)
    want = {it["id"]: np.asarray(it["corners_mm"], float) for it in layout["markers"]["items"]}
    found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in
                                    zip(ids.ravel(), corners, strict=True)}
    err = [float(np.abs(_page_mm(found[i], sheet, img.shape) - (want[i] + sheet.origin_mm)).max())
           for i in want if i in found]
    return {"markers": len(want), "detected": len(set(found) & set(want)),
            "missing": sorted(set(want) - set(found)), "max_corner_error_mm":
            max(err) if err else None, "dpi": dpi}


def check_board(sheet: Sheet, layout: dict[str, Any], dpi: int = CHECK_DPI,
                ) -> dict[str, Any]:
    """Rasterise the board sheet and detect it as the calibration stage does: corners
    found and the largest distance (mm) of one from the board's geometry."""
    cal = layout["calibration"]
    board = _charuco(cal["squares_x"], cal["squares_y"], cal["square_mm"], cal["marker_mm"],
                     cal["dictionary"])
    img = rasterise(sheet, dpi)
    cc, ci, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(img)
    expected = np.asarray(board.getChessboardCorners())[:, :2]
    n = 0 if ci is None else len(ci)
    err = None
    if n:
        got = _page_mm(np.asarray(cc).reshape(-1, 2), sheet, img.shape)
        ox, oy_top = sheet.origin_mm
        want = np.stack([ox + expected[ci.ravel(), 0], oy_top - expected[ci.ravel(), 1]], -1)
        err = float(np.abs(got - want).max())
    return {"corners": len(expected), "detected": n, "max_corner_error_mm": err, "dpi": dpi}


def write_sheet(sheet: Sheet, layout: dict[str, Any], out_dir: str | Path, name: str,
                check: dict[str, Any]) -> list[Path]:
    """``<name>.pdf`` and ``.svg`` at true scale, a ``.png`` preview (150 dpi) and
    ``<name>.yaml`` (the layout, and the check's figures as a comment)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for ext, dpi in (("pdf", 72), ("svg", 72), ("png", 150)):
        path = out / f"{name}.{ext}"
        tmp = path.with_name(f".{path.name}.tmp")
        sheet.figure.savefig(tmp, format=ext, dpi=dpi)
        tmp.replace(path)
        paths.append(path)
    figures = yaml.safe_dump(check, default_flow_style=True).strip()
    head = (f"# {name} layout in the capture format (docs/reference/capture-format.md); "
            f"page {sheet.width_mm:.1f} x {sheet.height_mm:.1f} mm\n"
            f"# checked at {check['dpi']} dpi: {figures}\n")
    path = out / f"{name}.yaml"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(head + yaml.safe_dump(layout, sort_keys=False, default_flow_style=None))
    tmp.replace(path)
    paths.append(path)
    return paths
