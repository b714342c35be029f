"""Report figures built from capture files and stage outputs (never from ground truth)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .conventions import LUMINANCE, FitArray
from .stores.capture import Capture  # noqa: E402
from .stores.images import read_image  # noqa: E402

__all__ = ["contact_sheet", "plot_hemisphere", "save_figure"]


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure through a temporary name and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path


def contact_sheet(cap: Capture, path: str | Path, thumb: int = 160, cols: int = 10) -> Path:
    """Thumbnails of every view (middle exposure), labelled, held-out views in red."""
    views = cap.views
    rows = int(np.ceil(len(views) / cols))
    first = read_image(views[0].exposures[0].path)
    h, w = first.shape[:2]
    th = int(thumb * h / w)
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 1.6, rows * 1.6 * th / thumb + 0.3),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, v in zip(axes.ravel(), views, strict=False):
        img = read_image(v.exposures[len(v.exposures) // 2].path)
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        step = max(1, w // thumb)
        ax.imshow(img[::step, ::step])
        ax.set_title(v.id + (" (held out)" if v.holdout else ""), fontsize=6,
                     color="red" if v.holdout else "black")
    fig.suptitle(f"{cap.surface_id}: {len(views)} views", fontsize=9)
    return save_figure(fig, path)


def plot_hemisphere(
    directions: np.ndarray, path: str | Path, labels: list[str] | None = None,
    holdout: np.ndarray | None = None, title: str = "view directions",
) -> Path:
    """View directions (N, 3) on the hemisphere: a 3-D scatter and the polar
    projection (zenith as radius), like 004 fig. 8.2/8.3."""
    d = np.asarray(directions, float)
    hold = np.zeros(len(d), bool) if holdout is None else np.asarray(holdout, bool)
    fig = plt.figure(figsize=(9, 4.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 37), np.linspace(0, np.pi / 2, 10))
    ax.plot_wireframe(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v), color="0.85",
                      linewidth=0.5)
    ax.scatter(*d[~hold].T, s=10, c="tab:blue", label="fitted")
    if hold.any():
        ax.scatter(*d[hold].T, s=18, c="tab:red", marker="^", label="held out")
    ax.set_box_aspect((1, 1, 0.5))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.legend(fontsize=7, loc="upper left")
    ax2 = fig.add_subplot(1, 2, 2, projection="polar")
    theta = np.degrees(np.arccos(np.clip(d[:, 2], -1, 1)))
    phi = np.arctan2(d[:, 1], d[:, 0])
    ax2.scatter(phi[~hold], theta[~hold], s=10, c="tab:blue")
    ax2.scatter(phi[hold], theta[hold], s=18, c="tab:red", marker="^")
    ax2.set_ylim(0, 90)
    ax2.set_title("zenith (deg) vs azimuth", fontsize=8)
    fig.suptitle(f"{title} ({len(d)})", fontsize=9)
    return save_figure(fig, path)


def plot_response(g: np.ndarray, path: str | Path, reference: np.ndarray | None = None,
                  title: str = "camera response", reference_label: str = "reference") -> Path:
    """Response curves ln X against level per channel; ``reference`` (256, 3) is drawn
    dashed after matching its offset at level 128 (e.g. a ground truth)."""
    fig, ax = plt.subplots(figsize=(5, 3.6))
    z = np.arange(256)
    for c, col in enumerate("rgb"):
        ax.plot(g[:, c], z, color=col, label=f"recovered {'RGB'[c]}")
        if reference is not None:
            ax.plot(reference[:, c] - reference[128, c] + g[128, c], z, "--", color=col,
                    alpha=0.6, label=f"{reference_label} {'RGB'[c]}")
    ax.set_xlabel("ln relative exposure")
    ax.set_ylabel("pixel level")
    ax.legend(fontsize=6)
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)


def plot_reprojection(records: list[dict], path: str | Path) -> Path:
    """Per-view pose reprojection RMS; dropped views marked."""
    fig, ax = plt.subplots(figsize=(max(5, len(records) * 0.08), 3))
    ids = [r["id"] for r in records]
    rms = [r.get("rms_px", np.nan) for r in records]
    kept = np.array([r["kept"] for r in records])
    x = np.arange(len(ids))
    ax.bar(x[kept], np.array(rms)[kept], color="tab:blue", label="kept")
    if (~kept).any():
        ax.bar(x[~kept], np.nan_to_num(np.array(rms)[~kept], nan=0.0), color="tab:red",
               label="dropped")
    ax.set_xticks(x[:: max(1, len(x) // 20)])
    ax.set_xticklabels(ids[:: max(1, len(x) // 20)], rotation=90, fontsize=6)
    ax.set_ylabel("reprojection RMS (px)")
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def plot_reexposure(hdr_metrics: dict, path: str | Path) -> Path:
    """Re-exposure self-check per view (mean and 95th percentile, 8-bit levels)."""
    per = hdr_metrics["per_view"]
    ids = [k for k, v in per.items() if v.get("reexposure_mean_levels") is not None]
    fig, ax = plt.subplots(figsize=(max(5, len(ids) * 0.08), 3))
    x = np.arange(len(ids))
    ax.bar(x, [per[k]["reexposure_p95_levels"] for k in ids], color="tab:orange",
           label="95th percentile")
    ax.bar(x, [per[k]["reexposure_mean_levels"] for k in ids], color="tab:blue", label="mean")
    ax.set_xticks(x[:: max(1, len(x) // 20)])
    ax.set_xticklabels(ids[:: max(1, len(x) // 20)], rotation=90, fontsize=6)
    ax.set_ylabel("|re-exposed - photo| (levels)")
    m, p95 = hdr_metrics["reexposure_mean_levels"], hdr_metrics["reexposure_p95_levels"]
    if m is not None:
        ax.set_title(f"re-exposure self-check: mean {m:.2f}, p95 {p95:.2f} levels", fontsize=9)
    else:
        ax.set_title("re-exposure self-check: linear input, not applicable", fontsize=9)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


LUMA = LUMINANCE


def plot_map(img: np.ndarray, path: str | Path, title: str, label: str = "",
             cmap: str = "viridis", vmin: float | None = None, vmax: float | None = None) -> Path:
    """One scalar map over the texels (row 0 at the top, as docs/reference/conventions.md)."""
    fig, ax = plt.subplots(figsize=(4.2, 3.6))
    im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, label=label, shrink=0.85)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("texel column")
    ax.set_ylabel("texel row")
    return save_figure(fig, path)


def plot_maps(maps: dict[str, np.ndarray], path: str | Path, title: str, cols: int = 4,
              cmap: str = "viridis", symmetric: bool = False) -> Path:
    """Several scalar maps side by side, each with its own colour scale."""
    n = len(maps)
    cols = min(cols, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 2.6, rows * 2.4), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (name, img) in zip(axes.ravel(), maps.items(), strict=False):
        finite = img[np.isfinite(img)]
        lim = float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0
        kw = {"vmin": -lim, "vmax": lim} if symmetric else {}
        im = ax.imshow(img, cmap="RdBu_r" if symmetric else cmap, interpolation="nearest", **kw)
        fig.colorbar(im, ax=ax, shrink=0.8)
        ax.set_title(name, fontsize=7)
    fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)


def plot_lobes(entries: list[dict], path: str | Path, title: str) -> Path:
    """Radiance against view direction for chosen texels (004 figs. 9.4 and 11.6).

    Each entry: ``label``, ``direction`` (n, 3), ``measured`` (n, 3) and optionally
    ``fitted`` (n, 3). Top row: luminance over the projected hemisphere (x, y of the
    direction) as height, measured dots and fitted crosses. Bottom row (with fits):
    percentage residual ``100 (fitted - measured) / measured`` of the luminance.
    """
    fitted = any("fitted" in e for e in entries)
    n = len(entries)
    fig = plt.figure(figsize=(2.8 * n, 5.2 if fitted else 2.8))
    for k, e in enumerate(entries):
        d = np.asarray(e["direction"])
        lm = np.asarray(e["measured"]) @ LUMA
        ax = fig.add_subplot(2 if fitted else 1, n, k + 1, projection="3d")
        ax.scatter(d[:, 0], d[:, 1], lm, s=4, c=lm, cmap="viridis")
        if "fitted" in e:
            lf = np.asarray(e["fitted"]) @ LUMA
            ax.scatter(d[:, 0], d[:, 1], lf, s=6, marker="x", color="tab:red", linewidths=0.6)
        ax.set_title(e["label"] + ("" if len(d) else ": no valid observation"), fontsize=7)
        ax.tick_params(labelsize=5)
        ax.set_xlabel("x", fontsize=6)
        ax.set_ylabel("y", fontsize=6)
        if "fitted" in e and len(d):  # a texel every view saw saturated has none
            ax2 = fig.add_subplot(2, n, n + k + 1)
            pct = 100 * (lf - lm) / np.maximum(np.abs(lm), 1e-12)
            lim = max(float(np.percentile(np.abs(pct), 98)), 0.5)
            sc = ax2.scatter(d[:, 0], d[:, 1], c=pct, s=8, cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax2.set_aspect("equal")
            ax2.set_xlim(-1, 1)
            ax2.set_ylim(-1, 1)
            ax2.tick_params(labelsize=5)
            ax2.set_title(f"residual %, mean |.| {np.mean(np.abs(pct)):.2f}", fontsize=7)
            fig.colorbar(sc, ax=ax2, shrink=0.7)
    fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)


def default_lobe_texels(S: int, T: int) -> list[tuple[int, int]]:
    """A 3 x 3 spread of texels (patch centres for a 3 x 3 layout)."""
    return [(int((i + 0.5) * T / 3), int((j + 0.5) * S / 3)) for i in range(3) for j in range(3)]


def fit_figures(g, obs, out_dir: str | Path, name: str, predict,
                texels: list[tuple[int, int]] | None = None,
                extra: dict[str, np.ndarray] | None = None) -> list[Path]:
    """Residual maps and lobe plots of a fit store ``g`` (zarr group with ``mpr``,
    ``rmse``, ``status``) against its observation map ``obs``; ``predict(row, col,
    directions)`` evaluates the fitted model of one texel; ``extra`` maps join the
    residual maps."""
    out_dir = Path(out_dir)
    mpr = g[FitArray.MPR][:].astype(float)
    maps = {f"mean % residual {c}": mpr[..., i] for i, c in enumerate("RGB")}
    maps["RMSE (mean of RGB)"] = g[FitArray.RMSE][:].astype(float).mean(-1)
    maps["status (1 ok, 2 too few obs., 3 failed)"] = g[FitArray.STATUS][:].astype(float)
    maps |= extra or {}
    paths = [plot_maps(maps, out_dir / f"{name}_residuals.png", f"{name}: residuals", cols=3)]
    entries = []
    for r, c in texels or default_lobe_texels(g.S, g.T):
        d, measured, _ = obs.texel(r, c)
        entries.append({"label": f"texel [{r}, {c}]", "direction": d,
                        "measured": measured, "fitted": predict(r, c, d)})
    paths.append(plot_lobes(entries, out_dir / f"{name}_lobes.png",
                            f"{name}: measured (dots) and model (crosses)"))
    return paths


def plot_light_rays(rays: dict, lights: list[dict], path: str | Path,
                    max_rays: int = 400) -> Path:
    """The lobe rays (texel centre toward the light) seen from the side (x-z) and from
    the front (y-z), each light's rays in its colour, the lights as stars (mm)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    p, u = rays["origins"], rays["dirs"]
    rng = np.random.default_rng(0)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    top = max([lt["position_mm"][2] for lt in lights] + [float(np.ptp(p[:, :2])) if len(p) else 1])
    for ax, (i, name) in zip(axes, ((0, "x"), (1, "y")), strict=True):
        for k, lt in enumerate(lights):
            idx = np.flatnonzero(lt["inliers"])
            idx = idx[rng.permutation(len(idx))[:max_rays]]
            s = (lt["position_mm"][2] - p[idx, 2]) / np.maximum(u[idx, 2], 1e-6)
            end = p[idx] + s[:, None] * u[idx]
            ax.plot(np.c_[p[idx, i], end[:, i]].T, np.c_[p[idx, 2], end[:, 2]].T,
                    color=colours[k % len(colours)], lw=0.3, alpha=0.3)
            ax.plot(lt["position_mm"][i], lt["position_mm"][2], "*", ms=16, mec="k",
                    color=colours[k % len(colours)], label=f"light {k + 1}")
        ax.set_xlabel(f"{name} (mm)")
        ax.set_ylabel("z (mm)")
        ax.set_ylim(-0.05 * top, 1.3 * top)
        ax.set_aspect("equal", adjustable="box")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"{len(lights)} light(s) where the lobes' mirror rays meet "
                 f"({len(p)} determined lobes)")
    return save_figure(fig, path)


