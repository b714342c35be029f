"""Command line: ``parammap <stage> ...`` (also ``python -m parammap``).

Every stage of the workflow can run from here without Snakemake. Bad input ends the
command with one line on stderr naming the file and key, and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from pathlib import Path

from . import __version__
from .config import ConfigError
from .errors import InputError
from .stores.paths import Processed

__all__ = ["main"]

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
# the only way to give this package's processes more than one BLAS thread
BLAS_THREADS_OVERRIDE = "PARAMMAP_BLAS_THREADS"

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {}


def _command(name: str):
    def deco(fn):
        _COMMANDS[name] = fn
        return fn
    return deco


logger = logging.getLogger("parammap")


def _log(msg: str) -> None:
    logger.info(msg)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is when a record is emitted (a test harness or
    a caller may swap it after the handler was made)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(verbosity: int = 0) -> None:
    """Route the package's log records to stderr (what Snakemake writes to each rule's
    log file): progress and results at the default level, warnings and errors only with
    ``-q`` (``verbosity`` < 0), debugging detail with ``-v`` (> 0)."""
    level = logging.INFO if verbosity == 0 else (logging.DEBUG if verbosity > 0
                                                 else logging.WARNING)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(
        "%(levelname)s %(name)s: %(message)s" if verbosity > 0 else "%(message)s"))
    logger.handlers[:] = [handler]
    logger.setLevel(level)
    logger.propagate = False


@_command("synth")
def _synth(a: argparse.Namespace) -> int:
    if a.preset.startswith("pbr-"):
        from .synth.pbr import generate_pbr

        generate_pbr(a.out, a.truth, preset=a.preset, seed=a.seed, surface_id=a.id)
    else:
        from .synth.generate import generate

        generate(a.out, a.truth, preset=a.preset, seed=a.seed, workers=a.workers,
                 surface_id=a.id)
    if a.camera_folder:
        from .synth.camera_folder import write_camera_folder
        from .synth.raw import Sensor

        write_camera_folder(a.out, a.camera_folder, seed=a.seed,
                            raw=Sensor() if a.raw else None, truth=a.truth)
    return 0


@_command("validate-capture")
def _validate(a: argparse.Namespace) -> int:
    from .stores.capture import validate_capture

    cap = validate_capture(a.capture)
    n_photos = sum(len(v.exposures) for v in cap.views)
    print(f"{cap.root}: ok - surface {cap.surface_id!r}, {len(cap.views)} views "
          f"({sum(v.holdout for v in cap.views)} held out), {n_photos} photos, "
          f"{len(cap.calibration_images)} calibration images, {len(cap.marker_ids)} markers")
    return 0


@_command("summary")
def _summary(a: argparse.Namespace) -> int:
    from .plots import contact_sheet
    from .stores.capture import load_capture

    cap = load_capture(a.capture)
    out = Path(a.out)
    contact_sheet(cap, out / "contact_sheet.png")
    _log(f"summary: wrote {out / 'contact_sheet.png'}")
    return 0


# stages that read the processed folder, not the capture (their positional argument)
ON_PROCESSED = ("fit-mh", "fit-sh", "fit-svbrdf", "material", "materials", "advise",
                "lights", "best", "export")


def _source(a: argparse.Namespace) -> str:
    """The processed folder a stage on processed outputs reads: its positional argument,
    else ``--out``. A capture folder there (the older spelling) is not read: noted."""
    if a.source is None:
        return a.out
    if (Path(a.source) / "capture.yaml").is_file():
        logger.warning(f"{a.command}: {a.source} is a capture; this stage reads the processed "
                       f"folder ({a.out}), so the capture argument can go")
        return a.out
    return a.source


def _stage_config(a: argparse.Namespace) -> dict:
    from .config import apply_settings, load_config, validate_config

    if a.config:
        cfg = load_config(a.config)
    else:
        import json

        part = json.loads(a.config_json) if getattr(a, "config_json", None) else {}
        if not isinstance(part, dict):
            raise ConfigError("--config-json: expected a JSON object")
        cfg = validate_config({"captures": {"cli": "."}} | part)
    return apply_settings(cfg, getattr(a, "set", None) or [])


@_command("response")
def _response(a: argparse.Namespace) -> int:
    from .stages.hdr import run_response
    from .stores.capture import load_capture

    run_response(load_capture(a.capture, check_images=False), a.out, _stage_config(a),
                 figure=a.figure, reference=a.reference, reference_label=a.reference_label)
    return 0


@_command("hdr")
def _hdr(a: argparse.Namespace) -> int:
    from .stages.hdr import run_hdr
    from .stores.capture import load_capture

    run_hdr(load_capture(a.capture, check_images=False), a.out, _stage_config(a),
            view_ids=a.view, response=a.response)
    return 0


@_command("calibrate")
def _calibrate(a: argparse.Namespace) -> int:
    from .stages.calibration import run_calibration
    from .stores.capture import load_capture

    run_calibration(load_capture(a.capture), a.out, _stage_config(a), workers=a.workers)
    return 0


@_command("poses")
def _poses(a: argparse.Namespace) -> int:
    from .stages.poses import run_poses
    from .stores.capture import load_capture

    run_poses(load_capture(a.capture), a.out, _stage_config(a), workers=a.workers)
    if a.figures:
        from .stages.figures import make_figures

        make_figures("poses", a.capture, a.out, a.figures)
    return 0


def _lobe_texels(config: dict) -> list[tuple[int, int]] | None:
    """The texels whose lobes the figures plot (config ``observation.lobe_texels``)."""
    return [tuple(x) for x in config["observation"]["lobe_texels"]] or None


def _model_figures(a: argparse.Namespace, model: str,
                   texels: list[tuple[int, int]] | None) -> None:
    """A fitted model's map figures, from its fit store, into the report folder."""
    if not a.figures:
        return
    from .conventions import SVBRDF_MODEL
    from .stages.figures import mh_figures, sh_figures, svbrdf_figures

    proc = Processed(a.out)
    fn = mh_figures if model.startswith("mh-") else \
        svbrdf_figures if model == SVBRDF_MODEL else sh_figures
    fn(proc.fit(model), proc.observation, a.figures, model, texels)


