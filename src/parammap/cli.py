"""Command line: ``parammap <stage> ...`` (also ``python -m parammap``).

Every stage of the workflow can run from here without Snakemake. Bad input ends the
command with one line on stderr naming the file and key, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from . import __version__
from .capture import CaptureError
from .config import ConfigError
from .imageio import ImageReadError

__all__ = ["main"]

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}


def _command(name: str):
    def deco(fn):
        _COMMANDS[name] = fn
        return fn
    return deco


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@_command("synth")
def _synth(a: argparse.Namespace) -> int:
    from .synth.generate import generate

    generate(a.out, a.truth, preset=a.preset, seed=a.seed, workers=a.workers,
             surface_id=a.id, log=_log)
    return 0


@_command("validate-capture")
def _validate(a: argparse.Namespace) -> int:
    from .capture import validate_capture

    cap = validate_capture(a.capture)
    n_photos = sum(len(v.exposures) for v in cap.views)
    print(f"{cap.root}: ok - surface {cap.surface_id!r}, {len(cap.views)} views "
          f"({sum(v.holdout for v in cap.views)} held out), {n_photos} photos, "
          f"{len(cap.calibration_images)} calibration images, {len(cap.marker_ids)} markers")
    return 0


@_command("summary")
def _summary(a: argparse.Namespace) -> int:
    from .capture import load_capture
    from .report import contact_sheet

    cap = load_capture(a.capture)
    out = Path(a.out)
    contact_sheet(cap, out / "contact_sheet.png")
    _log(f"summary: wrote {out / 'contact_sheet.png'}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="parammap", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"parammap {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="<stage>")

    s = sub.add_parser("synth", help="write a synthetic capture and its ground truth")
    s.add_argument("--preset", default="demo", help="tiny | demo | paper (default demo)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True, help="capture directory to write")
    s.add_argument("--truth", help="ground-truth directory (default <out>.truth)")
    s.add_argument("--workers", type=int, default=1, help="rendering processes")
    s.add_argument("--id", help="surface id (default synth-<preset>)")

    s = sub.add_parser("validate-capture", help="check a capture directory, images included")
    s.add_argument("capture")

    s = sub.add_parser("summary", help="capture summary figures (contact sheet)")
    s.add_argument("capture")
    s.add_argument("--out", required=True, help="report folder, e.g. reports/<id>")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except (CaptureError, ConfigError, ImageReadError, ValueError) as exc:
        print(f"parammap {args.command}: error: {exc}", file=sys.stderr)
        return 2
