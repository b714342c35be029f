"""OpenEXR reading and writing (OpenEXR 3 Python API), always via a temporary name."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from ..errors import InputError

__all__ = ["ExrError", "read_exr", "write_exr"]


class ExrError(InputError):
    """An EXR file that is missing, unreadable or not what the reader expects."""


def write_exr(
    path: str | Path, channels: dict[str, np.ndarray], attrs: dict[str, Any] | None = None,
    half: bool = False,
) -> Path:
    """Write named 2-D channels (float32, or float16 with ``half``) with ZIP compression.

    Header ``attrs`` may be strings, numbers or tuples of numbers.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dtype = np.float16 if half else np.float32
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attrs or {})
    data = {k: np.ascontiguousarray(v, dtype=dtype) for k, v in channels.items()}
    tmp = path.with_name(f".{path.stem}.tmp.exr")
    OpenEXR.File(header, data).write(str(tmp))
    tmp.replace(path)
    return path


def read_exr(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read every channel (as stored: float32 or float16) and the header.

    Raises
    ------
    ExrError
        If the file is missing or not a readable EXR.
    """
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: no such EXR file")
    try:
        # separate_channels: otherwise the binding merges R, G, B (also "Kd.R"...)
        # into one multi-channel array
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = dict(f.header())
            # the binding's arrays own their pixels: a copy would double the peak
            chans = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as exc:  # the binding raises bare RuntimeError/OSError variants
        raise ExrError(f"{path}: not a readable EXR file ({exc})") from None
    return chans, header