@_command("radiometry")
def _radiometry(a: argparse.Namespace) -> int:
    from .stages.radiometry import run_radiometry
    from .stores.capture import load_capture

    run_radiometry(load_capture(a.capture), a.out, _stage_config(a))
    return 0


@_command("observe")
def _observe(a: argparse.Namespace) -> int:
    from .stages.observation import run_observation
    from .stores.capture import load_capture

    full = _stage_config(a)
    run_observation(load_capture(a.capture), a.out, full, workers=a.workers)
    if a.figures:
        from .stages.figures import observation_figures

        observation_figures(Processed(a.out).observation, a.figures, _lobe_texels(full))
    return 0


@_command("fit-mh")
def _fit_mh(a: argparse.Namespace) -> int:
    from .stages.fit import run_fit

    full = _stage_config(a)
    m = run_fit(_source(a), a.out, full, model=f"mh-{a.lobes}", workers=a.workers)
    _model_figures(a, m["model"], _lobe_texels(full))
    return 0


@_command("fit-sh")
def _fit_sh(a: argparse.Namespace) -> int:
    from .stages.fit import run_fit

    full = _stage_config(a)
    m = run_fit(_source(a), a.out, full, model=a.model, workers=a.workers)
    _model_figures(a, m["model"], _lobe_texels(full))
    return 0


@_command("fit-svbrdf")
def _fit_svbrdf(a: argparse.Namespace) -> int:
    from .conventions import SVBRDF_MODEL
    from .stages.fit import run_fit

    full = _stage_config(a)
    m = run_fit(_source(a), a.out, full, model=SVBRDF_MODEL, workers=a.workers)
    _model_figures(a, m["model"], _lobe_texels(full))
    return 0


@_command("material")
def _material(a: argparse.Namespace) -> int:
    from .stages.export import run_material

    run_material(_source(a), a.out, _stage_config(a), model=a.model)
    return 0


@_command("materials")
def _materials(a: argparse.Namespace) -> int:
    from .stages.materials import run_materials

    m = run_materials(_source(a), a.out, _stage_config(a), workers=a.workers)
    _model_figures(a, m["model"], None)
    return 0


