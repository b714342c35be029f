"""Reading photos and exposure times, with errors that name the file."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import rawpy
import tifffile
from PIL import Image

from ..errors import InputError

__all__ = ["PHOTO_SUFFIXES", "RAW_SUFFIXES", "ImageReadError", "PhotoMeta", "demosaic",
           "exif_exposure_time", "image_size", "is_raw", "photo_meta", "read_image", "read_raw",
           "read_raw_mosaic",
           "write_image_atomic"]

# camera RAW files, read through LibRaw (rawpy)
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef",
                ".srw", ".nrw", ".3fr", ".iiq", ".erf", ".kdc", ".mos", ".rwl")
# camera files import reads
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png") + RAW_SUFFIXES
# a RAW's linear values are scaled so that its white level is this (16-bit)
RAW_FULL = 65535


def is_raw(path: str | Path) -> bool:
    """Whether ``path`` names a camera RAW file (by its suffix)."""
    return Path(path).suffix.lower() in RAW_SUFFIXES


class ImageReadError(InputError):
    """A photo that cannot be decoded (corrupt, truncated or not an image)."""


def read_image(path: str | Path) -> np.ndarray:
    """Read a photo as RGB, keeping its bit depth; a camera RAW as linear 16-bit RGB
    (:func:`read_raw`).

    Returns
    -------
    (H, W, 3) uint8 or uint16 array, channels in RGB order.

    Raises
    ------
    ImageReadError
        If the file is missing, truncated or cannot be decoded.
    """
    path = Path(path)
    if is_raw(path):
        return read_raw(path)
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


def _open_raw(path: Path):
    try:
        with warnings.catch_warnings():
            # rawpy warns in every worker forked from a pool: the deadlock it means needs
            # LibRaw's OpenMP code run in the parent before the fork and again in the
            # child, and no stage does both (HDR reads RAWs in its workers only,
            # calibration in its parent only)
            warnings.filterwarnings("ignore", category=RuntimeWarning,
                                    message="rawpy is being used in a process created")
            return rawpy.imread(str(path))
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise ImageReadError(f"{path}: not a readable camera RAW ({exc})") from None


def _demosaic(mosaic: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """Bilinear demosaicing of a colour filter array whose every 3 x 3 neighbourhood
    holds each colour (any Bayer order, X-Trans): (H, W) float32 values, (H, W) colour
    index 0..2 (R, G, B) of each photosite -> (H, W, 3) float32 (each channel the
    weighted mean of its own photosites in the 3 x 3 neighbourhood)."""
    k = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], np.float32)
    out = np.empty(mosaic.shape + (3,), np.float32)
    for c in range(3):
        m = (colors == c).astype(np.float32)
        num = cv2.filter2D(mosaic * m, -1, k, borderType=cv2.BORDER_REFLECT)
        den = cv2.filter2D(m, -1, k, borderType=cv2.BORDER_REFLECT)
        out[..., c] = num / np.maximum(den, 1e-6)
    return out


def read_raw_mosaic(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A camera RAW's visible photosites, linear: less their black level (per colour
    filter), over the white level less black, scaled so that the white level is 65535
    (a saturated photosite is 65535); no demosaicing, white balance or colour matrix.

    Returns
    -------
    mosaic : (H, W) uint16, linear in the sensor's exposure.
    colors : (H, W) uint8, each photosite's filter, 0 R, 1 G, 2 B.

    Raises
    ------
    ImageReadError
        If LibRaw cannot read the file or its filter array is not an RGB one.
    """
    path = Path(path)
    with _open_raw(path) as raw:
        mosaic = raw.raw_image_visible.astype(np.float32)
        cidx = raw.raw_colors_visible
        desc = raw.color_desc.decode("ascii", "replace")
        black = np.asarray(raw.black_level_per_channel, np.float32)
        whites = raw.camera_white_level_per_channel
        white = float(max(whites) if whites and max(whites) > 0 else raw.white_level)
        if raw.num_colors not in (3, 4) or any(c not in "RGB" for c in desc[:4]):
            raise ImageReadError(f"{path}: colour filter array {desc!r} is not RGB")
    colors = np.array(["RGB".index(c) for c in desc[:4]], np.uint8)[cidx]
    level = black[cidx]
    lin = np.clip((mosaic - level) / np.maximum(white - level, 1.0), 0, 1)
    lin[mosaic >= white] = 1.0
    return np.round(lin * RAW_FULL).astype(np.uint16), colors


