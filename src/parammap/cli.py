"""Command line: ``parammap <stage> ...`` (also ``python -m parammap``).

Every stage of the workflow can run from here without Snakemake. Bad input ends the
command with one line on stderr naming the file and key, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import __version__
from .config import ConfigError
from .errors import InputError

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
    if a.preset.startswith("pbr-"):
        from .synth.pbr import generate_pbr

        generate_pbr(a.out, a.truth, preset=a.preset, seed=a.seed, surface_id=a.id, log=_log)
        return 0
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
    from .capture import load_capture
    from .hdr import response_for_capture, save_response
    from .report import plot_response

    cfg = _stage_config(a)["hdr"]
    cap = load_capture(a.capture, check_images=False)
    out = Path(a.out)
    g, meta = response_for_capture(cap, cfg, log=_log)
    if g is None:
        (out / "camera").mkdir(parents=True, exist_ok=True)
        (out / "camera" / "response.txt").write_text("linear input: no response curve\n")
    else:
        save_response(out / "camera" / "response.csv", g, meta)
        if a.figure:
            from .hdr import load_reference_response

            ref = load_reference_response(a.reference) if a.reference else None
            plot_response(g, a.figure, reference=ref, reference_label=a.reference_label,
                          title=f"{cap.surface_id}: recovered response")
    _log(f"response: {meta['response']} -> {out / 'camera'}")
    return 0


@_command("hdr")
def _hdr(a: argparse.Namespace) -> int:
    import time

    from .capture import load_capture
    from .hdr import load_response, merge_view
    from .metrics import write_metrics

    cfg = _stage_config(a)["hdr"]
    cap = load_capture(a.capture, check_images=False)
    resp = a.response or Path(a.out) / "camera" / "response.csv"
    g = None if cap.response == "linear" else load_response(resp)
    views = [cap.view(v) for v in a.view] if a.view else cap.views
    out = Path(a.out)
    for v in views:
        t0 = time.perf_counter()
        stats = merge_view(v, g, out / "hdr" / f"{v.id}.exr", cfg["low"], cfg["high"])
        stats["seconds"] = time.perf_counter() - t0
        write_metrics(out / "hdr" / f"{v.id}.json", stats)
        _log(f"hdr: {v.id} saturated {stats['saturated_fraction']:.4f}")
    return 0


@_command("calibrate")
def _calibrate(a: argparse.Namespace) -> int:
    from .calibration import (
        CalibrationError,
        calibrate,
        load_intrinsics,
        marker_views,
        save_intrinsics,
    )
    from .capture import load_capture
    from .metrics import write_metrics

    cfg = _stage_config(a)["calibration"]
    cap = load_capture(a.capture)
    out = Path(a.out)
    if cap.intrinsics_path is not None:
        intr = load_intrinsics(cap.intrinsics_path)
        _log(f"calibrate: using saved intrinsics {cap.intrinsics_path}")
    else:
        intr = calibrate(cap, cfg["min_images"], cfg["min_corners"], log=_log)
        hdr = [(v.id, out / "hdr" / f"{v.id}.exr") for v in cap.fitted_views]
        if cfg["use_marker_views"] and len(cap.marker_ids):
            missing = [str(p) for _, p in hdr if not p.is_file()]
            if missing:
                raise CalibrationError(f"calibration.use_marker_views: HDR frames missing "
                                       f"(run the hdr stage first): {missing[0]}...")
            from .hdr import read_hdr

            extra = marker_views(cap, intr, ((vid, read_hdr(p)[0]) for vid, p in hdr),
                                 cfg["min_markers_per_view"], log=_log)
            if extra:
                board = intr
                intr = calibrate(cap, cfg["min_images"], cfg["min_corners"], log=_log,
                                 extra_views=extra, guess=board)
    save_intrinsics(out / "camera" / "intrinsics.yaml", intr)
    write_metrics(out / "metrics" / "calibration.json", {
        "rms_px": intr.rms_px, "images_used": intr.images_used,
        "images_total": len(cap.calibration_images), "fx_px": intr.K[0, 0],
        "fy_px": intr.K[1, 1], "cx_px": intr.K[0, 2], "cy_px": intr.K[1, 2],
        "dist": intr.dist, "per_image_rms_px": intr.per_image_rms_px})
    _log(f"calibrate: rms {intr.rms_px:.3f} px from {intr.images_used} photos")
    return 0


@_command("poses")
def _poses(a: argparse.Namespace) -> int:
    from .capture import load_capture
    from .metrics import write_metrics
    from .poses import run_poses

    full = _stage_config(a)
    cap = load_capture(a.capture)
    out = Path(a.out)
    m = run_poses(cap, out, full["poses"], full["observation"], log=_log)
    write_metrics(out / "metrics" / "poses.json", m)
    if a.figures:
        from .figures import make_figures

        make_figures("poses", a.capture, out, a.figures)
    return 0


@_command("observe")
def _observe(a: argparse.Namespace) -> int:
    from .capture import load_capture
    from .metrics import write_metrics
    from .observation import build_observation_map, observation_figures

    full = _stage_config(a)
    cfg = full["observation"]
    cap = load_capture(a.capture)
    out = Path(a.out)
    m = build_observation_map(
        cap, out, out / "observation.zarr", cfg["texels_x"], cfg["texels_y"], cfg["tile"],
        cfg["max_zenith_deg"], cfg["max_supersample"], a.workers or full["workers"],
        config=full, log=_log)
    write_metrics(out / "metrics" / "observation.json", m)
    if a.figures:
        observation_figures(out / "observation.zarr", a.figures,
                            [tuple(x) for x in cfg["lobe_texels"]] or None)
    _log(f"observation: {m['S']}x{m['T']} texels x {m['views']} views, valid "
         f"{m['valid_fraction']:.3f}, {m['bytes_on_disk'] / 1e6:.1f} MB in "
         f"{m['build_seconds']:.1f} s")
    return 0


def _run_fit(a: argparse.Namespace, name: str, fit, figures, family: str,
             model_args: tuple) -> dict:
    """Fit one model (``family``: the ``fit`` config section, mh or sh) over the
    observation map; write its metrics and figures."""
    from .metrics import write_metrics

    full = _stage_config(a)
    cfg = full["fit"]
    out = Path(a.out)
    m = fit(out / "observation.zarr", out / "fit" / f"{name}.zarr", *model_args, cfg[family],
            cfg["scheduler"], a.workers or cfg["workers"] or full["workers"], log=_log)
    write_metrics(out / "metrics" / f"fit-{name}.json", m)
    if a.figures:
        figures(out / "fit" / f"{name}.zarr", out / "observation.zarr", a.figures, name,
                [tuple(x) for x in full["observation"]["lobe_texels"]] or None)
    return m


@_command("fit-mh")
def _fit_mh(a: argparse.Namespace) -> int:
    from .models.mh import fit_mh_map, mh_figures, parse_lobes

    K = parse_lobes(a.lobes)
    name = f"mh-{K}"
    m = _run_fit(a, name, fit_mh_map, mh_figures, "mh", (K,))
    _log(f"fit-mh: {name} mean % residual {m['mean_percentage_residual']}, "
         f"{m['failed']} failed, {m['texels_per_second']:.1f} texels/s")
    return 0


@_command("fit-sh")
def _fit_sh(a: argparse.Namespace) -> int:
    from .models.sh import fit_sh_map, parse_sh_model, sh_figures

    hemi, n = parse_sh_model(a.model)
    name = f"sh-{hemi}-{n * n}"
    m = _run_fit(a, name, fit_sh_map, sh_figures, "sh", (hemi, n))
    _log(f"fit-sh: {name} mean % residual {m['mean_percentage_residual']}, "
         f"{m['texels_per_second']:.1f} texels/s")
    return 0


@_command("export")
def _export(a: argparse.Namespace) -> int:
    from .holdout import diffuse_map
    from .params import param_map_from_fit, write_param_map

    out = Path(a.out)
    for name in a.model:
        if name == "diffuse":
            pm = diffuse_map(out / "observation.zarr")
        else:
            pm = param_map_from_fit(out / "fit" / f"{name}.zarr")
        path = write_param_map(out / "params" / f"{name}.exr", pm, half=a.half)
        _log(f"export: {path} ({pm.params.shape[-1]} channels, "
             f"{'half' if a.half else 'float32'})")
    return 0


def _surface_maps(a: argparse.Namespace):
    """Processed folder, capture, intrinsics and the parameter maps named by --model."""
    from .calibration import load_intrinsics
    from .capture import load_capture
    from .params import read_param_map

    out = Path(a.out)
    maps = {name: read_param_map(out / "params" / f"{name}.exr") for name in a.model}
    return out, load_capture(a.capture), load_intrinsics(out / "camera" / "intrinsics.yaml"), maps


@_command("holdout")
def _holdout(a: argparse.Namespace) -> int:
    from .holdout import holdout_comparison
    from .metrics import write_metrics

    out, cap, intr, maps = _surface_maps(a)
    res = holdout_comparison(cap, intr, out, maps, out / "holdout", log=_log)
    write_metrics(out / "metrics" / "holdout.json", res)
    return 0


@_command("viewer")
def _viewer(a: argparse.Namespace) -> int:
    import yaml

    from .metrics import read_metrics
    from .viewer import write_viewer

    out, cap, intr, maps = _surface_maps(a)
    recs = yaml.safe_load((out / "camera" / "poses.yaml").read_text())["views"]
    views = [r for r in recs if r["kept"]]
    gamma = 1.0
    hold = out / "metrics" / "holdout.json"
    if hold.is_file():
        g = [v["gamma"] for v in read_metrics(hold)["views"].values()]
        gamma = float(np.median(g)) if g else gamma
    path = write_viewer(a.figures, cap.surface_id, maps, intr, views, gamma)
    _log(f"viewer: open {path}")
    return 0


@_command("figures")
def _figures(a: argparse.Namespace) -> int:
    from .figures import make_figures

    full = _stage_config(a)
    paths = make_figures(a.kind, a.capture, a.out, a.figures, model=a.model,
                         reference=a.reference, reference_label=a.reference_label,
                         models=a.models or [], timings=[Path(p) for p in a.timings or []],
                         lobe_texels=[tuple(x) for x in full["observation"]["lobe_texels"]]
                         or None)
    _log(f"figures {a.kind}: wrote {len(paths)} files to {a.figures}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="parammap", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"parammap {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="<stage>")

    s = sub.add_parser("synth", help="write a synthetic capture and its ground truth")
    s.add_argument("--preset", default="demo",
                   help="tiny | demo | paper (analytic, default demo) | pbr-tiny | pbr-bench | "
                        "pbr-two-lights (Mitsuba 3, needs parammap[pbr])")
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
    for name, helptext in (("response", "recover the camera response from the brackets"),
                           ("hdr", "merge brackets into linear HDR frames"),
                           ("calibrate", "intrinsics from the calibration photos"),
                           ("poses", "pose of every view from the surface markers"),
                           ("observe", "build the observation map (zarr)"),
                           ("fit-mh", "fit the Multiple Highlight model to every texel"),
                           ("fit-sh", "project every texel onto spherical harmonics"),
                           ("export", "write parameter-map EXRs from fit stores"),
                           ("holdout", "compare renders with the held-out photos")):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("capture")
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
        if name == "hdr":
            s.add_argument("--response", help="response CSV (default <out>/camera/response.csv)")
            s.add_argument("--view", action="append", help="only this view (repeatable)")
        if name in ("poses", "observe", "fit-mh", "fit-sh"):
            s.add_argument("--figures", help="report folder for the figures")
        if name in ("observe", "fit-mh", "fit-sh"):
            s.add_argument("--workers", type=int, help="processes (default: config workers)")
        if name == "fit-mh":
            s.add_argument("--lobes", default="1", help="lobes K, or auto (default 1)")
        if name in ("export", "holdout"):
            s.add_argument("--model", action="append", required=True,
                           help="model name (mh-1, sh-lsop-36, diffuse...), repeatable")
        if name == "export":
            s.add_argument("--half", action="store_true", help="half floats (default float32)")
        if name == "fit-sh":
            s.add_argument("--model", default="sh-lsop-36",
                           help="sh-<zh|mirror|lsop|rlsop|wls>-<coefficients>")
    s = sub.add_parser("viewer", help="write the WebGL2 viewer page for the fitted maps")
    s.add_argument("capture")
    s.add_argument("--out", required=True, help="data/processed/<id>")
    s.add_argument("--figures", required=True, help="viewer folder, reports/<id>/viewer")
    s.add_argument("--model", action="append", required=True, help="model name, repeatable")

    s = sub.add_parser("figures", help="report figures and tables from stage outputs")
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
    import cv2

    # OpenCV's parallel reductions (calibration, detection) differ in the last bits from
    # run to run; one thread makes every stage reproducible. Parallelism comes from
    # Snakemake jobs and worker processes instead.
    cv2.setNumThreads(1)
    args = _parser().parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except (InputError, OSError) as exc:  # bad input: one line; anything else is a bug
        print(f"parammap {args.command}: error: {exc}", file=sys.stderr)
        return 2