@_command("advise")
def _advise(a: argparse.Namespace) -> int:
    from .stages.advisor import run_advisor

    run_advisor(_source(a), a.out, _stage_config(a), figures=a.figures)
    return 0


@_command("lights")
def _lights(a: argparse.Namespace) -> int:
    from .stages.lights import run_lights

    measured = ambient = None
    if a.capture:
        from .stores.capture import load_capture

        cap = load_capture(a.capture)
        measured, ambient = cap.lights, cap.ambient
    run_lights(_source(a), _stage_config(a), figures=a.figures, measured=measured,
               ambient=ambient)
    return 0


@_command("best")
def _best(a: argparse.Namespace) -> int:
    from .stages.best import run_best

    run_best(_source(a), a.out, _stage_config(a), models=a.model, figures=a.figures,
             workers=a.workers)
    return 0


@_command("export")
def _export(a: argparse.Namespace) -> int:
    from .stages.export import run_export

    run_export(_source(a), a.out, _stage_config(a), models=a.model, half=a.half)
    return 0


@_command("holdout")
def _holdout(a: argparse.Namespace) -> int:
    from .stages.holdout import run_holdout
    from .stores.capture import load_capture

    run_holdout(load_capture(a.capture), a.out, _stage_config(a), models=a.model)
    return 0


@_command("viewer")
def _viewer(a: argparse.Namespace) -> int:
    from .stores.capture import load_capture
    from .viewer import write_surface_viewer

    write_surface_viewer(load_capture(a.capture), a.out, a.model, a.figures)
    return 0


@_command("paper")
def _paper(a: argparse.Namespace) -> int:
    from .paper import run_paper

    run_paper(a.out, a.experiment, a.quick, a.capture, a.processed, a.workers)
    return 0


@_command("batch-summary")
def _batch_summary(a: argparse.Namespace) -> int:
    from .stages.figures import batch_summary

    batch_summary(a.processed, a.surface, a.model or [], a.out)
    return 0


@_command("markers")
def _markers(a: argparse.Namespace) -> int:
    from .sheets import check_markers, marker_sheet, write_sheet

    marker = a.marker_mm or 0.2 * min(a.width_mm, a.height_mm)
    sheet, layout = marker_sheet(a.width_mm, a.height_mm, a.dictionary, marker, a.count,
                                 a.gap_mm)
    return _sheet_out(a, "markers", sheet, layout, check_markers(sheet, layout),
                      write_sheet)


@_command("board")
def _board(a: argparse.Namespace) -> int:
    from .sheets import board_sheet, check_board, write_sheet

    sheet, layout = board_sheet(a.squares_x, a.squares_y, a.square_mm,
                                a.marker_mm or 0.72 * a.square_mm, a.dictionary)
    return _sheet_out(a, "board", sheet, layout, check_board(sheet, layout), write_sheet)


@_command("import")
def _import(a: argparse.Namespace) -> int:
    from .stages.importer import run_import

    run_import(a.photos, a.out, layout=a.layout, board=a.board, holdout=a.holdout,
               seed=a.seed, surface_id=a.id, holdout_photos=a.holdout_photos or (),
               flatfield=a.flatfield, chart=a.chart, ambient_share=a.ambient_share,
               card_reflectance=a.card_reflectance)
    return 0


def _sheet_out(a: argparse.Namespace, name: str, sheet, layout: dict, check: dict,
               write) -> int:
    """Write a checked sheet; refuse one whose raster does not show all it should."""
    missing = check.get("missing") or (check["corners"] - check["detected"]
                                       if "corners" in check else 0)
    if missing:
        raise InputError(f"{name}: the sheet rasterised at {check['dpi']} dpi does not show "
                         f"all it should ({missing} not detected); try larger markers")
    paths = write(sheet, layout, a.out, name, check)
    _log(f"{name}: page {sheet.width_mm:.0f} x {sheet.height_mm:.0f} mm, corners within "
         f"{check['max_corner_error_mm']:.3f} mm of the layout at {check['dpi']} dpi; "
         f"wrote {', '.join(str(p) for p in paths)}")
    return 0


