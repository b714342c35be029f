"""Merged HDR frames (``hdr/<view>.exr``) and the camera response (``camera/response.csv``).

A frame holds linear relative radiance ``R, G, B``, the ``saturated`` and ``dark`` masks
and the relative noise sd per pixel (``noise``); frames written before the merge
recorded the noise read with ``noise`` None. The response is the log-exposure curve
``g[z, c] = ln X`` per 8-bit level z and channel c (``docs/conventions.md``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..conventions import NOISE_CHANNEL
from ..errors import InputError
from .exr import read_exr

__all__ = ["HdrError", "load_reference_response", "load_response", "read_hdr", "read_hdr_noise",
           "save_response"]


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
    rad = np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float32)
    return rad, ch["saturated"] > 0.5, ch["dark"] > 0.5, ch.get(NOISE_CHANNEL)


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


def load_response(path: str | Path) -> np.ndarray:
    """Read a response CSV written by :func:`save_response`; (256, 3)."""
    path = Path(path)
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
