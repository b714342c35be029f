"""Compare two runs' outputs: are two processed folders (or report folders) the same?

Reproducibility check for a refactor, a dependency upgrade or another machine: every
file present in both trees is compared by content, not bytes, so what cannot matter
(compression, PNG metadata, key order) does not count:

- OpenEXR: every channel (NaN equal to NaN) and every header attribute;
- zarr stores: every array and the attributes of the store and of each array;
- JSON / YAML (and the viewer's ``data.js``): the parsed values;
- PNG: the decoded pixels;
- CSV and text: line by line (a ``# {json}`` comment line by value);
- anything else (HTML, JS): the bytes.

Timings (keys such as ``seconds``, ``texels_per_second``; ``timings.csv``) differ from
run to run and are skipped. Numbers that differ are reported with their largest
relative difference; a tree is *equal to float precision* when no number moved by more
than ``rtol`` (default 0: identical).

Usage: ``python -m parammap.compare A B [--rtol 1e-6] [--allow-added]``; exit status 0
when the trees agree, 1 when not. With ``--allow-added``, keys, attributes and arrays
that only B has (metadata a newer version writes) are listed but do not count.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
import zarr

from .stores.exr import read_exr

__all__ = ["Difference", "compare_trees", "main"]

#: Keys whose values are timings or machine facts, different on every run.
VOLATILE_KEYS = frozenset({
    "seconds", "texels_per_second", "build_seconds", "sample_seconds", "read_mb_per_s",
    "scheduler", "workers", "wall_seconds", "created", "fit_seconds", "texels_per_s",
})
# timings, and the workflow's validation mark (it names the capture's absolute path)
VOLATILE_FILES = frozenset({"timings.csv", "timings.png", "capture.ok"})
SKIP_DIRS = frozenset({".snakemake", "logs", "__pycache__"})


@dataclass
class Difference:
    """What differs in one file: ``what`` (a key path or array name) and how much."""

    path: str
    what: list[str] = field(default_factory=list)
    max_rel: float = 0.0  # largest relative difference of numbers that moved
    exact: bool = False  # something other than a number differs (shape, text, key)
    added: list[str] = field(default_factory=list)  # keys or arrays only B has

    def only(self, what: str, in_a: bool) -> None:
        """A key, attribute or array present in one tree only: in B, an addition."""
        if in_a:
            self.add(f"{what}: only in A")
        else:
            self.added.append(what)

    def add(self, what: str, rel: float | None = None) -> None:
        self.what.append(what)
        if rel is None:
            self.exact = True
        else:
            self.max_rel = max(self.max_rel, rel)


def _rel(a: np.ndarray, b: np.ndarray) -> float | None:
    """Largest relative difference of two numeric arrays (None: shapes or NaNs differ)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        return None
    if not (np.issubdtype(a.dtype, np.number) and np.issubdtype(b.dtype, np.number)):
        return 0.0 if np.array_equal(a, b) else None
    a, b = a.astype(float), b.astype(float)
    na, nb = np.isnan(a), np.isnan(b)
    if not np.array_equal(na, nb):
        return None
    ok = ~na
    if not ok.any():
        return 0.0
    if not np.array_equal(np.isinf(a[ok]), np.isinf(b[ok])):
        return None
    d = np.abs(a[ok] - b[ok])
    d[np.isinf(a[ok])] = 0.0
    scale = np.maximum(np.abs(a[ok]), np.abs(b[ok]))
    scale[~np.isfinite(scale)] = 1.0
    return float(np.max(np.where(d > 0, d / np.maximum(scale, 1e-300), 0.0), initial=0.0))