@_command("figures")
def _figures(a: argparse.Namespace) -> int:
    from .stages.figures import make_figures

    full = _stage_config(a)
    paths = make_figures(a.kind, a.capture, a.out, a.figures, model=a.model,
                         reference=a.reference, reference_label=a.reference_label,
                         models=a.models or [], timings=[Path(p) for p in a.timings or []],
                         lobe_texels=_lobe_texels(full))
    _log(f"figures {a.kind}: wrote {len(paths)} files to {a.figures}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="parammap", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"parammap {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="<stage>")
    # -v / -q are accepted before or after the stage name
    common = argparse.ArgumentParser(add_help=False)
    for parser in (p, common):
        talk = parser.add_mutually_exclusive_group()
        talk.add_argument("-v", "--verbose", action="store_const", const=1, dest="verbosity",
                          default=argparse.SUPPRESS, help="debugging detail in the log")
        talk.add_argument("-q", "--quiet", action="store_const", const=-1, dest="verbosity",
                          default=argparse.SUPPRESS, help="warnings and errors only")

    def add(name: str, **kw) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], **kw)

    s = add("synth", help="write a synthetic capture and its ground truth")
    s.add_argument("--preset", default="demo",
                   help="tiny | demo | paper | lab (analytic, default demo) | pbr-tiny | "
                        "pbr-tiny-camera | pbr-bench | pbr-two-lights | pbr-two-lights-dense | "
                        "pbr-mirror "
                        "(Mitsuba 3, "
                        "needs parammap[pbr])")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True, help="capture directory to write")
    s.add_argument("--truth", help="ground-truth directory (default <out>.truth)")
    s.add_argument("--workers", type=int, default=1, help="rendering processes")
    s.add_argument("--id", help="surface id (default synth-<preset>)")
    s.add_argument("--camera-folder", help="also write the photos as a camera leaves them "
                   "(JPEG with EXIF, no YAML) and the sheets' layouts, for parammap import")
    s.add_argument("--raw", action="store_true", help="with --camera-folder: DNG files of a "
                   "simulated sensor (Bayer mosaic, black and white level, shot and read "
                   "noise) instead of JPEGs")

    s = add("markers", help="printable ArUco marker sheet around a surface, and its layout")
    s.add_argument("--width-mm", type=float, required=True, help="surface width (mm)")
    s.add_argument("--height-mm", type=float, required=True, help="surface height (mm)")
    s.add_argument("--dictionary", default="DICT_5X5_250", help="OpenCV ArUco dictionary")
    s.add_argument("--marker-mm", type=float,
                   help="marker side (default: a fifth of the surface's shorter side)")
    s.add_argument("--count", type=int, default=8, help="markers, a multiple of 4")
    s.add_argument("--gap-mm", type=float, help="surface edge to markers (default: a "
                                                "quarter of the marker side)")
    s.add_argument("--out", required=True, help="folder for markers.pdf/.svg/.png/.yaml")

    s = add("board", help="printable ChArUco calibration board, and its layout")
    s.add_argument("--squares-x", type=int, default=7)
    s.add_argument("--squares-y", type=int, default=5)
    s.add_argument("--square-mm", type=float, default=30.0)
    s.add_argument("--marker-mm", type=float, help="default: 0.72 of the square")
    s.add_argument("--dictionary", default="DICT_5X5_100", help="OpenCV ArUco dictionary")
    s.add_argument("--out", required=True, help="folder for board.pdf/.svg/.png/.yaml")

    s = add("import", help="a capture from a folder of camera files (EXIF brackets)")
    s.add_argument("photos", help="folder of JPEG/TIFF/PNG photos, searched recursively")
    s.add_argument("--layout", required=True, help="the markers' layout (parammap markers)")
    s.add_argument("--board", help="the board's layout (parammap board); its photos are "
                                   "recognised among the others")
    s.add_argument("--holdout", type=int, help="views held out (default: about 5 %%)")
    s.add_argument("--seed", type=int, default=0, help="draws the held-out views")
    s.add_argument("--holdout-photos", nargs="+", metavar="FILE",
                   help="hold out the views of these camera files instead")
    s.add_argument("--id", help="surface id (default: the capture folder's name)")
    s.add_argument("--flatfield", help="folder of brackets of a white card lying where the "
                                       "surface lies, under the capture's light")
    s.add_argument("--chart", help="folder of one bracket of a ColorChecker Classic under "
                                   "the capture's light")
    s.add_argument("--ambient-share", type=float, nargs="+", metavar="S",
                   help="the room's own light: the share (one value, or R G B, in [0, 1)) "
                        "of a white card's light at the surface's centre that stays with "
                        "the lamps off")
    s.add_argument("--card-reflectance", type=float, nargs="+", metavar="R",
                   help="the white card's diffuse reflectance (one value, or R G B, in "
                        "(0, 1]): sets the relightable map's albedo scale")
    s.add_argument("--out", required=True, help="capture directory to write")

    s = add("validate-capture", help="check a capture directory, images included")
    s.add_argument("capture")

    s = add("summary", help="capture summary figures (contact sheet)")
    s.add_argument("capture")
    s.add_argument("--out", required=True, help="report folder, e.g. reports/<id>")
    for name, helptext in (("response", "recover the camera response from the brackets"),
                           ("hdr", "merge brackets into linear HDR frames"),
                           ("calibrate", "intrinsics from the calibration photos"),
                           ("poses", "pose of every view from the surface markers"),
                           ("radiometry", "vignetting, the light's fall-off and the colour "
                                          "matrix from the white card and colour chart"),
                           ("observe", "build the observation map (zarr)"),
                           ("fit-mh", "fit the Multiple Highlight model to every texel"),
                           ("fit-sh", "project every texel onto spherical harmonics"),
                           ("fit-svbrdf", "fit a GGX microfacet SVBRDF under the found lights"),
                           ("materials", "basis materials (003) from an MH fit, as mh-materials"),
                           ("advise", "the next camera directions to shoot (from an MH fit)"),
                           ("lights", "where the lights are, from an MH fit's lobes"),
                           ("best", "the best model per texel among exported maps"),
                           ("export", "write parameter-map EXRs from fit stores"),
                           ("material", "a relightable map as glTF 2.0 and MaterialX"),
                           ("holdout", "compare renders with the held-out photos")):
        s = add(name, help=helptext)
        if name in ON_PROCESSED:
            s.add_argument("source", nargs="?", help="processed folder the stage reads "
                                                     "(default: --out)")
        else:
            s.add_argument("capture", help="capture folder")
        s.add_argument("--out", required=True, help="data/processed/<id>")
        s.add_argument("--config", help="workflow config (default: built-in defaults)")
        s.add_argument("--config-json", help="config sections as JSON (the workflow's way)")
        s.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                       help="override one config value, e.g. observation.texels_x=512")
        if name == "response":
            s.add_argument("--figure", help="PNG of the response curve")
            s.add_argument("--reference", help="reference curve drawn beside it: colour-hdri "
                                               "CRF .npy, truth response.npz or a CSV")
            s.add_argument("--reference-label", default="reference")
        if name == "best":
            s.add_argument("--model", action="append", required=True,
                           help="candidate model (exported map), repeatable")
        if name == "hdr":
            s.add_argument("--response", help="response CSV (default <out>/camera/response.csv)")
            s.add_argument("--view", action="append", help="only this view (repeatable)")
        if name in ("poses", "observe", "fit-mh", "fit-sh", "fit-svbrdf", "materials", "advise",
                    "lights", "best"):
            s.add_argument("--figures", help="report folder for the figures")
        if name in ("calibrate", "poses", "observe", "fit-mh", "fit-sh", "fit-svbrdf", "best",
                    "materials"):
            s.add_argument("--workers", type=int, help="processes (default: config workers)")
        if name == "fit-mh":
            s.add_argument("--lobes", default="1", help="lobes K, or auto (default 1)")
        if name == "lights":
            s.add_argument("--capture", help="the capture, whose measured lights (if it "
                                             "lists any) are compared with those found, "
                                             "and whose ambient light (if stated) the "
                                             "relightable fit takes")
        if name in ("export", "holdout"):
            s.add_argument("--model", action="append", required=True,
                           help="model name (mh-1, sh-lsop-36, diffuse...), repeatable")
        if name == "export":
            s.add_argument("--half", action="store_true", help="half floats (default float32)")
        if name == "material":
            s.add_argument("--model", default="svbrdf-ggx", help="the relightable map")
        if name == "fit-sh":
            s.add_argument("--model", default="sh-lsop-36",
                           help="sh-<zh|mirror|lsop|rlsop|wls>-<coefficients>")
    s = add("viewer", help="write the WebGL2 viewer page for the fitted maps")
    s.add_argument("capture")
    s.add_argument("--out", required=True, help="data/processed/<id>")
    s.add_argument("--figures", required=True, help="viewer folder, reports/<id>/viewer")
    s.add_argument("--model", action="append", required=True, help="model name, repeatable")

    s = add("paper", help="regenerate 004's experiments under the published conditions")
    s.add_argument("--out", default="reports/paper", help="report folder (reports/paper)")
    s.add_argument("--experiment", action="append",
                   help="only this experiment (repeatable): point_area, second_light, "
                        "sh_sweep, shininess, view_count, initialisers, sizes, sampling")
    s.add_argument("--quick", action="store_true", help="a reduced SH sweep (tests)")
    s.add_argument("--capture", help="a capture for 004 ch. 16's held-out tables")
    s.add_argument("--processed", help="its processed folder (poses, HDR, observation map)")
    s.add_argument("--workers", type=int, default=2, help="processes for those fits")

    s = add("batch-summary", help="one table and figure over every surface of a run")
    s.add_argument("--processed", default="data/processed", help="processed folder root")
    s.add_argument("--surface", action="append", required=True, help="surface id, repeatable")
    s.add_argument("--model", action="append", help="model name, repeatable")
    s.add_argument("--out", default="reports", help="folder for summary.csv and summary.png")

    s = add("figures", help="report figures and tables from stage outputs")
    s.add_argument("kind", help="response | hdr | calibration | poses | observation | model | "
                                "holdout | tables")
    s.add_argument("capture")
    s.add_argument("--out", required=True, help="data/processed/<id>")
    s.add_argument("--figures", required=True, help="report folder, reports/<id>")
    s.add_argument("--model", help="model name for kind model")
    s.add_argument("--models", nargs="*", help="model names for kind tables")
    s.add_argument("--timings", nargs="*", help="Snakemake benchmark files for kind tables")
    s.add_argument("--reference", help="reference response for kind response")
    s.add_argument("--reference-label", default="reference")
    s.add_argument("--config", help="workflow config (default: built-in defaults)")
    s.add_argument("--config-json", help="config sections as JSON")
    s.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE")
    return p


