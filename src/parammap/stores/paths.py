"""Where every stage reads and writes in a processed folder (``data/processed/<id>``).

The layout of ``docs/reference/outputs.md``, spelled out once: stages, the CLI, figures
and evaluation ask a :class:`Processed` for their paths instead of joining names, and
``camera/poses.yaml`` has one reader, :func:`read_poses`. The Snakemake rules name the
same files (``workflow/rules``); a test checks that they agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = ["Processed"]


@dataclass(frozen=True)
class Processed:
    """The processed folder of one surface; every path of docs/reference/outputs.md is a member."""

    root: Path

    def __init__(self, root: str | Path | Processed) -> None:
        object.__setattr__(self, "root", Path(root.root if isinstance(root, Processed)
                                              else root))

    def __fspath__(self) -> str:
        return str(self.root)

    @property
    def capture_ok(self) -> Path:
        """The workflow's mark that the capture passed validation."""
        return self.root / "capture.ok"

    # camera/
    @property
    def camera(self) -> Path:
        return self.root / "camera"

    @property
    def response_csv(self) -> Path:
        """Recovered response, ``ln X`` per 8-bit level and channel (for linear input a
        file that says so)."""
        return self.camera / "response.csv"

    @property
    def intrinsics(self) -> Path:
        return self.camera / "intrinsics.yaml"

    @property
    def lights(self) -> Path:
        """The lights found from the lobes (:mod:`parammap.stores.lights`)."""
        return self.camera / "lights.yaml"

    @property
    def radiometry(self) -> Path:
        """Flat-field and colour correction (:mod:`parammap.stores.radiometry`)."""
        return self.camera / "radiometry.json"

    @property
    def poses(self) -> Path:
        return self.camera / "poses.yaml"

    # hdr/
    @property
    def hdr_dir(self) -> Path:
        return self.root / "hdr"

    def hdr(self, view_id: str) -> Path:
        """Merged linear HDR frame of a view."""
        return self.hdr_dir / f"{view_id}.exr"

    def hdr_stats(self, view_id: str) -> Path:
        """Per-view merge statistics (gathered into ``metrics/hdr.json``)."""
        return self.hdr_dir / f"{view_id}.json"

    # maps
    @property
    def observation(self) -> Path:
        return self.root / "observation.zarr"

    def fit(self, model: str) -> Path:
        return self.root / "fit" / f"{model}.zarr"

    def params(self, model: str) -> Path:
        return self.root / "params" / f"{model}.exr"

    def gltf(self, model: str) -> Path:
        """A relightable map as glTF 2.0 (:mod:`parammap.stores.material`), its textures
        beside it."""
        return self.root / "params" / f"{model}.gltf"

    def mtlx(self, model: str) -> Path:
        """A relightable map as MaterialX (:mod:`parammap.stores.material`)."""
        return self.root / "params" / f"{model}.mtlx"

    # evaluation
    @property
    def holdout_dir(self) -> Path:
        """Renders, photos and difference images of the held-out views."""
        return self.root / "holdout"

    def metrics(self, stage: str) -> Path:
        """``metrics/<stage>.json``: ``hdr``, ``calibration``, ``poses``, ``observation``,
        ``fit-<model>``, ``holdout``."""
        return self.root / "metrics" / f"{stage}.json"


