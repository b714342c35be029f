"""Merged HDR frames (``hdr/<view>.exr``) and the camera response (``camera/response.csv``).

A frame holds linear relative radiance ``R, G, B``, the ``saturated`` and ``dark`` masks
and the relative noise sd per pixel (``noise``); frames written before the merge
recorded the noise read with ``noise`` None. A frame merged from camera RAWs also holds
the merged photosites before demosaicing (``cfa``), their filters' repeating pattern in
the header (``cfa_pattern``). The response is the log-exposure curve
``g[z, c] = ln X`` per 8-bit level z and channel c (``docs/reference/conventions.md``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from .common import SOFTWARE_ATTR, UNITS_ATTR, software
from .exr import read_exr, write_exr

__all__ = ["CFA_CHANNEL", "HDR_CHANNELS", "NOISE_CHANNEL", "HdrError", "is_linear_response",
           "load_reference_response", "load_response", "read_hdr", "read_hdr_mosaic",
           "read_hdr_noise",
           "read_rgb", "save_linear_response", "save_response", "hdr_provenance",
           "write_hdr", "write_rgb"]

#: Channels of a merged HDR frame (``hdr/<view>.exr``): radiance, the masks, and the
#: relative noise sd per pixel that the fits weigh observations by.
RGB = ("R", "G", "B")
SATURATED, DARK, NOISE_CHANNEL = "saturated", "dark", "noise"
HDR_CHANNELS = (*RGB, SATURATED, DARK, NOISE_CHANNEL)
#: The merged photosites of a RAW capture's frame, and the header attribute that names
#: each one's filter: the pattern's rows and columns, then its filters row by row
#: (``"2x2:RGGB"``; X-Trans ``"6x6:..."``).
CFA_CHANNEL, CFA_ATTR = "cfa", "cfa_pattern"


def write_rgb(path: str | Path, rgb: np.ndarray, attrs: dict | None = None) -> Path:
    """Write (H, W, 3) linear radiance as an RGB OpenEXR (atomically)."""
    return write_exr(path, {c: rgb[..., i] for i, c in enumerate(RGB)}, attrs or {})


def read_rgb(path: str | Path) -> np.ndarray:
    """(H, W, 3) radiance of an RGB OpenEXR (:func:`write_rgb`, a merged frame)."""
    ch, _ = read_exr(path)
    return np.stack([ch[c] for c in RGB], -1)


def hdr_provenance(config_digest: str, response_digest: str,
                   radiometry: dict[str, str] | None = None) -> dict[str, str]:
    """Header attributes that say what made a frame: the software, digests of the hdr
    config and of the response (``linear`` for linear input), and what ``radiometry``
    says of its flat-field and colour (``parammap_flatfield``, ``parammap_colour``;
    :func:`parammap.stores.radiometry.merged_frame_radiometry`)."""
    return {SOFTWARE_ATTR: software(), "config_digest": config_digest,
            "response_digest": response_digest,
            **{f"parammap_{k}": v for k, v in (radiometry or {}).items()}}


def _cfa_pattern(colors: np.ndarray) -> str:
    """``"RxC:FILTERS"`` of an (H, W) filter index (0 R, 1 G, 2 B) that repeats."""
    H, W = colors.shape
    for n in (2, 4, 6):
        period = colors[:n, :n]
        if np.array_equal(np.tile(period, (H // n + 1, W // n + 1))[:H, :W], colors):
            return f"{n}x{n}:" + "".join("RGB"[int(c)] for c in period.ravel())
    raise ValueError("the colour filter array does not repeat within 6 x 6 photosites")


def _cfa_colors(pattern: str, shape: tuple[int, int]) -> np.ndarray:
    """The (H, W) filter index that :func:`_cfa_pattern` describes."""
    dims, names = pattern.split(":")
    n, m = (int(x) for x in dims.split("x"))
    period = np.array(["RGB".index(c) for c in names], np.uint8).reshape(n, m)
    H, W = shape
    return np.tile(period, (H // n + 1, W // m + 1))[:H, :W]


def write_hdr(path: str | Path, radiance: np.ndarray, saturated: np.ndarray,
              dark: np.ndarray, noise: np.ndarray, view_id: str,
              provenance: dict[str, str] | None = None,
              mosaic: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Write a merged HDR frame: (H, W, 3) radiance, (H, W) bool masks of saturated and
    dark pixels, (H, W) relative noise sd; the header names the view, the units and
    ``provenance`` (:func:`hdr_provenance`). ``mosaic``: a RAW capture's merged
    photosites (H, W) in the radiance's units and each one's filter (H, W) (0 R, 1 G,
    2 B)."""
    chans = {**{c: radiance[..., i] for i, c in enumerate(RGB)},
             SATURATED: saturated.astype(np.float32), DARK: dark.astype(np.float32),
             NOISE_CHANNEL: noise}
    attrs = {"view_id": view_id, UNITS_ATTR: "relative radiance (response exp(g)/t)",
             NOISE_CHANNEL: "relative sd of the radiance per pixel (merge_noise)",
             **(provenance or {})}
    if mosaic is not None:
        chans[CFA_CHANNEL] = mosaic[0]
        attrs[CFA_ATTR] = _cfa_pattern(mosaic[1])
    return write_exr(path, chans, attrs)


