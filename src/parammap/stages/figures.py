"""Report figures and tables of one surface, built only from stage outputs
(``data/processed/<id>``): deleting ``reports/`` and rebuilding it never refits.

Each ``kind`` writes into ``reports/<id>/``:

- ``response``: response.png (recovered curve; a reference beside it when given)
- ``hdr``: reexposure.png (re-exposure self-check per view)
- ``calibration``: calibration.png (per-photo RMS of the board calibration)
- ``radiometry``: radiometry.png (vignetting, the light's irradiance, the colour chart's
  error: the flat-field and colour the frames are read through)
- ``poses``: view_directions.png, pose_reprojection.png, poses.csv (every view, kept
  or dropped and why)
- ``observation``: observation_valid_count.png, observation_lobes.png
- ``model``: <model>_params.png, <model>_residuals.png, <model>_lobes.png
- ``holdout``: holdout.csv, holdout_regions.csv (per region of similar texels),
  holdout/<view>.png (photo / render / difference per model)
- ``tables``: sizes.csv (004 tables 9.1, 11.1, 12.1), models.csv, timings.csv
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..conventions import (
    LUMINANCE,
    MH_KD,
    MH_M,
    SV_ALPHA,
    SV_COAT,
    SV_KD,
    SV_KS,
    SVBRDF_MODEL,
    FitArray,
    mh_dir_z,
    mh_ks,
    mh_lobes,
    mh_sd_dir,
    sh_degree_order,
)
from ..errors import InputError
from ..geometry import texel_centres
from ..models.mh import mh_eval
from ..models.sh.basis import sh_eval
from ..models.svbrdf import svbrdf_eval
from ..plots import (
    default_lobe_texels,
    fit_figures,
    plot_hemisphere,
    plot_lobes,
    plot_map,
    plot_maps,
    plot_radiometry,
    plot_reexposure,
    plot_reprojection,
    plot_response,
    save_figure,
)
from ..stores.camera import read_poses
from ..stores.capture import load_capture
from ..stores.common import store_bytes
from ..stores.fit import open_fit
from ..stores.hdr import is_linear_response, load_reference_response, load_response
from ..stores.images import read_image
from ..stores.metrics import read_metrics
from ..stores.observation import open_observation_map
from ..stores.paths import Processed
from ..stores.radiometry import read_radiometry

__all__ = ["KINDS", "make_figures"]

KINDS = ("response", "hdr", "calibration", "radiometry", "poses", "observation", "model",
         "holdout", "tables")


def _write_csv(path: Path, rows: list[dict]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["empty"])
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return path


def _calibration(proc: Processed, out: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    m = read_metrics(proc.metrics("calibration"))
    per = m.get("per_image_rms_px") or {}
    fig, ax = plt.subplots(figsize=(max(4, len(per) * 0.25), 3))
    ax.bar(range(len(per)), list(per.values()), color="tab:blue")
    ax.set_xticks(range(len(per)))
    ax.set_xticklabels(list(per), rotation=90, fontsize=6)
    ax.set_ylabel("reprojection RMS (px)")
    ax.set_title(f"calibration: RMS {m['rms_px']:.3f} px from {m['images_used']} photos; "
                 f"fx {m['fx_px']:.1f}, fy {m['fy_px']:.1f}, c ({m['cx_px']:.1f}, "
                 f"{m['cy_px']:.1f})", fontsize=8)
    return [save_figure(fig, out / "calibration.png")]


def _poses(proc: Processed, out: Path, width_mm: float, height_mm: float, sid: str) -> list[Path]:

    records = read_poses(proc.poses)["views"]
    paths = [plot_reprojection(records, out / "pose_reprojection.png")]
    paths.append(_write_csv(out / "poses.csv", [{
        "view": r["id"], "holdout": r["holdout"], "kept": r["kept"],
        "markers": len(r.get("markers", [])),
        "rms_px": f"{r['rms_px']:.3f}" if "rms_px" in r else "",
        "shift_mm": f"{r['shift_mm']:.3f}" if "shift_mm" in r else "",
        "texel_shift": f"{r['texel_shift']:.3f}" if "texel_shift" in r else "",
        "direction_sd_deg": f"{r['direction_sd_deg']:.4f}" if "direction_sd_deg" in r else "",
        "region_used": f"{r['partial']:.2f}" if "partial" in r else ("1" if r["kept"] else ""),
        "reason": r.get("reason", r.get("warning", ""))} for r in records]))
    kept = [r for r in records if r["kept"]]
    if kept:
        C = np.array([r["centre_mm"] for r in kept]) - [width_mm / 2, height_mm / 2, 0]
        paths.append(plot_hemisphere(C / np.linalg.norm(C, axis=1, keepdims=True),
                                     out / "view_directions.png",
                                     holdout=np.array([r["holdout"] for r in kept]),
                                     title=f"{sid}: camera directions from poses"))
    return paths


def _holdout(proc: Processed, out: Path) -> list[Path]:
    import matplotlib.pyplot as plt


    m = read_metrics(proc.metrics("holdout"))
    rows = []
    paths = []
    for vid, rec in m["views"].items():
        for name, s in rec["models"].items():
            rows.append({"view": vid, "model": name, "gamma": f"{rec['gamma']:.4g}",
                         "mean_diff_8bit": f"{s['mean_diff_8bit']:.2f}",
                         "std_diff_8bit": f"{s['std_diff_8bit']:.2f}",
                         "psnr_db": f"{s['psnr_db']:.2f}" if s["psnr_db"] else "",
                         "pixels": s["pixels"], "pose_warning": rec.get("pose_warning", "")})
        names = list(rec["models"])
        fig, axes = plt.subplots(len(names), 3, figsize=(7.5, 2.1 * len(names)), squeeze=False)
        photo = read_image(proc.holdout_dir / f"{vid}_photo.png")
        # crop to the sampled region (everything else is black in the photo image)
        ys, xs = np.nonzero(photo.max(-1) > 0)
        crop = (slice(max(ys.min() - 4, 0), ys.max() + 5),
                slice(max(xs.min() - 4, 0), xs.max() + 5)) if ys.size else \
            (slice(None), slice(None))
        photo = photo[crop]
        for k, name in enumerate(names):
            img = read_image(proc.holdout_dir / f"{vid}_{name}.png")[crop]
            diff = read_image(proc.holdout_dir / f"{vid}_{name}_diff.png")[..., 0][crop]
            axes[k, 0].imshow(photo)
            axes[k, 1].imshow(img)
            im = axes[k, 2].imshow(diff, cmap="magma", vmin=0, vmax=64)
            s = rec["models"][name]
            axes[k, 1].set_title(f"{name}", fontsize=7)
            axes[k, 2].set_title(f"|diff| mean {s['mean_diff_8bit']:.2f} "
                                 f"sd {s['std_diff_8bit']:.2f}", fontsize=7)
            for ax in axes[k]:
                ax.axis("off")
        axes[0, 0].set_title(f"held-out photo {vid} (gamma {rec['gamma']:.3g})", fontsize=7)
        fig.colorbar(im, ax=axes[:, 2], shrink=0.5, label="8-bit difference")
        paths.append(save_figure(fig, out / "holdout" / f"{vid}.png"))
    paths.insert(0, _write_csv(out / "holdout.csv", rows))
    paths.insert(1, _write_csv(out / "holdout_regions.csv", region_table(m)))
    return paths


def region_table(m: dict) -> list[dict]:
    """Rows of ``holdout_regions.csv`` from ``metrics/holdout.json``: one per region,
    its description, then each model's mean 8-bit difference over the held-out views
    (pixel-weighted)."""
    names = m.get("models", [])
    rows = []
    for reg in m.get("regions", []):
        j = str(reg["region"])
        row = {"region": j, "texels": reg["texels"],
               "mean_radiance": " ".join(f"{x:.3g}" for x in reg["mean_radiance"] or []),
               "gloss_ratio": f"{reg['gloss_ratio']:.3g}" if reg["gloss_ratio"] else ""}
        for name in names:
            per = [rec["regions"][name][j] for rec in m["views"].values()
                   if j in rec.get("regions", {}).get(name, {})]
            px = sum(e["pixels"] for e in per)
            row[name] = f"{sum(e['mean_diff_8bit'] * e['pixels'] for e in per) / px:.2f}" \
                if px else ""
        rows.append(row)
    return rows


def _tables(proc: Processed, out: Path, models: list[str], timings: list[Path]) -> list[Path]:
    obs_bytes = store_bytes(proc.observation)
    om = read_metrics(proc.metrics("observation"))
    sizes = [{"item": "observation map (zarr, compressed)", "bytes": obs_bytes,
              "MB": f"{obs_bytes / 1e6:.2f}", "ratio_to_observation": "1"},
             {"item": "observation map (uncompressed)", "bytes": om["bytes_uncompressed"],
              "MB": f"{om['bytes_uncompressed'] / 1e6:.2f}",
              "ratio_to_observation": f"{om['bytes_uncompressed'] / obs_bytes:.2f}"}]
    rows = []
    for name in models:
        exr = proc.params(name)
        if exr.is_file():
            b = exr.stat().st_size
            sizes.append({"item": f"params/{name}.exr", "bytes": b, "MB": f"{b / 1e6:.3f}",
                          "ratio_to_observation": f"{b / obs_bytes:.4f}"})
        mf = proc.metrics(f"fit-{name}")
        if mf.is_file():
            m = read_metrics(mf)
            mpr = m.get("mean_percentage_residual") or [float("nan")] * 3
            med = m.get("median_percentage_residual") or [float("nan")] * 3
            rows.append({"model": name, "texels": m["texels"], "fitted": m["fitted"],
                         "failed": m["failed"],
                         "mean_pct_residual_RGB": " ".join(f"{x:.2f}" for x in mpr),
                         "median_pct_residual_RGB": " ".join(f"{x:.2f}" for x in med),
                         "texels_per_s": f"{m['texels_per_second']:.1f}",
                         "seconds": f"{m['seconds']:.1f}"})
    time_rows = []
    for p in sorted(timings):
        lines = Path(p).read_text().splitlines()
        if len(lines) < 2:
            continue
        head, vals = lines[0].split("\t"), lines[1].split("\t")
        rec = dict(zip(head, vals, strict=False))
        time_rows.append({"step": Path(p).stem, "seconds": rec.get("s", ""),
                          "max_rss_mb": rec.get("max_rss", "")})
    return [_write_csv(out / "sizes.csv", sizes), _write_csv(out / "models.csv", rows),
            _write_csv(out / "timings.csv", time_rows)]


def make_figures(kind: str, capture_dir: str | Path, processed: str | Path,
                 out_dir: str | Path, model: str | None = None,
                 reference: str | Path | None = None, reference_label: str = "reference",
                 models: list[str] | None = None, timings: list[Path] | None = None,
                 lobe_texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Build one kind of report figure (see the module docstring)."""
    proc, out = Processed(processed), Path(out_dir)
    if kind not in KINDS:
        raise InputError(f"unknown figure kind {kind!r} (one of {', '.join(KINDS)})")
    cap = load_capture(capture_dir)
    if kind == "response":

        if not proc.response_csv.is_file() or is_linear_response(proc.response_csv):
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(5, 1))
            ax.axis("off")
            ax.text(0.5, 0.5, "linear input: no response curve", ha="center")
            return [save_figure(fig, out / "response.png")]
        g = load_response(proc.response_csv)
        ref = load_reference_response(reference) if reference else None
        return [plot_response(g, out / "response.png", reference=ref,
                              reference_label=reference_label,
                              title=f"{cap.surface_id}: recovered response")]
    if kind == "hdr":
        return [plot_reexposure(read_metrics(proc.metrics("hdr")),
                                out / "reexposure.png")]
    if kind == "calibration":
        return _calibration(proc, out)
    if kind == "radiometry":
        rad = read_radiometry(proc.radiometry)
        colour = read_metrics(proc.metrics("radiometry")).get("colour") or {}
        return [plot_radiometry(rad.vignetting, rad.field_max, rad.irradiance,
                                colour.get("delta_e"), cap.width_mm, cap.height_mm,
                                out / "radiometry.png",
                                f"{cap.surface_id}: flat-field and colour")]
    if kind == "poses":
        return _poses(proc, out, cap.width_mm, cap.height_mm, cap.surface_id)
    if kind == "observation":

        return observation_figures(proc.observation, out, lobe_texels)
    if kind == "model":
        if not model:
            raise InputError("figures model: --model is required")
        fit = proc.fit(model)
        if model.startswith("mh-"):
            return mh_figures(fit, proc.observation, out, model, lobe_texels)
        if model == SVBRDF_MODEL:
            return svbrdf_figures(fit, proc.observation, out, model, lobe_texels)
        return sh_figures(fit, proc.observation, out, model, lobe_texels)
    if kind == "holdout":
        return _holdout(proc, out)
    return _tables(proc, out, models or [], timings or [])


