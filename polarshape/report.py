"""The run report: ``report.html`` with PNG plots in ``report/``, or one ``report.png`` summary.

Contents: normal map and albedo; DoLP and AoLP observed vs rendered (the brightest light); fit curves
(DoLP against the viewing angle θ_V = ∠(N, V), intensity / (E · albedo) against the lighting angle
θ_L = ∠(N, L), as in figures 4–5 of Ichikawa et al. 2023: binned medians of the observations and of
the fitted model, with a sample of the observations as dots); residual maps (RMS over the lights of
the s0 and DoLP residuals); parameters, metrics, timings, skipped steps; the angular-error map and
its histogram when the capture has ground-truth normals.

Angles shown in degrees (user-facing); AoLP from image x toward image y (down), spec §1.
Plots are drawn with matplotlib's object API (no pyplot, no global backend state) and written
atomically.
"""

from __future__ import annotations

import html
import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from polarshape.imaging.stokes import aolp, dolp
from polarshape.checks import to_numpy
from polarshape.io.atomic import atomic_path, atomic_write_text

logger = logging.getLogger(__name__)

__all__ = ["ReportData", "fit_curves", "write_report"]

_BINS_DEG = np.arange(0.0, 90.0 + 1e-9, 3.0)
_MIN_PER_BIN = 5


@dataclass
class ReportData:
    """Everything the report shows (H × W super-pixels, K lights; numpy arrays).

    Attributes:
        normals: (H, W, 3) camera-frame unit normals, NaN outside the mask.
        albedo: (H, W) albedo map or None.
        mask: (H, W) bool.
        observed: (K, 3, H, W) observed Stokes (fraction of full scale).
        rendered: (K, 3, H, W) Stokes of the fitted model, or None.
        lights: (K, H, W, 3) unit directions surface → light (per pixel, for every light type).
        irradiance: (K, H, W) relative irradiance E.
        view: (H, W, 3) unit directions surface → camera.
        valid: (K, H, W) bool observations used (not dark, not saturated), or None (= all).
        params: the params.json content so far (model, params, metrics, timings_s, skipped, ...).
        error_map: (H, W) angular error against ground truth, degrees (NaN = not evaluated), or None.
        seed: seed of the sample of observations drawn as dots.
        max_curve_pixels: most (pixel, light) observations used for the fit curves.
    """

    normals: np.ndarray
    albedo: np.ndarray | None
    mask: np.ndarray
    observed: np.ndarray
    rendered: np.ndarray | None
    lights: np.ndarray
    irradiance: np.ndarray
    view: np.ndarray
    valid: np.ndarray | None
    params: dict[str, Any]
    error_map: np.ndarray | None = None
    seed: int = 0
    max_curve_pixels: int = 20000


# --- derived quantities ------------------------------------------------------------------------


def _dolp(stokes: np.ndarray) -> np.ndarray:
    """(..., 3, H, W) → (..., H, W) DoLP (:func:`polarshape.imaging.stokes.dolp`), NaN where s0 ≤ 0
    (a figure shows no value there rather than one bounded by an eps)."""
    rho = to_numpy(dolp(torch.from_numpy(np.ascontiguousarray(stokes)), eps=0.0))
    return np.where(stokes[..., 0, :, :] > 0, rho, np.nan)