class HdrError(InputError):
    """A bracket or response that cannot give an HDR frame."""


def read_hdr(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an HDR frame: (H, W, 3) float32 radiance, saturated and dark masks."""
    return read_hdr_noise(path)[:3]


def read_hdr_noise(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                np.ndarray | None]:
    """:func:`read_hdr` plus the (H, W) relative noise sd of the frame (None for
    frames written before the merge recorded it)."""
    ch, _ = read_exr(path)
    rad = np.stack([ch[c] for c in RGB], -1).astype(np.float32)
    return rad, ch[SATURATED] > 0.5, ch[DARK] > 0.5, ch.get(NOISE_CHANNEL)


def read_hdr_mosaic(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """A RAW capture frame's merged photosites (H, W) float32 and their filters (H, W)
    uint8 (0 R, 1 G, 2 B); None for a frame merged from demosaiced or 8-bit photos."""
    ch, header = read_exr(path)
    if CFA_CHANNEL not in ch or CFA_ATTR not in header:
        return None
    m = np.asarray(ch[CFA_CHANNEL], np.float32)
    return m, _cfa_colors(str(header[CFA_ATTR]), m.shape)


def save_response(path: str | Path, g: np.ndarray, meta: dict | None = None) -> Path:
    """Write the response as CSV (level, g_R, g_G, g_B), reusable via
    ``camera.response: <path>``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    head = "# parammap camera response: g = ln(relative exposure) per 8-bit level\n"
    if meta:
        head += "# " + json.dumps(meta) + "\n"
    body = "level,g_R,g_G,g_B\n" + "".join(
        f"{z},{g[z, 0]:.8g},{g[z, 1]:.8g},{g[z, 2]:.8g}\n" for z in range(256))
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(head + body)
    tmp.replace(path)
    return path


# the first line of the response file of a linear capture (no curve)
_LINEAR_HEAD = "# parammap camera response: linear input, no curve"


def save_linear_response(path: str | Path, meta: dict | None = None) -> Path:
    """Write the response file of a linear capture (16-bit or RAW): a header saying so,
    no curve. The workflow's later stages find the file either way."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(_LINEAR_HEAD + "\n" + ("# " + json.dumps(meta) + "\n" if meta else ""))
    tmp.replace(path)
    return path


def is_linear_response(path: str | Path) -> bool:
    """Whether ``path`` is the response file of a linear capture
    (:func:`save_linear_response`)."""
    try:
        with Path(path).open() as f:
            return f.readline().rstrip("\n") == _LINEAR_HEAD
    except OSError:
        return False


def load_response(path: str | Path) -> np.ndarray:
    """Read a response CSV written by :func:`save_response`; (256, 3)."""
    path = Path(path)
    if is_linear_response(path):
        raise HdrError(f"{path}: the response of a linear capture (no curve to read)")
    try:
        lines = [ln for ln in path.read_text().splitlines()
                 if ln.strip() and not ln.startswith("#")]
        arr = np.array([ln.split(",") for ln in lines[1:]], float)
    except (OSError, ValueError) as exc:
        raise HdrError(f"{path}: not a response curve CSV ({exc})") from None
    if arr.shape != (256, 4):
        raise HdrError(f"{path}: expected 256 rows of level,g_R,g_G,g_B (got {arr.shape})")
    return arr[:, 1:]


def load_reference_response(path: str | Path) -> np.ndarray:
    """A reference response for plots, as ln exposure (256, 3): a colour-hdri CRF
    ``.npy`` (linear relative exposure per level), a generator truth ``response.npz``
    (key ``exposure``) or a response CSV of :func:`save_response`."""
    path = Path(path)
    if path.suffix == ".csv":
        return load_response(path)
    try:
        arr = np.load(path)
        arr = arr["exposure"] if path.suffix == ".npz" else arr
    except (OSError, ValueError, KeyError) as exc:
        raise HdrError(f"{path}: not a reference response ({exc})") from None
    arr = np.asarray(arr, float)
    if arr.shape != (256, 3):
        raise HdrError(f"{path}: reference response must be 256x3 (got {arr.shape})")
    return np.log(np.maximum(arr, 1e-6))