def read_raw(path: str | Path) -> np.ndarray:
    """A camera RAW (DNG or a proprietary format, through LibRaw) as linear RGB.

    :func:`read_raw_mosaic` demosaiced bilinearly (:func:`_demosaic`) in the camera's
    own colour space (no white balance, no colour matrix, no tone curve), the white
    level at 65535. A pixel with a saturated photosite anywhere in its 3 x 3
    neighbourhood is 65535 in every channel, so a merge sees it as saturated.

    Returns
    -------
    (H, W, 3) uint16, linear in the sensor's exposure.

    Raises
    ------
    ImageReadError
        If LibRaw cannot read the file or its filter array is not an RGB one.
    """
    return demosaic(*read_raw_mosaic(path))


def demosaic(mosaic: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """:func:`read_raw`'s RGB from :func:`read_raw_mosaic`'s photosites (H, W) uint16
    and filters (H, W): bilinear, a pixel with a saturated photosite in its 3 x 3
    neighbourhood saturated in every channel.

    Returns
    -------
    (H, W, 3) uint16, linear, the white level at 65535.
    """
    rgb = _demosaic(mosaic.astype(np.float32) / RAW_FULL, colors)
    sat = cv2.dilate((mosaic >= RAW_FULL).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    rgb[sat] = 1.0
    return np.round(rgb * RAW_FULL).astype(np.uint16)


def image_size(path: str | Path) -> tuple[int, int]:
    """(H, W) of a photo, its pixels decoded (a corrupt file fails here) but a RAW's not
    demosaiced.

    Raises
    ------
    ImageReadError
        If the file cannot be decoded.
    """
    path = Path(path)
    if not is_raw(path):
        return tuple(read_image(path).shape[:2])
    with _open_raw(path) as raw:
        try:
            return tuple(raw.raw_image_visible.shape[:2])
        except Exception as exc:  # noqa: BLE001 - LibRaw's decode errors vary by format
            raise ImageReadError(f"{path}: not a readable camera RAW ({exc})") from None


def exif_exposure_time(path: str | Path) -> float | None:
    """The EXIF ``ExposureTime`` of a photo (a RAW's own header) in seconds, or None when
    absent."""
    if is_raw(path):
        try:
            return photo_meta(path).exposure_s
        except ImageReadError:
            return None
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
    if is_raw(path):
        return _raw_meta(path)
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


def _raw_meta(path: Path) -> PhotoMeta:
    """:class:`PhotoMeta` of a camera RAW: exposure, ISO, aperture, focal length and time
    as LibRaw reads them; make and model from the file's TIFF tags where it is TIFF-based
    (DNG and most proprietary formats)."""
    with _open_raw(path) as raw:
        o, sizes = raw.other, raw.sizes
    tags = _tiff_tags(path)

    def pos(x, code: int) -> float | None:
        x = x if x and x > 0 else _number(tags.get(code))
        return float(x) if x and x > 0 else None

    taken = o.timestamp.timestamp() if o.timestamp and o.timestamp.year > 1970 else None
    flip = {0: 1, 3: 3, 5: 8, 6: 6}.get(int(sizes.flip), 1)  # LibRaw's flip as EXIF's
    camera = " ".join(str(tags[k]).strip() for k in (0x010F, 0x0110) if tags.get(k))
    return PhotoMeta(path, pos(o.shutter_speed, 0x829A), pos(o.aperture, 0x829D),
                     pos(o.iso_speed, 0x8827), pos(o.focal_length, 0x920A), taken, flip,
                     camera, (int(sizes.width), int(sizes.height)))


def _tiff_tags(path: Path) -> dict[int, object]:
    """The first IFD's tags and its EXIF IFD's, by code, of a TIFF-based RAW (DNG, CR2,
    NEF, ARW, ...); empty for other formats (LibRaw's own reading then stands alone)."""
    try:
        with tifffile.TiffFile(path) as tf:
            tags = {t.code: t.value for t in tf.pages[0].tags.values()}
    except (tifffile.TiffFileError, OSError, ValueError, IndexError):
        return {}
    exif = tags.get(0x8769)  # tifffile hands the EXIF IFD out by tag name
    if isinstance(exif, dict):
        for name, value in exif.items():
            code = tifffile.TIFF.TAGS.get(name)
            if isinstance(code, int):
                tags.setdefault(code, value)
    return tags


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