def _aolp_deg(stokes: np.ndarray) -> np.ndarray:
    """(..., 3, H, W) → (..., H, W) AoLP in degrees, (−90, 90], from image x toward image y
    (:func:`polarshape.imaging.stokes.aolp`)."""
    return np.degrees(to_numpy(aolp(torch.from_numpy(np.ascontiguousarray(stokes)))))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between (..., 3) vectors in degrees (atan2 form, spec §3)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def _binned_median(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres and medians of y in 3° bins of x (NaN where a bin has < 5 samples)."""
    centres = 0.5 * (_BINS_DEG[:-1] + _BINS_DEG[1:])
    medians = np.full(centres.shape, np.nan)
    index = np.digitize(x, _BINS_DEG) - 1
    for b in range(centres.size):
        sel = y[(index == b) & np.isfinite(y)]
        if sel.size >= _MIN_PER_BIN:
            medians[b] = np.median(sel)
    return centres, medians


def fit_curves(data: ReportData) -> dict[str, np.ndarray]:
    """Samples and binned medians for the fit-curve plots.

    Returns:
        dict with ``theta_v`` / ``dolp_obs`` / ``dolp_fit`` (sampled observations, degrees and DoLP),
        ``theta_l`` / ``shading_obs`` / ``shading_fit`` (intensity / (E · albedo)), and the binned
        medians ``*_bins``, ``dolp_obs_med``, ``dolp_fit_med``, ``shading_obs_med``,
        ``shading_fit_med`` (fit entries only when a rendering exists).
    """
    k, _, h, w = data.observed.shape
    normals = np.broadcast_to(data.normals[None], (k, h, w, 3))
    lights, irr = data.lights, data.irradiance  # (K, H, W, 3), (K, H, W)
    use = np.broadcast_to(data.mask[None], (k, h, w)) & np.all(np.isfinite(normals), axis=-1)
    if data.valid is not None:
        use = use & data.valid
    idx = np.flatnonzero(use)
    rng = np.random.default_rng(data.seed)
    if idx.size > data.max_curve_pixels:
        idx = np.sort(rng.choice(idx, data.max_curve_pixels, replace=False))
    kk, yy, xx = np.unravel_index(idx, (k, h, w))
    n = normals[kk, yy, xx]  # (M, 3)
    out: dict[str, np.ndarray] = {
        "theta_v": _angle_deg(n, data.view[yy, xx]),
        "theta_l": _angle_deg(n, lights[kk, yy, xx]),
    }
    scale = irr[kk, yy, xx]
    if data.albedo is not None:
        scale = scale * data.albedo[yy, xx]
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(scale > 0, scale, np.nan)
        out["dolp_obs"] = _dolp(data.observed)[kk, yy, xx]
        out["shading_obs"] = data.observed[kk, 0, yy, xx] / scale
        if data.rendered is not None:
            out["dolp_fit"] = _dolp(data.rendered)[kk, yy, xx]
            out["shading_fit"] = data.rendered[kk, 0, yy, xx] / scale
    for key, x in (("dolp", "theta_v"), ("shading", "theta_l")):
        for kind in ("obs", "fit"):
            if f"{key}_{kind}" in out:
                out[f"{key}_bins"], out[f"{key}_{kind}_med"] = _binned_median(out[x], out[f"{key}_{kind}"])
    return out


def _reference_light(data: ReportData) -> int:
    """The light with the brightest mean s0 inside the mask."""
    s0 = np.where(data.mask[None], data.observed[:, 0], np.nan)
    means = np.nanmean(s0.reshape(s0.shape[0], -1), axis=1)
    return int(np.nanargmax(means)) if np.isfinite(means).any() else 0


def _masked(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, image, np.nan)


# --- panels ------------------------------------------------------------------------------------


def _image(ax: Axes, image: np.ndarray, title: str, *, cmap: str | None = "viridis", vmin: float | None = None,
           vmax: float | None = None, colorbar: bool = True) -> None:
    shown = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if colorbar and image.ndim == 2:
        ax.figure.colorbar(shown, ax=ax, fraction=0.046, pad=0.04)


def _panel_normals(ax: Axes, data: ReportData) -> None:
    rgb = np.clip((np.nan_to_num(data.normals) + 1.0) / 2.0, 0.0, 1.0)
    rgb[~np.all(np.isfinite(data.normals), axis=-1)] = 0.0
    _image(ax, rgb, "normal map (RGB = (n+1)/2, camera frame)", cmap=None, colorbar=False)


def _panel_albedo(ax: Axes, data: ReportData) -> None:
    if data.albedo is None:
        ax.axis("off")
        ax.text(0.5, 0.5, "no albedo map", ha="center", va="center")
        return
    finite = data.albedo[np.isfinite(data.albedo)]
    vmax = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    _image(ax, data.albedo, "albedo", cmap="gray", vmin=0.0, vmax=max(vmax, 1e-12))


def _panel_polarisation(axes: Sequence[Axes], data: ReportData) -> None:
    """Four panels: DoLP observed, DoLP rendered, AoLP observed, AoLP rendered (reference light)."""
    k = _reference_light(data)
    used = data.mask if data.valid is None else data.mask & data.valid[k]  # dark pixels have meaningless DoLP
    obs_dolp = _masked(_dolp(data.observed[k]), used)
    top = float(np.nanpercentile(obs_dolp, 99)) if np.isfinite(obs_dolp).any() else 1.0
    top = max(top, 1e-3)
    _image(axes[0], obs_dolp, f"DoLP observed (light {k})", vmin=0.0, vmax=top)
    _image(axes[2], _masked(_aolp_deg(data.observed[k]), used), "AoLP observed, deg", cmap="twilight",
           vmin=-90.0, vmax=90.0)
    if data.rendered is None:
        for ax in (axes[1], axes[3]):
            ax.axis("off")
            ax.text(0.5, 0.5, "no rendering\n(model without one)", ha="center", va="center")
        return
    fit_dolp = _masked(_dolp(data.rendered[k]), used)
    _image(axes[1], fit_dolp, f"DoLP rendered ({data.params.get('model', '')})", vmin=0.0, vmax=top)
    fit_aolp = _masked(_aolp_deg(data.rendered[k]), used & (np.nan_to_num(fit_dolp) > 1e-6))
    _image(axes[3], fit_aolp, "AoLP rendered, deg (where DoLP > 0)", cmap="twilight", vmin=-90.0, vmax=90.0)


def _curve(ax: Axes, x: np.ndarray, y: np.ndarray, bins: np.ndarray, med_obs: np.ndarray, med_fit: np.ndarray | None,
           xlabel: str, ylabel: str, title: str) -> None:
    ax.scatter(x, y, s=1, alpha=0.15, color="0.5", rasterized=True, label="observations")
    ax.plot(bins, med_obs, "o-", color="C0", ms=3, label="observed (median)")
    if med_fit is not None:
        ax.plot(bins, med_fit, "s--", color="C3", ms=3, label="model (median)")
    finite = y[np.isfinite(y)]
    if finite.size:
        ax.set_ylim(0.0, max(float(np.percentile(finite, 99)) * 1.1, 1e-3))
    ax.set_xlim(0, 90)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left")


def _panel_curves(axes: Sequence[Axes], data: ReportData) -> None:
    c = fit_curves(data)
    if c["theta_v"].size == 0:
        for ax in axes:
            ax.axis("off")
            ax.text(0.5, 0.5, "no valid observation", ha="center", va="center")
        return
    _curve(axes[0], c["theta_v"], c["dolp_obs"], c["dolp_bins"], c["dolp_obs_med"], c.get("dolp_fit_med"),
           "viewing angle θ_V = ∠(N, V), deg", "DoLP", "DoLP vs viewing angle")
    ylabel = "s0 / (E · albedo)" if data.albedo is not None else "s0 / E"
    _curve(axes[1], c["theta_l"], c["shading_obs"], c["shading_bins"], c["shading_obs_med"], c.get("shading_fit_med"),
           "lighting angle θ_L = ∠(N, L), deg", ylabel, "intensity vs lighting angle")


def _residual_maps(data: ReportData) -> tuple[np.ndarray, np.ndarray] | None:
    """(H, W) RMS over the used lights of the relative s0 residual and of the DoLP residual."""
    if data.rendered is None:
        return None
    use = data.valid if data.valid is not None else np.ones(data.observed[:, 0].shape, bool)
    s0_obs, s0_fit = data.observed[:, 0], data.rendered[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        count = use.sum(0)  # (H, W)
        mean_s0 = np.where(use, s0_obs, 0.0).sum(0) / count  # (H, W), NaN where no light is used
        rel = np.where(use, (s0_fit - s0_obs) / mean_s0[None], np.nan)
        d_dolp = np.where(use, _dolp(data.rendered) - _dolp(data.observed), np.nan)
        rel_rms = np.sqrt(np.nansum(rel**2, axis=0) / count)
        dolp_rms = np.sqrt(np.nansum(d_dolp**2, axis=0) / count)
    ok = data.mask & (count > 0)
    return np.where(ok, rel_rms, np.nan), np.where(ok, dolp_rms, np.nan)


def _panel_residuals(axes: Sequence[Axes], data: ReportData) -> None:
    maps = _residual_maps(data)
    if maps is None:
        for ax in axes:
            ax.axis("off")
            ax.text(0.5, 0.5, "no rendering: no residuals", ha="center", va="center")
        return
    rel, dolp_rms = maps
    top = float(np.nanpercentile(rel, 99)) if np.isfinite(rel).any() else 1.0
    _image(axes[0], rel, "RMS s0 residual / mean s0", cmap="magma", vmin=0.0, vmax=max(top, 1e-6))
    top = float(np.nanpercentile(dolp_rms, 99)) if np.isfinite(dolp_rms).any() else 1.0
    _image(axes[1], dolp_rms, "RMS DoLP residual", cmap="magma", vmin=0.0, vmax=max(top, 1e-6))


def _panel_error(axes: Sequence[Axes], data: ReportData) -> None:
    err = data.error_map
    assert err is not None
    finite = err[np.isfinite(err)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    _image(axes[0], err, "angular error vs ground truth, deg", cmap="inferno", vmin=0.0, vmax=max(top, 1e-3))
    ax = axes[1]
    if finite.size:
        ax.hist(finite, bins=60, range=(0.0, max(top, 1e-3)), color="C1")
        for label, value, style in (("mean", finite.mean(), "-"), ("median", np.median(finite), "--"),
                                    ("p90", np.percentile(finite, 90), ":")):
            ax.axvline(value, color="k", linestyle=style, label=f"{label} {value:.2f}°")
        ax.legend(fontsize=7)
    ax.set_xlabel("angular error, deg")
    ax.set_ylabel("pixels")
    ax.set_title("error histogram", fontsize=9)


# --- text --------------------------------------------------------------------------------------


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if not math.isfinite(value) else f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items())
    return str(value)


def _flat_metrics(metrics: dict[str, Any]) -> list[tuple[str, str]]:
    rows = []
    for group, values in metrics.items():
        if isinstance(values, dict):
            rows += [(f"{group}.{k}", _fmt(v)) for k, v in values.items()]
        else:
            rows.append((group, _fmt(values)))
    return rows


def _text_lines(params: dict[str, Any]) -> list[str]:
    lines = [f"model: {params.get('model')}"]
    lines += [f"  {k} = {_fmt(v)}" for k, v in (params.get("params") or {}).items()]
    lines += ["metrics:"] + [f"  {k} = {v}" for k, v in _flat_metrics(params.get("metrics") or {})]
    lines += ["timings (s):"] + [f"  {k}: {v:.2f}" for k, v in (params.get("timings_s") or {}).items()]
    lines += ["skipped:"] + [f"  {s}" for s in params.get("skipped") or []]
    return lines


# --- output ------------------------------------------------------------------------------------


def _save(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    return path


def _figure(ncols: int, nrows: int = 1, size: float = 3.6) -> tuple[Figure, list[Axes]]:
    fig = Figure(figsize=(size * ncols, size * nrows * 0.9), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel().tolist()
    return fig, axes


def _table(title: str, rows: Sequence[tuple[str, str]]) -> str:
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<h2>{html.escape(title)}</h2><table>{body}</table>"


def _write_html(folder: Path, data: ReportData) -> list[Path]:
    plots_dir = folder / "report"
    plots: list[tuple[str, Path]] = []
    figures: list[tuple[str, str, int, int, Callable[[list[Axes]], None]]] = [
        ("maps", "Normal map and albedo", 2, 1, lambda ax: (_panel_normals(ax[0], data), _panel_albedo(ax[1], data))),
        ("polarisation", "DoLP and AoLP, observed vs rendered", 2, 2, lambda ax: _panel_polarisation(ax, data)),
        ("fit_curves", "Fit curves", 2, 1, lambda ax: _panel_curves(ax, data)),
        ("residuals", "Residual maps", 2, 1, lambda ax: _panel_residuals(ax, data)),
    ]
    if data.error_map is not None:
        figures.append(("error_map", "Angular error against ground truth", 2, 1, lambda ax: _panel_error(ax, data)))
    for name, title, ncols, nrows, draw in figures:
        fig, axes = _figure(ncols, nrows)
        draw(axes)
        plots.append((title, _save(fig, plots_dir / f"{name}.png")))
    p = data.params
    sections = [
        _table("Parameters", [("model", str(p.get("model")))] + [(k, _fmt(v)) for k, v in (p.get("params") or {}).items()]),
        _table("Metrics", _flat_metrics(p.get("metrics") or {})) if p.get("metrics") else "<h2>Metrics</h2><p>no ground truth</p>",
        _table("Timings (s)", [(k, f"{v:.3f}") for k, v in (p.get("timings_s") or {}).items()]),
        _table("Skipped", [(s.split(":", 1)[0], s.split(":", 1)[-1].strip()) for s in p.get("skipped") or []]),
        _table("Capture", [(k, _fmt(v)) for k, v in (p.get("capture") or {}).items()]),
    ]
    images = "".join(
        f'<h2>{html.escape(title)}</h2><img src="report/{html.escape(path.name)}" alt="{html.escape(title)}">'
        for title, path in plots
    )
    page = (
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>polarshape report</title><style>"
        "body{font-family:sans-serif;margin:2em;max-width:1100px}table{border-collapse:collapse}"
        "td{border:1px solid #ccc;padding:2px 8px;font-size:90%}img{max-width:100%}</style></head><body>"
        f"<h1>polarshape run report</h1><p>{html.escape(str(p.get('summary', '')))}</p>"
        f"{images}{''.join(sections)}"
        f"<h2>params.json (at report time)</h2><pre>{html.escape(json.dumps(p, indent=1, default=str)[:20000])}</pre>"
        "</body></html>"
    )
    report = atomic_write_text(folder / "report.html", page)
    return [report] + [path for _, path in plots]


def _write_png(folder: Path, data: ReportData) -> list[Path]:
    rows = 4 if data.error_map is not None else 3
    fig, axes = _figure(4, rows, size=3.4)
    _panel_normals(axes[0], data)
    _panel_albedo(axes[1], data)
    _panel_curves(axes[2:4], data)
    _panel_polarisation(axes[4:8], data)
    _panel_residuals(axes[8:10], data)
    text_axes = axes[10:12]
    if data.error_map is not None:
        _panel_error(axes[12:14], data)
        text_axes = axes[10:12] + axes[14:16]
    lines = _text_lines(data.params)
    per = math.ceil(len(lines) / len(text_axes))
    for i, ax in enumerate(text_axes):
        ax.axis("off")
        ax.text(0.0, 1.0, "\n".join(lines[i * per:(i + 1) * per]), va="top", ha="left", family="monospace", fontsize=7)
    return [_save(fig, folder / "report.png")]


def write_report(folder: str | Path, data: ReportData, *, fmt: Literal["html", "png"] = "html") -> list[Path]:
    """Write the report into ``folder`` (a result folder under construction).

    Args:
        folder: destination folder; ``html`` writes report.html and report/*.png, ``png`` report.png.
        data: what to show.
        fmt: "html" or "png".

    Returns:
        The files written (report.html first).
    """
    folder = Path(folder)
    if fmt == "html":
        files = _write_html(folder, data)
    elif fmt == "png":
        files = _write_png(folder, data)
    else:
        raise ValueError(f"report format must be 'html' or 'png'; got {fmt!r}")
    logger.info("report: %s", ", ".join(f.name for f in files))
    return files