def _compare_values(a: Any, b: Any, where: str, diff: Difference) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k in VOLATILE_KEYS:
                continue
            if k not in a or k not in b:
                diff.only(f"{where}/{k}", k in a)
            else:
                _compare_values(a[k], b[k], f"{where}/{k}", diff)
        return
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            diff.add(f"{where}: {len(a)} against {len(b)} items")
            return
        try:
            A, B = np.asarray(a, float), np.asarray(b, float)
        except (TypeError, ValueError):
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                _compare_values(x, y, f"{where}[{i}]", diff)
            return
        r = _rel(A, B)
        if r is None or r > 0:
            diff.add(where, r)
        return
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        r = _rel(np.asarray(a), np.asarray(b))
        if r is None or r > 0:
            diff.add(where, r)
        return
    num = (int, float, np.integer, np.floating)
    if isinstance(a, num) and isinstance(b, num) and not isinstance(a, bool):
        if a == b or (isinstance(a, float) and isinstance(b, float)
                      and math.isnan(a) and math.isnan(b)):
            return
        diff.add(where, abs(a - b) / max(abs(a), abs(b)))
        return
    if a != b and repr(a) != repr(b):  # OpenEXR header types compare by value in repr
        diff.add(f"{where}: {str(a)[:40]!r} against {str(b)[:40]!r}")


def _arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray], where: str,
            diff: Difference) -> None:
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            diff.only(f"{where}{k}", k in a)
            continue
        r = _rel(a[k], b[k])
        if r is None or r > 0:
            diff.add(f"{where}{k}", r)


def _compare_exr(a: Path, b: Path, diff: Difference) -> None:

    (ca, ha), (cb, hb) = read_exr(a), read_exr(b)
    _arrays(ca, cb, "channel ", diff)
    _compare_values(ha, hb, "header", diff)


def _compare_zarr(a: Path, b: Path, diff: Difference) -> None:


    warnings.filterwarnings("ignore", message=".*not recognized as a component")
    ga, gb = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    _compare_values(dict(ga.attrs), dict(gb.attrs), "attrs", diff)
    na = {k for k, _ in ga.arrays()}
    nb = {k for k, _ in gb.arrays()}
    for k in sorted(na | nb):
        if k not in na or k not in nb:
            diff.only(f"array {k}", k in na)
            continue
        r = _rel(ga[k][...], gb[k][...])
        if r is None or r > 0:
            diff.add(f"array {k}", r)
        _compare_values(dict(ga[k].attrs), dict(gb[k].attrs), f"array {k} attrs", diff)


def _compare_png(a: Path, b: Path, diff: Difference) -> None:

    ia = cv2.imread(str(a), cv2.IMREAD_UNCHANGED)
    ib = cv2.imread(str(b), cv2.IMREAD_UNCHANGED)
    if ia is None or ib is None or ia.shape != ib.shape:
        diff.add("image size or format")
    elif not np.array_equal(ia, ib):
        diff.add(f"{int((ia != ib).any(-1).sum() if ia.ndim == 3 else (ia != ib).sum())} "
                 f"pixels differ")


def _load_text(p: Path) -> Any:
    if p.suffix == ".json":
        return json.loads(p.read_text())
    if p.suffix == ".js":  # the viewer's data: ``window.NAME = {json};``
        text = p.read_text()
        return json.loads(text[text.index("=") + 1:].strip().rstrip(";"))

    return yaml.safe_load(p.read_text())


def _compare_lines(a: Path, b: Path, diff: Difference) -> None:
    """Text tables line by line; a ``# {...}`` comment line (JSON, e.g. the response
    CSV's provenance) is compared by value, timings skipped."""
    la, lb = a.read_text().splitlines(), b.read_text().splitlines()
    if a.suffix == ".csv" and la and lb and la[0] == lb[0]:

        keep = [k for k, h in enumerate(next(csv.reader([la[0]])))
                if h not in VOLATILE_KEYS and not h.endswith("seconds")]
        la, lb = ([",".join(r[k] for k in keep if k < len(r)) for r in csv.reader(x)]
                  for x in (la, lb))
    if len(la) != len(lb):
        diff.add(f"{len(la)} against {len(lb)} lines")
        return
    for k, (x, y) in enumerate(zip(la, lb, strict=True)):
        if x == y:
            continue
        if x.startswith("# {") and y.startswith("# {"):
            try:
                _compare_values(json.loads(x[2:]), json.loads(y[2:]), f"line {k + 1}", diff)
                continue
            except json.JSONDecodeError:
                pass
        diff.add(f"line {k + 1}")