def mh_figures(fit_path: str | Path, obs_path: str | Path, out_dir: str | Path, name: str,
               texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Parameter maps, residual maps and lobe plots (measured vs fitted with percentage
    residuals, like 004 fig. 11.6) of an MH fit store."""
    g = open_fit(fit_path)
    obs = open_observation_map(obs_path)
    out_dir = Path(out_dir)
    p = g[FitArray.PARAMS][:].astype(float)
    K = mh_lobes(p.shape[-1])
    maps = {"Kd (luminance)": p[..., MH_KD] @ LUMINANCE,
            "log10 m": np.log10(np.clip(p[..., MH_M], 1, None))}
    for k in range(K):
        maps[f"lobe {k + 1} Ks (luminance)"] = p[..., mh_ks(k)] @ LUMINANCE
        maps[f"lobe {k + 1} zenith (deg)"] = np.degrees(np.arccos(np.clip(p[..., mh_dir_z(k)],
                                                                          -1, 1)))
    if g.lobes == "auto":
        maps["lobes used"] = g[FitArray.K_USED][:].astype(float)
    if FitArray.LABEL in g:  # the basis materials (parammap.stages.materials)
        lab = g[FitArray.LABEL][:].astype(float)
        maps["basis material (0: diffuse only)"] = np.where(lab < 0, np.nan, lab)
        maps["weight of the chosen material"] = np.nanmax(g[FitArray.WEIGHTS][:], axis=-1)
    if FitArray.SD in g:  # how far each texel can be trusted (parammap.models.mh.uncertainty)
        sd = g[FitArray.SD][:].astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            maps["sd of m / m"] = sd[..., MH_M] / p[..., MH_M]
        maps["lobe 1 direction sd (deg)"] = sd[..., mh_sd_dir(0)]
    paths = [plot_maps(maps, out_dir / f"{name}_params.png", f"{name}: parameter maps")]
    return paths + fit_figures(g, obs, out_dir, name, lambda r, c, d: mh_eval(p[r, c], d),
                               texels)


def sh_figures(fit_path: str | Path, obs_path: str | Path, out_dir: str | Path, name: str,
               texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Coefficient maps of the first bands, residual maps and lobe plots."""
    g = open_fit(fit_path)
    obs = open_observation_map(obs_path)
    out_dir = Path(out_dir)
    n2 = g.coefficients
    c = g[FitArray.COEFFS][:].astype(float).reshape(g.T, g.S, 3, n2)
    lum = c.transpose(0, 1, 3, 2) @ LUMINANCE
    l_, m_ = sh_degree_order(g.n_bands)
    maps = {f"y[{l},{m}] (luminance)": lum[..., i]
            for i, (l, m) in enumerate(zip(l_, m_, strict=True)) if l < 3}
    paths = [plot_maps(maps, out_dir / f"{name}_params.png",
                       f"{name}: coefficients of bands 0-2", cols=5, symmetric=True)]
    extra = {}
    if FitArray.SD in g:  # how far each texel can be trusted (models.sh.coefficient_sd)
        sd = g[FitArray.SD][:].astype(float).reshape(c.shape).transpose(0, 1, 3, 2) @ LUMINANCE
        with np.errstate(invalid="ignore", divide="ignore"):
            extra["sd of y[0,0] / y[0,0]"] = sd[..., 0] / np.abs(lum[..., 0])
        extra["sd of y[1,0] (luminance)"] = sd[..., 2]
    return paths + fit_figures(g, obs, out_dir, name,
                               lambda r, col, d: sh_eval(c[r, col], d), texels, extra)


def svbrdf_figures(fit_path: str | Path, obs_path: str | Path, out_dir: str | Path,
                   name: str, texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Parameter maps (Kd, Ks, GGX alpha and its relative sd, the coat's share),
    residual maps and lobe plots of an svbrdf fit store."""
    g = open_fit(fit_path)
    obs = open_observation_map(obs_path)
    out_dir = Path(out_dir)
    p = g[FitArray.PARAMS][:].astype(float)
    sd = g[FitArray.SD][:].astype(float)
    lights = g.lights  # with a flat-field's irradiance: compared with its observations
    with np.errstate(invalid="ignore", divide="ignore"):
        maps = {"Kd (luminance)": p[..., SV_KD] @ LUMINANCE,
                "Ks (luminance)": p[..., SV_KS] @ LUMINANCE,
                "GGX alpha": p[..., SV_ALPHA],
                "sd of alpha / alpha": sd[..., SV_ALPHA] / p[..., SV_ALPHA],
                "coat (diffuse share)": p[..., SV_COAT]}
    paths = [plot_maps(maps, out_dir / f"{name}_params.png", f"{name}: parameter maps")]

    def predict(r, c, d):
        pt = texel_centres(g.S, g.T, g.width_mm, g.height_mm, [r], [c]).reshape(1, 3)
        return svbrdf_eval(np.repeat(p[r, c][None], len(d), 0), np.repeat(pt, len(d), 0),
                           d, *lights)

    return paths + fit_figures(g, obs, out_dir, name, predict, texels)


def _robust_outliers(values: np.ndarray, k: float = 3.0) -> np.ndarray:
    """Values further than ``k`` scaled MADs from the median (NaN: never)."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    if ok.sum() < 3:
        return np.zeros(v.shape, bool)
    med = np.median(v[ok])
    mad = 1.4826 * np.median(np.abs(v[ok] - med))
    return ok & (np.abs(v - med) > k * max(mad, 1e-9 * max(abs(med), 1.0)))


def batch_summary(processed_dir: str | Path, surfaces: list[str], models: list[str],
                  out_dir: str | Path) -> list[Path]:
    """One row per surface of a run (views kept, calibration and pose RMS, map size,
    per-model fit residual and held-out error, fit time), ``summary.csv`` and
    ``summary.png`` in ``out_dir``; values more than 3 MADs from the run's median are
    marked, so a lab processing many surfaces sees the outliers at a glance."""
    import matplotlib.pyplot as plt

    rows = []
    for sid in surfaces:
        proc = Processed(Path(processed_dir) / sid)

        def metric(stage: str, proc=proc) -> dict:
            path = proc.metrics(stage)
            return read_metrics(path) if path.is_file() else {}

        poses, cal, obs, hold = (metric(s) for s in ("poses", "calibration", "observation",
                                                     "holdout"))
        row = {"surface": sid, "views": poses.get("views"),
               "kept_fraction": poses.get("kept_fraction"),
               "calibration_rms_px": cal.get("rms_px"),
               "pose_median_rms_px": poses.get("median_rms_px"),
               "texels": obs.get("texels"), "valid_fraction": obs.get("valid_fraction")}
        for m in models:
            fit = metric(f"fit-{m}")
            mpr = fit.get("mean_percentage_residual")
            row[f"{m} residual %"] = float(np.mean(mpr)) if mpr else None
            row[f"{m} seconds"] = fit.get("seconds")
            diffs = [v["models"][m]["mean_diff_8bit"] for v in hold.get("views", {}).values()
                     if m in v.get("models", {})]
            row[f"{m} held-out 8-bit"] = float(np.mean(diffs)) if diffs else None
        rows.append(row)
    out = Path(out_dir)
    paths = [_write_csv(out / "summary.csv", rows)]
    cols = [k for k in rows[0] if k != "surface"] if rows else []
    fig, axes = plt.subplots(len(cols), 1, figsize=(max(4.0, 0.35 * len(rows) + 2),
                                                    1.1 * len(cols) + 0.6), squeeze=False)
    x = np.arange(len(rows))
    for ax, col in zip(axes[:, 0], cols, strict=True):
        v = np.array([np.nan if r[col] is None else float(r[col]) for r in rows])
        bad = _robust_outliers(v)
        ax.scatter(x[~bad], v[~bad], s=12, color="tab:blue")
        ax.scatter(x[bad], v[bad], s=24, color="tab:red", marker="x")
        ax.set_ylabel(col, fontsize=6, rotation=0, ha="right", va="center")
        ax.tick_params(labelsize=6)
        ax.set_xticks([])
    if rows:
        axes[-1, 0].set_xticks(x, [r["surface"] for r in rows], rotation=90, fontsize=6)
    fig.suptitle(f"{len(rows)} surfaces (red: more than 3 MADs from the median)", fontsize=8)
    paths.append(save_figure(fig, out / "summary.png"))
    return paths


def observation_figures(store: str | Path, out_dir: str | Path,
                        texels: list[tuple[int, int]] | None = None) -> list[Path]:
    """Valid-observation count per texel and lobe plots of chosen texels, from the store."""
    g = open_observation_map(store)
    out_dir = Path(out_dir)
    S, T = g.S, g.T
    count = g.valid_count()
    paths = [plot_map(count, out_dir / "observation_valid_count.png",
                      f"valid observations per texel ({len(g.view_ids)} views)",
                      "views")]
    texels = texels or default_lobe_texels(S, T)
    entries = []
    for r, c in texels:
        d, measured, v = g.texel(r, c)
        entries.append({"label": f"texel [{r}, {c}] ({int(v.sum())} obs.)",
                        "direction": d, "measured": measured})
    paths.append(plot_lobes(entries, out_dir / "observation_lobes.png",
                            "measured radiance (luminance) against view direction"))
    return paths
