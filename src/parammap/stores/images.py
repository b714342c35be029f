"""Reading photos and exposure times, with errors that name the file."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ..errors import InputError

__all__ = ["ImageReadError", "exif_exposure_time", "read_image", "write_image_atomic"]


class ImageReadError(InputError):
    """A photo that cannot be decoded (corrupt, truncated or not an image)."""


def read_image(path: str | Path) -> np.ndarray:
    """Read a photo as RGB, keeping its bit depth.

    Returns
    -------
    (H, W, 3) uint8 or uint16 array, channels in RGB order.

    Raises
    ------
    ImageReadError
        If the file is missing, truncated or cannot be decoded.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageReadError(f"{path}: cannot read file ({exc.strerror})") from None
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-64:]:
        # libjpeg decodes truncated files into grey padding with only a warning.
        raise ImageReadError(f"{path}: truncated JPEG (no end-of-image marker)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageReadError(f"{path}: not a readable image")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[..., :3]
    if img.dtype not in (np.uint8, np.uint16):
        raise ImageReadError(f"{path}: unsupported pixel type {img.dtype}")
    return np.ascontiguousarray(img[..., ::-1])


def exif_exposure_time(path: str | Path) -> float | None:
    """The EXIF ``ExposureTime`` of a photo in seconds, or None when absent."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
    except (OSError, ValueError):
        return None
    value = exif.get_ifd(0x8769).get(0x829A) or exif.get(0x829A)
    if value is None:
        return None
    try:
        return float(Fraction(str(value))) if not isinstance(value, (int, float)) else float(value)
    except (ValueError, ZeroDivisionError):
        try:
            return float(value)
        except (TypeError, ValueError):
            return None


def write_image_atomic(path: str | Path, rgb: np.ndarray) -> None:
    """Write an RGB uint8/uint16 image (PNG/JPEG by extension) via a temporary name."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix, np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"{path}: could not encode image")
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.tobytes())
    tmp.replace(path)
