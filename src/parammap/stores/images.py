"""Reading photos and exposure times, with errors that name the file."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ..errors import InputError

__all__ = ["PHOTO_SUFFIXES", "ImageReadError", "PhotoMeta", "exif_exposure_time",
           "photo_meta", "read_image", "write_image_atomic"]

# camera files import reads (RAW formats need a LibRaw binding, not installed)
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png")


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
    return _number(exif.get_ifd(_EXIF_IFD).get(0x829A) or exif.get(0x829A))


@dataclass(frozen=True)
class PhotoMeta:
    """What a camera file's header says: exposure time (s), f-number, ISO, focal length
    (mm), when it was taken (s since the epoch, sub-second where the camera writes it),
    orientation (EXIF 1-8), make and model, and the image size (width, height) px; None
    where the file does not say."""

    path: Path
    exposure_s: float | None
    f_number: float | None
    iso: float | None
    focal_mm: float | None
    taken_s: float | None
    orientation: int | None
    camera: str
    size: tuple[int, int]


_EXIF_IFD = 0x8769


def _number(value) -> float | None:
    if value is None:
        return None
    if isinstance(value, tuple):  # ISO may be a tuple of speeds
        value = value[0] if value else None
        if value is None:
            return None
    try:
        return float(Fraction(str(value))) if not isinstance(value, (int, float)) \
            else float(value)
    except (ValueError, ZeroDivisionError):
        try:
            return float(value)
        except (TypeError, ValueError):
            return None


def photo_meta(path: str | Path) -> PhotoMeta:
    """The header of one camera file (:class:`PhotoMeta`); the pixels are not decoded.

    Raises
    ------
    ImageReadError
        If the file cannot be opened as an image.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            size = im.size
            exif = im.getexif()
    except (OSError, ValueError) as exc:
        raise ImageReadError(f"{path}: not a readable image ({exc})") from None
    sub = exif.get_ifd(_EXIF_IFD)

    def tag(key: int):
        return sub.get(key, exif.get(key))

    taken = None
    stamp = tag(0x9003) or tag(0x0132)  # DateTimeOriginal, else DateTime
    if stamp:
        try:
            taken = datetime.strptime(str(stamp).strip(), "%Y:%m:%d %H:%M:%S").timestamp()
            frac = str(tag(0x9291) or "").strip()  # SubsecTimeOriginal
            if frac.isdigit():
                taken += float(f"0.{frac}")
        except ValueError:
            taken = None
    orientation = tag(0x0112)
    camera = " ".join(str(x).strip() for x in (tag(0x010F), tag(0x0110)) if x)
    return PhotoMeta(path, _number(tag(0x829A)), _number(tag(0x829D)), _number(tag(0x8827)),
                     _number(tag(0x920A)), taken,
                     int(orientation) if orientation is not None else None, camera,
                     (int(size[0]), int(size[1])))


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
