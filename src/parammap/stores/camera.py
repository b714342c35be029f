"""The camera: intrinsics (``camera/intrinsics.yaml``) and each view's pose
(``camera/poses.yaml``), with the map grid the poses stage chose."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import InputError
from ..geometry import Intrinsics
from .observation import ObservationError
from .paths import Processed

__all__ = ["PosesError", "ViewPose", "kept_poses", "load_intrinsics", "read_poses",
           "save_intrinsics"]


class PosesError(InputError):
    """A missing or malformed ``camera/poses.yaml``."""


def read_poses(path: str | Path) -> dict[str, Any]:
    """Read ``camera/poses.yaml``: ``views`` (one record per view, kept or dropped, in
    capture order) and the map grid chosen by the poses stage (``map``).

    Raises
    ------
    PosesError
        For a missing file or one without a list of views.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise PosesError(f"{path}: cannot read the poses ({exc.strerror or exc}); run the "
                         "poses stage first") from None
    except yaml.YAMLError as exc:
        raise PosesError(f"{path}: not a poses file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise PosesError(f"{path}: not a poses file (no list of views)")
    return data


def save_intrinsics(path: str | Path, intr: Intrinsics) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {
        "image_size": [int(v) for v in intr.image_size],
        "K": np.asarray(intr.K).tolist(),
        "dist": np.asarray(intr.dist).ravel().tolist(),
        "dist_model": "opencv k1 k2 p1 p2 k3",
        "rms_px": float(intr.rms_px),
        "images_used": int(intr.images_used),
        "per_image_rms_px": intr.per_image_rms_px or {},
    }
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    tmp.replace(path)
    return path


def load_intrinsics(path: str | Path) -> Intrinsics:
    path = Path(path)
    try:
        d = yaml.safe_load(path.read_text())
        K = np.array(d["K"], float).reshape(3, 3)
        dist = np.array(d["dist"], float).ravel()
        size = tuple(int(v) for v in d["image_size"])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: not an intrinsics file ({exc})") from None
    return Intrinsics(K, dist, size, float(d.get("rms_px", float("nan"))),
                      int(d.get("images_used", 0)), d.get("per_image_rms_px"))


@dataclass(frozen=True)
class ViewPose:
    """A kept view: OpenCV pose ``p_cam = R p_world + t`` (mm) and its HDR frame."""

    id: str
    R: np.ndarray
    t: np.ndarray
    hdr: Path
    cov: np.ndarray | None = None  # (6, 6) pose covariance of a partial view
    max_texel_shift: float | None = None  # its texels beyond this shift are left out

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


def kept_poses(processed: str | Path) -> tuple[list[ViewPose], list[str]]:
    """Kept, non-held-out views of a processed folder's ``camera/poses.yaml`` (in file
    order, with their HDR frames) and the ids of the held-out views."""
    proc = Processed(processed)
    poses_yaml = proc.poses
    recs = read_poses(poses_yaml)["views"]
    views, held = [], []
    for r in recs:
        if r.get("holdout"):
            held.append(str(r["id"]))
            continue
        if not r.get("kept"):
            continue
        partial = r.get("partial") is not None and r.get("cov") is not None
        views.append(ViewPose(str(r["id"]), np.asarray(r["R"], float).reshape(3, 3),
                              np.asarray(r["t"], float).ravel(), proc.hdr(str(r["id"])),
                              np.asarray(r["cov"], float) if partial else None,
                              float(r["max_texel_shift"]) if partial else None))
    if not views:
        raise ObservationError(f"{poses_yaml}: no kept view to build an observation map from")
    return views, held


class CalibrationError(InputError):
    """Calibration cannot go on (too few usable board photos...)."""