def _entries(root: Path) -> Iterator[str]:
    """Relative paths of the comparable entries: files, and zarr stores as one entry."""
    stack = [root]
    while stack:
        d = stack.pop()
        for p in sorted(d.iterdir()):
            if p.name in SKIP_DIRS or p.name.startswith(".") and p.name != ".zarr":
                continue
            if p.is_dir() and p.suffix != ".zarr":
                stack.append(p)
            elif p.name not in VOLATILE_FILES:
                yield p.relative_to(root).as_posix()


def compare_file(a: Path, b: Path, rel: str) -> Difference:
    """Compare one entry (a file or a zarr store) of two trees by content."""
    diff = Difference(rel)
    suffix = a.suffix.lower()
    if suffix == ".zarr":
        _compare_zarr(a, b, diff)
    elif suffix == ".exr":
        _compare_exr(a, b, diff)
    elif suffix in (".json", ".yaml", ".yml") or (
            suffix == ".js" and a.read_text(errors="replace").startswith("window.")):
        _compare_values(_load_text(a), _load_text(b), "", diff)
    elif suffix == ".png":
        _compare_png(a, b, diff)
    elif suffix in (".csv", ".txt"):
        _compare_lines(a, b, diff)
    elif a.read_bytes() != b.read_bytes():
        diff.add("bytes differ")
    return diff


def compare_trees(a: str | Path, b: str | Path) -> tuple[list[Difference], list[str], list[str]]:
    """Compare every entry present in both trees.

    Returns
    -------
    diffs : one :class:`Difference` per compared entry that is not identical.
    only_a, only_b : entries found in one tree only.
    """
    a, b = Path(a), Path(b)
    ea, eb = set(_entries(a)), set(_entries(b))
    diffs = []
    for rel in sorted(ea & eb):
        d = compare_file(a / rel, b / rel, rel)
        if d.what or d.added:
            diffs.append(d)
    return diffs, sorted(ea - eb), sorted(eb - ea)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m parammap.compare", description=__doc__.split(
        "\n\n")[0])
    ap.add_argument("a", type=Path, help="first tree (e.g. data/processed/demo)")
    ap.add_argument("b", type=Path, help="second tree")
    ap.add_argument("--rtol", type=float, default=0.0,
                    help="largest relative difference of a number still counted as equal")
    ap.add_argument("--allow-added", action="store_true",
                    help="keys, attributes or arrays that only B has (new metadata) do not "
                         "count as differences")
    args = ap.parse_args(argv)
    for p in (args.a, args.b):
        if not p.is_dir():
            print(f"compare: {p}: not a folder", file=sys.stderr)
            return 2
    diffs, only_a, only_b = compare_trees(args.a, args.b)
    n = len(set(_entries(args.a)) & set(_entries(args.b)))
    bad = [d for d in diffs if d.exact or d.max_rel > args.rtol
           or (d.added and not args.allow_added)]
    near = [d for d in diffs if d.max_rel and d not in bad]
    for d in diffs:
        kind = "DIFFERS" if d in bad else ("float  " if d.max_rel else "added  ")
        what = d.what + [f"{a}: added" for a in d.added]
        detail = "; ".join(what[:4]) + (f" (+{len(what) - 4})" if len(what) > 4 else "")
        rel = f" max rel {d.max_rel:.2g}" if d.max_rel else ""
        print(f"{kind} {d.path}{rel}: {detail}")
    for p in only_a:
        print(f"only in {args.a}: {p}")
    for p in only_b:
        print(f"only in {args.b}: {p}")
    added = len(diffs) - len(bad) - len(near)
    print(f"compared {n} entries: {n - len(diffs)} identical, {added} identical but for "
          f"added keys, {len(near)} equal within rtol {args.rtol:g}, {len(bad)} different; "
          f"{len(only_a)} + {len(only_b)} in one tree only")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