def _label(ax, title: str, xlabel: str, ylabel: str, legend: bool = True) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if legend:
        ax.legend(fontsize=8)
    ax.set_title(title)


def _note(ax, text: str) -> None:
    """A panel that says what is not there instead of a plot."""
    ax.axis("off")
    ax.text(0.5, 0.5, text, ha="center", va="center")


def plot_radiometry(vignetting: np.ndarray | None, field_max: float | None,
                    irradiance: np.ndarray | None, delta_e: list[float] | None,
                    width_mm: float, height_mm: float, path: str | Path,
                    title: str = "") -> Path:
    """The flat-field and colour a capture's frames are read through: the vignetting
    against the field radius (dashed beyond the widest field the card covered), the
    light's relative irradiance over the surface, and the colour chart's CIEDE2000 per
    patch; a panel says so where the capture has no card or chart."""
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    ax = axes[0]
    if vignetting is not None:
        rho = np.linspace(0, 1.5 * np.sqrt(field_max), 200)
        inside = rho <= np.sqrt(field_max)
        lnv = np.stack([np.minimum(rho ** 2, field_max) ** (k + 1)
                        for k in range(len(vignetting))], -1) @ np.asarray(vignetting)
        v = np.exp(lnv)
        ax.plot(rho[inside], v[inside], "k-")
        ax.plot(rho[~inside], v[~inside], "k--", label="held beyond the card")
        _label(ax, "lens vignetting", "field radius (tan of the field angle)",
               "relative illumination V")
    else:
        _note(ax, "no white card:\nno vignetting or light fall-off\ndivided out")
    ax = axes[1]
    if irradiance is not None:
        im = ax.imshow(irradiance, extent=(0, width_mm, 0, height_mm), cmap="magma")
        fig.colorbar(im, ax=ax, shrink=0.8, label="G (mean 1)")
        _label(ax, "the light's relative irradiance", "x (mm)", "y (mm)", legend=False)
    else:
        _note(ax, "light fall-off not divided out")
    ax = axes[2]
    if delta_e is not None:
        ax.bar(np.arange(1, len(delta_e) + 1), delta_e, color="0.4")
        ax.axhline(float(np.mean(delta_e)), color="C3", lw=1,
                   label=f"mean {np.mean(delta_e):.2f}")
        _label(ax, "colour chart", "chart patch", "CIEDE2000 after correction")
    else:
        _note(ax, "no colour chart:\ncamera RGB as merged")
    fig.suptitle(title, y=1.04)
    return save_figure(fig, path)
