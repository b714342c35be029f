"""What every zarr store of a processed folder shares: the completion mark, opening a
finished store, its size on disk and its inputs' modification times; and reading a
small JSON or YAML record with one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import yaml
import zarr

from .. import __version__

__all__ = ["COMPLETE_ATTR", "HEIGHT_ATTR", "MapStore", "SOFTWARE_ATTR", "S_ATTR", "TILE_ATTR",
           "T_ATTR", "UNITS_ATTR", "WIDTH_ATTR", "free_disk_gib", "mtime_ns", "open_complete",
           "read_document", "software", "store_bytes"]

# Set on a store's group only after every chunk is written and just before the rename
# from its temporary name: a store without it is never accepted.
COMPLETE_ATTR = "parammap_complete"

# The map's grid and provenance, carried by every map artifact (zarr attributes of the
# observation map and the fit stores, header attributes of the parameter-map EXRs).
S_ATTR, T_ATTR, TILE_ATTR = "S", "T", "tile"
WIDTH_ATTR, HEIGHT_ATTR = "width_mm", "height_mm"
SOFTWARE_ATTR = "software"
# what an array or a file holds, in words (xarray shows it)
UNITS_ATTR = "units"


def read_document(path: str | Path, error: type[Exception], what: str) -> Any:
    """A small JSON (``.json``) or YAML record, parsed; ``error`` with one line naming
    the file (``what``: the record, for the message) when it cannot be read or parsed."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror})") from None
    try:
        return json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc.msg})") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None


def software() -> str:
    """The provenance string stores carry (``parammap <version>``)."""
    return f"parammap {__version__}"


def mtime_ns(path: str | Path) -> int:
    """A file's modification time (ns), 0 when it is missing: part of the keys that say
    whether a partial store may be resumed."""
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return 0


def free_disk_gib(path: str | Path) -> float:
    """Free space (GiB) on the disk that holds ``path`` or, where it does not exist yet,
    its nearest existing parent."""
    path = Path(path).resolve()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free / 2**30


def store_bytes(path: str | Path) -> int:
    """Bytes on disk of a file or a directory store."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def open_complete(path: str | Path, error: type[Exception], what: str) -> zarr.Group:
    """Open a finished zarr group; ``error`` names a missing or incomplete one."""
    path = Path(path)
    try:
        g = zarr.open_group(path, mode="r")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as exc:
        raise error(f"{path}: no {what} ({exc})") from None
    if not g.attrs.get(COMPLETE_ATTR):
        raise error(f"{path}: incomplete {what} (interrupted run?)")
    return g


class MapStore:
    """A finished zarr store of a map (observation map, fit store) opened for reading:
    its arrays by name (``store[name]``), its attributes and its grid. Subclasses add
    the artifact's own arrays and attributes as properties."""

    def __init__(self, group: zarr.Group, path: str | Path) -> None:
        self.group, self.path = group, Path(path)

    def __getitem__(self, name: str) -> zarr.Array:
        return self.group[name]

    def __contains__(self, name: str) -> bool:
        return name in self.group

    @property
    def attrs(self):
        """The zarr group's attributes, as zarr hands them out (for notebooks and tests;
        the package reads the typed properties)."""
        return self.group.attrs

    @property
    def metadata(self) -> dict[str, Any]:
        """Every attribute (a copy): settings, figures and provenance."""
        return dict(self.group.attrs)

    @property
    def T(self) -> int:
        """Texel rows."""
        return self.group.attrs[T_ATTR]

    @property
    def S(self) -> int:
        """Texel columns."""
        return self.group.attrs[S_ATTR]

    @property
    def tile(self) -> int:
        """Texels across a chunk."""
        return int(self.group.attrs[TILE_ATTR])

    @property
    def width_mm(self) -> float:
        return self.group.attrs[WIDTH_ATTR]

    @property
    def height_mm(self) -> float:
        return self.group.attrs[HEIGHT_ATTR]