def main(argv: list[str] | None = None) -> int:
    import os

    # One BLAS thread per process: the stages run in parallel over views and texel
    # tiles (worker processes, Snakemake jobs), and a BLAS with a thread per core on
    # top oversubscribes the cores; the fits' many small solves are slower threaded
    # anyway. Snakemake sets OMP_NUM_THREADS and its kin to a job's threads, which the
    # stages spend on worker processes: kept, they made the demo's sh-rlsop-36 fit 98 s
    # (193 s of CPU) where one thread takes 12.5 s (21.5 s). Set for the workers to come
    # (spawned ones read the variables) and for the BLAS already loaded (a call from
    # Python; forked workers inherit it); PARAMMAP_BLAS_THREADS asks for more.
    from threadpoolctl import threadpool_limits

    blas = os.environ.get(BLAS_THREADS_OVERRIDE, "1")
    os.environ.update(dict.fromkeys(BLAS_THREAD_VARIABLES, blas))
    threadpool_limits(int(blas), user_api="blas")
    import cv2

    # OpenCV's parallel reductions (calibration, detection) differ in the last bits from
    # run to run; one thread makes every stage reproducible. Parallelism comes from
    # Snakemake jobs and worker processes instead.
    cv2.setNumThreads(1)
    args = _parser().parse_args(argv)
    setup_logging(getattr(args, "verbosity", 0))
    try:
        return _COMMANDS[args.command](args)
    except (InputError, OSError) as exc:  # bad input: one line; anything else is a bug
        print(f"parammap {args.command}: error: {exc}", file=sys.stderr)
        return 2
