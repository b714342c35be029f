"""Camera RAW files made from linear radiance: a sensor (a 2 x 2 colour filter array,
black and white levels, shot and read noise) and a DNG writer (tifffile), so the RAW
path (:func:`parammap.stores.images.read_raw`) is tested on files that LibRaw reads as it
reads a camera's."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import tifffile

__all__ = ["Sensor", "expose_raw", "write_dng"]


@dataclass(frozen=True)
class Sensor:
    """A RAW camera's sensor: its colour filter array (``pattern``, 2 x 2 from the top
    left), black and white level (DN), full well (electrons at the white level) and read
    noise (electrons, sd)."""

    pattern: str = "RGGB"
    black: int = 512
    white: int = 15600
    full_well: float = 24000.0
    read_noise_e: float = 5.0
    # the optical low-pass filter in front of the mosaic (Gaussian sd, pixels): a
    # camera's lens and filter band-limit the image so the mosaic does not alias
    olpf_px: float = 0.0
    # each filter's sensitivity to the linear exposure (R, G, B): a camera's green
    # photosites collect more of a white light than its red and blue ones
    gains: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def colors(self, H: int, W: int) -> np.ndarray:
        """(H, W) colour index (0 R, 1 G, 2 B) of each photosite."""
        cfa = np.array(["RGB".index(c) for c in self.pattern]).reshape(2, 2)
        return np.tile(cfa, (H // 2 + 1, W // 2 + 1))[:H, :W]

    @property
    def noise_model(self) -> tuple[float, float]:
        """``(a, b)`` of ``var(v) = a v + b`` for the value v over the white level less
        black (what :func:`parammap.stages.hdr.fit_sensor_noise` measures)."""
        return 1.0 / self.full_well, (self.read_noise_e / self.full_well) ** 2


def expose_raw(v: np.ndarray, sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """The mosaic a sensor records of the (H, W, 3) linear exposure ``v`` (1 = the white
    level, per channel): blurred by the optical low-pass filter, each photosite takes
    its filter's channel times the filter's gain, Poisson electrons and Gaussian read
    noise, the black level, clipped at the white level.

    Returns
    -------
    (H, W) uint16 DN.
    """
    H, W = v.shape[:2]
    v = np.asarray(v, np.float32)
    if sensor.olpf_px > 0:
        v = cv2.GaussianBlur(v, (0, 0), sensor.olpf_px, borderType=cv2.BORDER_REFLECT)
    cidx = sensor.colors(H, W)
    site = np.take_along_axis(v.astype(float), cidx[..., None], 2)[..., 0]
    site *= np.asarray(sensor.gains, float)[cidx]
    e = rng.poisson(np.clip(site, 0, 2) * sensor.full_well).astype(float)
    e += rng.normal(0, sensor.read_noise_e, e.shape)
    dn = sensor.black + e * (sensor.white - sensor.black) / sensor.full_well
    return np.clip(np.round(dn), 0, sensor.white).astype(np.uint16)


def _rational(x: float, den: int = 100000) -> tuple[int, int]:
    f = Fraction(x).limit_denominator(den)
    return f.numerator, f.denominator


def write_dng(path: str | Path, mosaic: np.ndarray, sensor: Sensor, exposure_s: float | None,
              taken: datetime, iso: int = 100, f_number: float = 8.0, focal_mm: float = 35.0,
              camera: tuple[str, str] = ("Parammap", "SynthRaw")) -> None:
    """A DNG of a (H, W) uint16 mosaic: the filter array, black and white level, an
    identity colour matrix and the shot's settings in the main IFD (no ``ExposureTime``
    where ``exposure_s`` is None). Written under a temporary name, then renamed."""
    cfa = tuple("RGB".index(c) for c in sensor.pattern)
    one = (1, 1)
    tags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, cfa, True),  # CFAPattern
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, " ".join(camera), True),  # UniqueCameraModel
        (50714, "H", 1, sensor.black, True),  # BlackLevel
        (50717, "H", 1, sensor.white, True),  # WhiteLevel
        (50721, "2i", 9, (*one, 0, 1, 0, 1, 0, 1, *one, 0, 1, 0, 1, 0, 1, *one), True),
        (50728, "2I", 3, (*one, *one, *one), True),  # AsShotNeutral
        (271, "s", 0, camera[0], True), (272, "s", 0, camera[1], True),
        (306, "s", 0, taken.strftime("%Y:%m:%d %H:%M:%S"), True),
        (33437, "2I", 1, _rational(f_number, 100), True),
        (34855, "I", 1, int(iso), True),
        (37386, "2I", 1, _rational(focal_mm, 100), True),
    ]
    if exposure_s is not None:
        tags.append((33434, "2I", 1, _rational(exposure_s), True))
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tifffile.imwrite(tmp, np.asarray(mosaic, np.uint16), photometric=32803, subfiletype=0,
                     extratags=tags, compression=None)
    tmp.replace(path)
