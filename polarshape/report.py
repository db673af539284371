"""The run report: ``report.html`` with PNG plots in ``report/``, or one ``report.png`` summary.

Contents, top first: the summary line, what actually ran (:func:`model_line`, e.g. "intensity-only
FMBRDF: no polarisation above noise") and the held-out error (:func:`validation_line`); the
self-check warnings in a coloured box (:func:`warning_items`; "no warnings" when there are none);
normal map and albedo (grey scale from the 1–99 % range of the mask, :func:`display_range`); a
shaded preview of the integrated surface beside its depth map (:func:`shaded_surface`); the model
comparison on the held-out lights (table and bars, with the noise floor) and, per held-out light,
photo vs prediction (s0, residual, DoLP); the parameters with their meaning, units and the true
value of a simulated capture (:data:`PARAMETER_MEANINGS`, :func:`material_truth`); DoLP and AoLP
observed vs rendered (the brightest light); fit curves (DoLP against the viewing angle
θ_V = ∠(N, V), intensity / (E · albedo) against the lighting angle θ_L = ∠(N, L), as in figures 4–5
of Ichikawa et al. 2023: binned medians of the observations and of the fitted model, with a sample
of the observations as dots); residual maps (RMS over the lights of the s0 and DoLP residuals); the
loss history and the material's parameters over the fit; metrics, self-check measurements,
timings, skipped steps; the angular-error map and its histogram when the capture has ground-truth
normals. A panel or section without data shows one line saying why, never an empty axis.

The page is written before the run's total time is known: :func:`rewrite_report_page` writes it
again (text only, plots kept) once params.json is final.

Angles shown in degrees (user-facing); AoLP from image x toward image y (down), spec §1.
Plots are drawn with matplotlib's object API (no pyplot, no global backend state) and written
atomically.
"""

from __future__ import annotations

import contextlib
import gc
import html
import json
import logging
import math
import textwrap
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.checks import to_numpy
from polarshape.imaging.pixels import bit_depth_of
from polarshape.imaging.stokes import aolp, dolp
from polarshape.io.atomic import atomic_path, atomic_write_text
from polarshape.io.material import MATERIAL_UNITS, MaterialError, load_material
from polarshape.io.results import MATERIAL_COLOURS
from polarshape.scene.sensor import SensorModel

if TYPE_CHECKING:  # matplotlib (~0.7 s with fontTools) is imported where a figure is drawn
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

logger = logging.getLogger(__name__)

__all__ = [
    "MODEL_NAMES", "PARAMETER_MEANINGS", "ReportData", "display_range", "empty_map_note", "fit_curves",
    "material_truth", "model_line", "rewrite_report_page", "shaded_surface", "surface_points", "validation_line",
    "warning_items", "write_report",
]

_BINS_DEG = np.arange(0.0, 90.0 + 1e-9, 3.0)
_MIN_PER_BIN = 5


@dataclass
class ReportData:
    """Everything the report shows (H × W super-pixels, K lights; numpy arrays).

    Attributes:
        normals: (H, W, 3) camera-frame unit normals, NaN outside the mask.
        albedo: (H, W) albedo map or None.
        albedo_rgb: (H, W, 3) body albedo per colour channel R, G, B (a colour capture) or None; the
            albedo panel shows it in colour.
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
        depth: (H, W) depth of the integrated surface, NaN outside, or None (no depth/mesh preview).
        holdout_lights: indices of the lights held out by the validation, or None.
        holdout_observed: (N, 3, H, W) observed Stokes of the held-out frames, or None.
        holdout_predicted: (N, 3, H, W) the run model's prediction of them from the fit without them, or None.
        truth: the capture's true material parameters (same names as ``params["params"]``), or None.
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
    depth: np.ndarray | None = None
    holdout_lights: list[int] | None = None
    holdout_observed: np.ndarray | None = None
    holdout_predicted: np.ndarray | None = None
    truth: dict[str, float] | None = None
    albedo_rgb: np.ndarray | None = None


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


# --- display ranges, notes ---------------------------------------------------------------------


def display_range(image: np.ndarray, mask: np.ndarray | None = None, *, low: float = 1.0, high: float = 99.0
                  ) -> tuple[float, float] | None:
    """Colour-scale limits of a map: the ``low`` and ``high`` percentiles of its finite values in ``mask``.

    Robust to outliers: a scale set by the maximum lets one hot pixel turn the rest of a map one flat
    colour (the albedo panel of ``make run`` did).

    Args:
        image: (H, W) map (NaN = no value).
        mask: (H, W) bool pixels to use, or None (all).
        low, high: percentiles, in [0, 100].

    Returns:
        (vmin, vmax), equal for a constant map; None when no finite value lies in the mask.

    Example:
        >>> display_range(np.r_[np.linspace(0.4, 0.6, 99), 50.0])  # doctest: +ELLIPSIS
        (0.40..., 0.60...)
    """
    values = image if mask is None else image[mask]
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    lo, hi = np.percentile(values, [low, high])
    return float(lo), float(hi)


def empty_map_note(image: np.ndarray) -> str | None:
    """Why an (H, W) map has nothing to show as an image — "nothing to show: no finite value" or
    "constant: 0.5 everywhere" (drawn as a note instead of a blank axis or a colourbar of one
    value) — or None when it has something to show."""
    finite = image[np.isfinite(image)]
    if finite.size == 0:
        return "nothing to show: no finite value"
    lo, hi = float(finite.min()), float(finite.max())
    return f"constant: {lo:.4g} everywhere" if lo == hi else None


def _note(ax: Axes, title: str, text: str) -> None:
    """An axis with nothing to draw: its title and a one-line reason instead of an empty frame."""
    ax.axis("off")
    ax.set_title(title, fontsize=9)
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=8, wrap=True, transform=ax.transAxes)


def _image(ax: Axes, image: np.ndarray, title: str, *, cmap: str | None = "viridis", vmin: float | None = None,
           vmax: float | None = None, colorbar: bool = True) -> AxesImage | None:
    """``imshow`` with a colourbar; a note instead of a blank axis or a colourbar of a constant
    when an (H, W) map is all NaN or constant (then None), and the data range when the given one is
    degenerate. Returns the image drawn."""
    if image.ndim == 2:
        reason = empty_map_note(image)
        if reason is not None:
            _note(ax, title, reason)
            return None
        if vmin is not None and vmax is not None and not vmax > vmin:
            finite = image[np.isfinite(image)]
            vmin, vmax = float(finite.min()), float(finite.max())
    shown = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if colorbar and image.ndim == 2:
        ax.figure.colorbar(shown, ax=ax, fraction=0.046, pad=0.04)
    return shown


def _upper(image: np.ndarray, mask: np.ndarray, q: float = 99.0, floor: float = 1e-6) -> float:
    """The ``q``-th percentile of ``image`` in ``mask`` (at least ``floor``; 1 when nothing is finite)."""
    rng = display_range(image, mask, low=0.0, high=q)
    return max(rng[1], floor) if rng is not None else 1.0


# --- panels ------------------------------------------------------------------------------------


def _panel_normals(ax: Axes, data: ReportData) -> None:
    finite = np.all(np.isfinite(data.normals), axis=-1)
    if not finite.any():
        _note(ax, "normal map", "nothing to show: no finite normal")
        return
    rgb = np.clip((np.nan_to_num(data.normals) + 1.0) / 2.0, 0.0, 1.0)
    rgb[~finite] = 0.0
    _image(ax, rgb, "normal map (RGB = (n+1)/2, camera frame)", cmap=None, colorbar=False)


def _panel_albedo(ax: Axes, data: ReportData) -> None:
    name = "body albedo k_b" if data.params.get("model") == "fmbrdf" else "albedo ρ"
    if data.albedo_rgb is not None:
        top = _upper(data.albedo_rgb, data.mask)
        rgb = np.clip(np.nan_to_num(data.albedo_rgb) / top, 0.0, 1.0)
        rgb[~data.mask] = 0.0
        _image(ax, rgb, f"{name} R, G, B (one scale: 99 % of the mask → 1)", cmap=None, colorbar=False)
        return
    if data.albedo is None:
        _note(ax, name, "no albedo map")
        return
    shown = _masked(data.albedo, data.mask)
    rng = display_range(shown, data.mask)
    vmin, vmax = rng if rng is not None else (None, None)
    _image(ax, shown, f"{name} (grey scale: 1–99 % of the mask)", cmap="gray", vmin=vmin, vmax=vmax)


def surface_points(depth: np.ndarray, view: np.ndarray, *, projection: str = "orthographic",
                   pixel_size: float = 1.0) -> np.ndarray:
    """(H, W, 3) camera-frame points of a depth map (NaN where the depth is).

    Args:
        depth: (H, W) camera z of the surface, NaN outside.
        view: (H, W, 3) unit directions surface → camera (for a perspective camera the ray of
            each pixel is −view).
        projection: "orthographic" (x = column · pixel_size, y = row · pixel_size) or "perspective"
            (the point on the pixel's ray at that z).
        pixel_size: orthographic size of a super-pixel in the depth's units.
    """
    if projection == "perspective":
        ray = -np.asarray(view, dtype=np.float64)  # (H, W, 3), camera → surface
        with np.errstate(divide="ignore", invalid="ignore"):
            return ray * (depth / ray[..., 2])[..., None]
    rows, cols = np.mgrid[0:depth.shape[0], 0:depth.shape[1]].astype(np.float64)
    return np.stack([cols * pixel_size, rows * pixel_size, depth], axis=-1)


def _derivative(points: np.ndarray, axis: int) -> np.ndarray:
    """(H, W, 3) derivative along image ``axis``: central where both neighbours exist, else one-sided."""
    fwd = np.full_like(points, np.nan)
    bwd = np.full_like(points, np.nan)
    ahead = [slice(None)] * 3
    behind = [slice(None)] * 3
    ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
    step = points[tuple(ahead)] - points[tuple(behind)]
    fwd[tuple(behind)] = step
    bwd[tuple(ahead)] = step
    central = 0.5 * (fwd + bwd)
    return np.where(np.isfinite(central), central, np.where(np.isfinite(fwd), fwd, bwd))


def shaded_surface(depth: np.ndarray, view: np.ndarray, *, projection: str = "orthographic",
                   pixel_size: float = 1.0) -> np.ndarray:
    """A grey shaded render of a depth map: its normals lit by a key light near the camera.

    Normals are the cross product of the surface's image-space derivatives
    (:func:`surface_points`), turned toward the camera; brightness = 0.08 + 0.8 (N·L)₊ +
    0.35 (N·H)₊³⁰ (Lambert + a little Blinn–Phong specular), L the view direction tilted toward
    the upper left, H = (L + V)/‖L + V‖.

    Args:
        depth, view, projection, pixel_size: as :func:`surface_points`.

    Returns:
        (H, W) brightness in [0, 1], NaN where the depth (or every neighbour) is missing.
    """
    points = surface_points(depth, view, projection=projection, pixel_size=pixel_size)  # (H, W, 3)
    view = np.asarray(view, dtype=np.float64)
    normal = np.cross(_derivative(points, 1), _derivative(points, 0))  # (H, W, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        normal *= np.where(np.sum(normal * view, axis=-1, keepdims=True) < 0, -1.0, 1.0)
        light = view + np.array([-0.35, -0.45, 0.0])  # up-left of the camera (y down)
        light /= np.linalg.norm(light, axis=-1, keepdims=True)
        half = light + view
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
    diffuse = np.clip(np.sum(normal * light, axis=-1), 0.0, None)
    specular = np.clip(np.sum(normal * half, axis=-1), 0.0, None) ** 30
    shade = np.clip(0.08 + 0.8 * diffuse + 0.35 * specular, 0.0, 1.0)
    return np.where(np.isfinite(depth) & np.isfinite(shade), shade, np.nan)


def _depth_units(params: dict[str, Any]) -> str:
    return "super-pixels" if (params.get("mesh") or {}).get("units") == "superpixels" else "m"


def _panel_surface(axes: Sequence[Axes], data: ReportData) -> None:
    """Shaded render of the integrated surface (what mesh.ply looks like) beside its depth map."""
    assert data.depth is not None
    projection = str((data.params.get("capture") or {}).get("projection", "orthographic"))
    pixel_size = (data.params.get("integration") or {}).get("pixel_size_m") or 1.0
    shade = shaded_surface(data.depth, data.view, projection=projection, pixel_size=float(pixel_size))
    _image(axes[0], shade, "surface preview (shaded depth / mesh)", cmap="gray", vmin=0.0, vmax=1.0, colorbar=False)
    rng = display_range(data.depth, np.isfinite(data.depth))
    vmin, vmax = rng if rng is not None else (None, None)
    _image(axes[1], data.depth, f"depth (camera z, {_depth_units(data.params)}; 1–99 %)", cmap="viridis_r",
           vmin=vmin, vmax=vmax)


def _panel_polarisation(axes: Sequence[Axes], data: ReportData) -> None:
    """Four panels: DoLP observed, DoLP rendered, AoLP observed, AoLP rendered (reference light)."""
    k = _reference_light(data)
    used = data.mask if data.valid is None else data.mask & data.valid[k]  # dark pixels have meaningless DoLP
    obs_dolp = _masked(_dolp(data.observed[k]), used)
    top = _upper(obs_dolp, used, floor=1e-3)
    _image(axes[0], obs_dolp, f"DoLP observed (light {k})", vmin=0.0, vmax=top)
    _image(axes[2], _masked(_aolp_deg(data.observed[k]), used), "AoLP observed, deg", cmap="twilight",
           vmin=-90.0, vmax=90.0)
    if data.rendered is None:
        for ax, name in ((axes[1], "DoLP rendered"), (axes[3], "AoLP rendered")):
            _note(ax, name, "no rendering (model without one)")
        return
    fit_dolp = _masked(_dolp(data.rendered[k]), used)
    _image(axes[1], fit_dolp, f"DoLP rendered ({data.params.get('model', '')})", vmin=0.0, vmax=top)
    fit_aolp = _masked(_aolp_deg(data.rendered[k]), used & (np.nan_to_num(fit_dolp) > 1e-6))
    _image(axes[3], fit_aolp, "AoLP rendered, deg (where DoLP > 0)", cmap="twilight", vmin=-90.0, vmax=90.0)


def _curve(ax: Axes, x: np.ndarray, y: np.ndarray, bins: np.ndarray, med_obs: np.ndarray, med_fit: np.ndarray | None,
           xlabel: str, ylabel: str, title: str) -> None:
    ax.scatter(x, y, s=1, alpha=0.15, color="0.5", rasterized=True)
    ax.plot([], [], ".", color="0.5", label="observations")  # a legend entry without copying the scatter (slow)
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
        for ax, name in zip(axes, ("DoLP vs viewing angle", "intensity vs lighting angle")):
            _note(ax, name, "no valid observation")
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
        for ax, name in zip(axes, ("RMS s0 residual", "RMS DoLP residual")):
            _note(ax, name, "no rendering: no residuals")
        return
    rel, dolp_rms = maps
    _image(axes[0], rel, "RMS s0 residual / mean s0", cmap="magma", vmin=0.0, vmax=_upper(rel, data.mask))
    _image(axes[1], dolp_rms, "RMS DoLP residual", cmap="magma", vmin=0.0, vmax=_upper(dolp_rms, data.mask))


def _light_errors(params: dict[str, Any], light: int) -> dict[str, Any]:
    """params["validation"]'s per-light record of the run's model for ``light`` ({} when absent)."""
    models = (params.get("validation") or {}).get("models") or {}
    for record in (models.get(params.get("model")) or {}).get("per_light") or []:
        if record.get("light") == light:
            return record
    return {}


def _holdout_shown(data: ReportData) -> list[int]:
    """Rows of the held-out arrays drawn (at most :data:`_MAX_HOLDOUT_SHOWN`)."""
    if data.holdout_observed is None or data.holdout_predicted is None:
        return []
    return list(range(min(len(data.holdout_observed), len(data.holdout_predicted), _MAX_HOLDOUT_SHOWN)))


_MAX_HOLDOUT_SHOWN = 3


def _lattice(present: np.ndarray) -> tuple[slice, slice]:
    """Row and column slices of the regular lattice that holds the ``present`` (H, W) pixels: the
    validation may fit every s-th row and column only (0 between); shown at its own resolution,
    not as a grid of dots. (slice(None), slice(None)) when they are not on a coarser lattice."""
    out = []
    for axis in (1, 0):
        index = np.flatnonzero(present.any(axis=axis))
        step = int(np.gcd.reduce(np.diff(index))) if index.size > 1 else 1
        out.append(slice(int(index[0]), None, step) if step > 1 else slice(None))
    return out[0], out[1]


def _panel_holdout(axes: Sequence[Axes], data: ReportData) -> None:
    """Per held-out light (a row of five): photo s0 | predicted s0 | relative residual | photo DoLP |
    predicted DoLP, the prediction made by the fit without that light; one colour scale per
    quantity for all rows (a colourbar under each: s0, residual, DoLP)."""
    assert data.holdout_observed is not None and data.holdout_predicted is not None
    model = str(data.params.get("model", "model"))
    lights = data.holdout_lights or []
    rows = _holdout_shown(data)
    obs = data.holdout_observed[rows].astype(np.float64)  # (N, 3, H, W)
    pred = data.holdout_predicted[rows].astype(np.float64)
    used = data.mask[None] & (obs[:, 0] > 0)  # (N, H, W)
    if data.valid is not None and all(0 <= lights[r] < len(data.valid) for r in rows if r < len(lights)):
        used &= np.stack([data.valid[lights[r]] if r < len(lights) else data.mask for r in rows])
    lattice = _lattice(used.any(0))
    rows_at, cols_at = lattice
    obs, pred, used = obs[..., rows_at, cols_at], pred[..., rows_at, cols_at], used[..., rows_at, cols_at]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_s0 = np.array([np.mean(o[0][u]) if u.any() else np.nan for o, u in zip(obs, used)])  # (N,)
        rel = np.where(used, (pred[:, 0] - obs[:, 0]) / mean_s0[:, None, None], np.nan)  # (N, H, W)
    obs_dolp, pred_dolp = np.where(used, _dolp(obs), np.nan), np.where(used, _dolp(pred), np.nan)
    s0_top = _upper(np.where(used, obs[:, 0], np.nan), used)
    rel_lim = _upper(np.abs(rel), used)
    dolp_top = min(_upper(obs_dolp, used, floor=1e-3), 1.0)
    grid = np.asarray(axes, dtype=object).reshape(len(rows), 5)
    shown = []
    for row in rows:
        ax = grid[row]
        light = lights[row] if row < len(lights) else row
        record = _light_errors(data.params, light)
        err, dolp_err = _number(record.get("s0_rel_rmse")), _number(record.get("dolp_rmse"))
        columns = (
            (np.where(used[row], obs[row, 0], np.nan), f"light {light}: photo s0", "gray", 0.0, s0_top),
            (np.where(used[row], pred[row, 0], np.nan),
             f"{model} prediction, s0 rel. RMSE {_fmt(err)}", "gray", 0.0, s0_top),
            (rel[row], "(prediction − photo) / mean s0", "RdBu_r", -rel_lim, rel_lim),
            (obs_dolp[row], f"light {light}: photo DoLP", "viridis", 0.0, dolp_top),
            (pred_dolp[row], f"predicted DoLP{'' if dolp_err is None else f', RMSE {dolp_err:.3g}'}", "viridis",
             0.0, dolp_top),
        )
        shown = [_image(a, image, title, cmap=cmap, vmin=lo, vmax=hi, colorbar=False)
                 for a, (image, title, cmap, lo, hi) in zip(ax, columns)]
    figure = grid[0, 0].figure
    for columns, image in (((0, 1), shown[0] or shown[1]), ((2,), shown[2]), ((3, 4), shown[3] or shown[4])):
        if image is not None:
            figure.colorbar(image, ax=list(grid[:, list(columns)].ravel()), location="bottom", fraction=0.04,
                            pad=0.02, aspect=40)


#: Report names of the validation's models (params["validation"]["models"] keys).
MODEL_NAMES: dict[str, str] = {
    "fmbrdf": "FMBRDF", "lambertian": "Lambertian", "l_ts": "Lambertian + Torrance–Sparrow",
    "baek": "Baek et al. 2018 pBRDF", "on_ts": "Oren–Nayar + Torrance–Sparrow", "oren_nayar": "Oren–Nayar",
    "torrance_sparrow": "Torrance–Sparrow",
}


_SHORT_NAMES = {"fmbrdf": "FMBRDF", "lambertian": "Lambertian", "l_ts": "L + TS", "baek": "Baek"}


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _model_order(validation: dict[str, Any]) -> list[str]:
    models = validation.get("models") or {}
    ranked = [m for m in validation.get("ranking") or [] if m in models]
    return ranked + [m for m in models if m not in ranked]


def _panel_models(axes: Sequence[Axes], params: dict[str, Any]) -> None:
    """Bars of each model's held-out s0 relative RMSE (with the noise floor) and DoLP RMSE."""
    validation = params.get("validation") or {}
    models = validation.get("models") or {}
    order = _model_order(validation)
    floor = _number(validation.get("noise_floor_s0_rel"))
    for ax, key, label in ((axes[0], "s0_rel_rmse", "held-out s0 relative RMSE"),
                           (axes[1], "dolp_rmse", "held-out DoLP RMSE")):
        values = [_number(models[m].get(key)) for m in order]
        if all(v is None for v in values):
            _note(ax, label, "not measured for any model")
            continue
        x = np.arange(len(order))
        colours = ["C3" if m == params.get("model") else "0.6" for m in order]
        ax.bar(x, [v or 0.0 for v in values], color=colours)
        for xi, v in zip(x, values):
            ax.text(xi, v or 0.0, "n/a" if v is None else f"{v:.3g}", ha="center", va="bottom", fontsize=7)
        if key == "s0_rel_rmse" and floor is not None:
            ax.axhline(floor, color="k", linestyle="--", label=f"noise floor {floor:.3g}")
            ax.legend(fontsize=7)
        ax.set_xticks(x, [_SHORT_NAMES.get(m, m) for m in order], fontsize=8)
        ax.set_ylabel(label)
        ax.set_title(f"{label} (red: this run's model)", fontsize=9)


_TRACED = ("ior", "alpha", "beta", "r_k")


def _panel_history(axes: Sequence[Axes], params: dict[str, Any]) -> None:
    """Loss against the outer iteration over all levels (log y), and the material's parameters."""
    records = [r for r in (params.get("losses") or {}).get("history") or []
               if isinstance(r, dict) and _number(r.get("loss")) is not None]
    if not records:
        _note(axes[0], "loss history", "no loss recorded")
        _note(axes[1], "parameters", "no loss recorded")
        return
    x = np.arange(len(records))
    loss = np.array([float(r["loss"]) for r in records])
    ax = axes[0]
    ax.plot(x, loss, "o-", ms=3, color="C0")
    if np.all(loss > 0):
        ax.set_yscale("log")
    stages = [str(r.get("stage", "")) for r in records]
    for i in range(1, len(records)):
        if stages[i] != stages[i - 1]:
            ax.axvline(i - 0.5, color="0.7", linestyle=":")
    for i, stage in enumerate(stages):
        if stage and (i == 0 or stage != stages[i - 1]):
            ax.text(i, float(loss.max()), stage, fontsize=7, va="top", color="0.4")
    ax.set_xlabel("outer iteration (all levels)")
    ax.set_ylabel(str(records[-1].get("loss_name", "loss")))
    ax.set_title(f"loss history ({len(records)} records, final {loss[-1]:.4g})", fontsize=9)
    traced = [k for k in _TRACED if all(_number(r.get(k)) is not None for r in records)]
    if len(records) < 2 or not traced:
        _note(axes[1], "parameters", f"no parameter trace ({params.get('model')}: "
              f"{'one record' if len(records) < 2 else 'no material parameters'})")
        return
    ax = axes[1]
    for name in traced:
        label = f"{_SYMBOLS.get(name, name)} → {records[-1][name]:.4g}"
        ax.plot(x, [float(r[name]) for r in records], "-", label=label)
    kappa = [_number(r.get("kappa")) for r in records]
    if all(k is not None for k in kappa) and any(k for k in kappa):
        twin = ax.twinx()
        twin.plot(x, kappa, "k--", label=f"κ → {kappa[-1]:.4g}")
        twin.set_ylabel("κ")
        twin.legend(fontsize=7, loc="lower right")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_xlabel("outer iteration (all levels)")
    ax.set_title("material parameters during the fit", fontsize=9)


def _panel_error(axes: Sequence[Axes], data: ReportData) -> None:
    err = data.error_map
    assert err is not None
    finite = err[np.isfinite(err)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    _image(axes[0], err, "angular error vs ground truth, deg", cmap="inferno", vmin=0.0, vmax=max(top, 1e-3))
    ax = axes[1]
    if not finite.size:
        _note(ax, "error histogram", "no pixel evaluated")
        return
    counts, edges = np.histogram(finite, bins=60, range=(0.0, max(top, 1e-3)))
    ax.stairs(counts, edges, fill=True, color="C1")  # one patch: ax.hist's 60 bars take 0.2 s to draw
    for label, value, style in (("mean", finite.mean(), "-"), ("median", np.median(finite), "--"),
                                ("p90", np.percentile(finite, 90), ":")):
        ax.axvline(value, color="k", linestyle=style, label=f"{label} {value:.2f}°")
    ax.legend(fontsize=7)
    ax.set_xlabel("angular error, deg")
    ax.set_ylabel("pixels")
    ax.set_title("error histogram", fontsize=9)


# --- parameters: meaning, units, truth ---------------------------------------------------------

#: What the albedos (k_s, k_b, a Lambertian ρ) are relative to, beside their units
#: (:data:`polarshape.io.material.MATERIAL_UNITS`).
_ALBEDO_SCALE = ("s0 in fraction of the sensor's full scale per unit relative irradiance E of a light (its "
                 "capture.yaml intensity): absorbs exposure, gain and light power, not an absolute reflectance")

#: name in params.json → (symbol, meaning, units / relative to what).
PARAMETER_MEANINGS: dict[str, tuple[str, str, str]] = {
    "ior": ("μ", "index of refraction of the dielectric (Fresnel reflection and transmission, spec §5)",
            MATERIAL_UNITS["ior"]),
    "alpha": ("α", "roughness: width of the microfacet distribution D(θ) = c·exp(−(θ/α)^β), θ the angle of a "
              "microfacet normal from N (spec §3; not a GGX or Beckmann α)", MATERIAL_UNITS["alpha"]),
    "beta": ("β", "shape of D: 2 ≈ Gaussian, 1 Laplacian-like, < 1 heavy tails", MATERIAL_UNITS["beta"]),
    "kappa": ("κ", "microfacet correlation of the body reflection: concentration of f(n, n_i) ∝ exp(κ n·n_i) "
              "(0 = facets placed at random, spec §7)", MATERIAL_UNITS["kappa"]),
    "k_s": ("k_s", "surface-reflection albedo: s_s = k_s · D · G1(L) G1(V) / (4 N·V) · Fresnel R · E (spec §6)",
            _ALBEDO_SCALE),
    "k_b": ("k_b", "body-reflection albedo, median of the per-pixel map (albedo.npy): s_b = (k_b/π) · G · "
            "∫∫ Fresnel transmission in and out · E (spec §7)", _ALBEDO_SCALE),
    "r_k": ("r_k", "albedo ratio k_b / k_s (the paper's fitted parameter)",
            "1 (exposure and light power cancel)"),
    "albedo_median": ("ρ", "median Lambertian albedo (albedo.npy): s0 = ρ · E · (N·L)₊, ρ = k_d/π",
                      _ALBEDO_SCALE),
    "valid_fraction": ("", "fraction of the mask where photometric stereo found a trustworthy normal",
                       "fraction of mask pixels"),
    "k_d": ("k_d", "diffuse albedo of the baselines (Lambertian, Oren–Nayar body; Baek's transmitted body)",
            _ALBEDO_SCALE),
    "sigma": ("σ", "Oren–Nayar roughness (standard deviation of the facet slope angle)", MATERIAL_UNITS["sigma"]),
    "roughness": ("m", "Torrance–Sparrow Beckmann RMS slope (Baek: GGX α)", MATERIAL_UNITS["roughness"]),
}
_SYMBOLS = {name: symbol or name for name, (symbol, _, _) in PARAMETER_MEANINGS.items()}


def _radiance_to_full_scale(provenance: dict[str, Any], scene: dict[str, Any]) -> float | None:
    """Fraction of full scale of s0 per unit radiance of the simulated camera (None when unknown):
    electrons per radiance × exposure / (electrons per count × (top count − black level))."""
    try:
        fields = {k: v for k, v in (scene.get("sensor") or {}).items() if k in SensorModel.__dataclass_fields__}
        sensor = SensorModel(**fields)
        camera = scene.get("camera") or {}
        bits = bit_depth_of(str(camera.get("pixel_format", "PolarizeMono12")))
        exposure = float(provenance.get("exposure_us", camera.get("exposure_us", sensor.reference_exposure_us)))
        gain = float(provenance.get("gain_db", camera.get("gain_db", 0.0)))
        return sensor.full_scale_per_radiance(exposure, gain, bits)
    except (TypeError, ValueError, KeyError):
        return None


def _scene_material(scene: dict[str, Any]) -> tuple[dict[str, Any], bool] | None:
    """(material parameters with ``model``, textured) of the simulated object(s) in the mask; None
    when they differ between objects or cannot be read."""
    found = []
    for obj in scene.get("objects") or []:
        if not isinstance(obj, dict) or not obj.get("in_mask", True):
            continue
        if obj.get("split") is not None:  # an object of two materials: no one true material
            return None
        material = dict(obj.get("material") or {})
        if "file" in material:
            try:
                record = load_material(material["file"])
            except MaterialError:
                return None
            material = {"model": record.model, **record.parameters}
        found.append((material, obj.get("texture") is not None))
    if not found or any(f != found[0] for f in found[1:]):
        return None
    return found[0]


def material_truth(provenance: dict[str, Any] | None) -> dict[str, float] | None:
    """The true material of a simulated capture, named and scaled as the fitted parameters.

    Args:
        provenance: ``capture.ground_truth["scene"]`` (the simulator's record, scene config under
            ``"scene"``), or None.

    Returns:
        FMBRDF object: ior, alpha, beta, kappa, k_s, k_b, r_k (k_s and k_b times the camera's
        radiance → full-scale factor, so they compare with the fit; k_b and r_k left out for a
        textured object); Lambertian: albedo_median (k_d/π, scaled); Baek: ior. Always with
        ``radiance_to_full_scale`` (that factor) when it is known. None for a capture that is not
        simulated or whose objects in the mask have different materials.
    """
    scene = provenance.get("scene") if isinstance(provenance, dict) else None
    if not isinstance(scene, dict):
        return None
    found = _scene_material(scene)
    if found is None:
        return None
    material, textured = found
    scale = _radiance_to_full_scale(provenance, scene)
    truth: dict[str, float] = {}
    model = material.get("model")
    if model == "fmbrdf":
        p = FMBRDFParams(**{k: float(v) for k, v in material.items() if k in FMBRDF_PARAM_NAMES})
        truth.update(ior=p.ior, alpha=p.alpha, beta=p.beta, kappa=p.kappa)
        if scale is not None:
            truth["k_s"] = p.k_s * scale
            if not textured:
                truth["k_b"] = p.k_b * scale
        if not textured:
            truth["r_k"] = p.as_dict()["r_k"]
    elif model == "lambertian" and scale is not None and not textured:
        truth["albedo_median"] = float(material.get("k_d", 0.5)) / math.pi * scale
    elif model == "baek" and "ior" in material:
        truth["ior"] = float(material["ior"])
    if scale is not None:
        truth["radiance_to_full_scale"] = scale
    return truth or None


def _parameter_rows(params: dict[str, Any], truth: dict[str, float] | None) -> list[tuple[str, ...]]:
    """(name, symbol, value, [true,] meaning, units) per fitted parameter."""
    rows = []
    for name, value in (params.get("params") or {}).items():
        symbol, meaning, units = PARAMETER_MEANINGS.get(name, ("", "", ""))
        row = [name, symbol, _fmt(value)]
        if truth is not None:
            row.append(_fmt(float(truth[name])) if name in truth else "—")
        rows.append(tuple(row + [meaning, units]))
    return rows


# --- text --------------------------------------------------------------------------------------


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if not math.isfinite(value) else f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items())
    if value is None:
        return "n/a"
    return str(value)


def _flat_metrics(metrics: dict[str, Any]) -> list[tuple[str, str]]:
    rows = []
    for group, values in metrics.items():
        if isinstance(values, dict):
            rows += [(f"{group}.{k}", _fmt(v)) for k, v in values.items()]
        else:
            rows.append((group, _fmt(values)))
    return rows


def warning_items(params: dict[str, Any]) -> list[tuple[str, str]]:
    """(name, message) of the self-check warnings (``params["checks"]["warnings"]``) and of every
    other recorded warning (``params["warnings"]``, "Name: message"), each once."""
    items: list[tuple[str, str]] = []
    for record in (params.get("checks") or {}).get("warnings") or []:
        if isinstance(record, dict):
            item = (str(record.get("name", "warning")), str(record.get("message", "")))
            if item not in items:
                items.append(item)
    for text in params.get("warnings") or []:
        name, sep, message = str(text).partition(": ")
        item = (name, message) if sep else ("warning", name)
        if item not in items:
            items.append(item)
    return items


def model_line(params: dict[str, Any]) -> str:
    """What actually ran, in words (e.g. "intensity-only FMBRDF: no polarisation above noise")."""
    model = params.get("model")
    capture = params.get("capture") or {}
    if model == "fmbrdf":
        if capture.get("has_polarisation") is False:
            text = "intensity-only FMBRDF: no polarisation above noise (DoLP and AoLP not fitted)"
        else:
            text = "FMBRDF: normals and material fitted to intensity and polarisation (s0, s1, s2)"
        material = params.get("material") or {}
        if material.get("applied"):
            text += f"; known material {material.get('file')} ({material.get('use')})"
    elif model == "lambertian":
        text = "Lambertian photometric stereo (intensity only, no polarisation model)"
    else:
        text = f"model {model}"
    chosen = [s for s in params.get("skipped") or [] if "model choice" in s or "chosen" in s]
    choice = ((params.get("validation") or {}).get("model_choice") or {})
    if choice.get("verdict"):
        chosen.append(f"held-out evidence: {choice['verdict']}")
    return text + "".join(f"; {c}" for c in chosen)


def validation_line(params: dict[str, Any]) -> str:
    """The held-out validation in one line (or why it is not there)."""
    v = params.get("validation")
    if not isinstance(v, dict):
        return "held-out validation: no params['validation'] (not run)"
    if not v.get("holdout") or not v.get("models"):
        return f"held-out validation did not run: {v.get('reason') or 'no light held out'}"
    model = params.get("model")
    err = _number(((v.get("models") or {}).get(model) or {}).get("s0_rel_rmse"))
    floor = _number(v.get("noise_floor_s0_rel"))
    text = f"held-out validation on lights {v['holdout']}: {model} s0 rel. RMSE {_fmt(err)}"
    if floor is not None:
        text += f" (noise floor {floor:.3g}" + (f", {err / floor:.2f}×)" if err is not None and floor > 0 else ")")
    ranking = v.get("ranking") or []
    if ranking:
        text += f"; best model on the held-out lights: {MODEL_NAMES.get(ranking[0], ranking[0])}"
    return text + (f"; {v['reason']}" if v.get("reason") else "")


def _text_lines(params: dict[str, Any]) -> list[str]:
    warned = warning_items(params)
    lines = [f"ran: {model_line(params)}", validation_line(params)]
    lines += [f"WARNING {name}: {message}" for name, message in warned] or ["no warnings"]
    lines += [f"model: {params.get('model')}"]
    lines += [f"  {k} = {_fmt(v)}" for k, v in (params.get("params") or {}).items()]
    if len(params.get("materials") or []) > 1:
        lines += [f"material {i}: " + ", ".join(f"{k} = {_fmt(v)}" for k, v in m.items())
                  for i, m in enumerate(params["materials"])]
    lines += ["metrics:"] + [f"  {k} = {v}" for k, v in _flat_metrics(params.get("metrics") or {})]
    lines += ["timings (s):"] + [f"  {k}: {v:.2f}" for k, v in (params.get("timings_s") or {}).items()]
    lines += ["skipped:"] + [f"  {s}" for s in params.get("skipped") or []]
    return lines


# --- output ------------------------------------------------------------------------------------


def _save(fig: Figure, path: Path, *, tight: bool = False) -> Path:
    """Write ``fig`` as a PNG atomically; ``tight`` crops to what is drawn (one more draw pass)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight" if tight else None)
    return path


def _figure(ncols: int, nrows: int = 1, size: float = 3.6, margins: dict[str, float] | None = None
            ) -> tuple[Figure, list[Axes]]:
    """A figure of ``nrows`` × ``ncols`` axes: constrained layout, or fixed ``margins``
    (``subplots_adjust``'s arguments: several times faster to save, for figures whose labels are known)."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(size * ncols, size * nrows * 0.9), layout=None if margins else "constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel().tolist()
    if margins:
        fig.subplots_adjust(**margins)
    return fig, axes


#: Fixed margins of the figures drawn without constrained layout (by file stem).
_MARGINS: dict[str, dict[str, float]] = {
    "maps": {"left": 0.01, "right": 0.92, "bottom": 0.03, "top": 0.9, "wspace": 0.1},
    "surface": {"left": 0.01, "right": 0.88, "bottom": 0.03, "top": 0.9, "wspace": 0.1},
    "polarisation": {"left": 0.01, "right": 0.92, "bottom": 0.02, "top": 0.94, "wspace": 0.12, "hspace": 0.12},
    "fit_curves": {"left": 0.1, "right": 0.98, "bottom": 0.14, "top": 0.92, "wspace": 0.25},
    "residuals": {"left": 0.01, "right": 0.9, "bottom": 0.03, "top": 0.9, "wspace": 0.3},
    "error_map": {"left": 0.01, "right": 0.98, "bottom": 0.14, "top": 0.9, "wspace": 0.4},
    "holdout": {"left": 0.01, "right": 0.99, "bottom": 0.02, "top": 0.95, "wspace": 0.05, "hspace": 0.15},
    "models": {"left": 0.09, "right": 0.98, "bottom": 0.1, "top": 0.9, "wspace": 0.3},
    "loss_history": {"left": 0.1, "right": 0.92, "bottom": 0.15, "top": 0.9, "wspace": 0.25},
}


def _esc(value: Any) -> str:
    return html.escape(str(value))


def _table(title: str, rows: Sequence[Sequence[str]], header: Sequence[str] | None = None, note: str = "") -> str:
    head = "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>" if header else ""
    body = "".join("<tr>" + "".join(f"<td>{_esc(c)}</td>" for c in row) + "</tr>" for row in rows)
    caption = f"<p class='note'>{_esc(note)}</p>" if note else ""
    return f"<h2>{_esc(title)}</h2>{caption}<table>{head}{body}</table>"


def _missing(title: str, why: str) -> str:
    """A section whose data is absent: its heading and one line saying why."""
    return f"<h2>{_esc(title)}</h2><p class='note'>{_esc(why)}</p>"


#: A figure of the HTML report: (file stem, title, columns, rows, draw).
_Spec = tuple[str, str, int, int, Callable[[list["Axes"]], None]]


def _figure_specs(data: ReportData) -> dict[str, _Spec | str]:
    """Every figure of the HTML report by key: its spec, or the one line saying why it is not there."""
    p = data.params
    specs: dict[str, _Spec | str] = {
        "maps": ("maps", "Normal map and albedo", 2, 1,
                 lambda ax: (_panel_normals(ax[0], data), _panel_albedo(ax[1], data))),
    }
    specs["surface"] = (("surface", "Surface: shaded preview and depth", 2, 1, lambda ax: _panel_surface(ax, data))
                        if data.depth is not None and np.isfinite(data.depth).any()
                        else "no depth map (integration did not run or gave no finite depth)")
    rows = _holdout_shown(data)
    specs["holdout"] = (("holdout", "Held-out lights: prediction vs photo", 5, len(rows),
                         lambda ax: _panel_holdout(ax, data)) if rows
                        else "no held-out prediction (" + validation_line(p) + ")")
    validation = p.get("validation") or {}
    specs["models"] = (("models", "Model comparison on the held-out lights", 2, 1, lambda ax: _panel_models(ax, p))
                       if validation.get("models") else validation_line(p))
    specs["polarisation"] = ("polarisation", "DoLP and AoLP, observed vs rendered", 2, 2,
                             lambda ax: _panel_polarisation(ax, data))
    specs["fit_curves"] = ("fit_curves", "Fit curves", 2, 1, lambda ax: _panel_curves(ax, data))
    specs["residuals"] = ("residuals", "Residual maps (fitted lights)", 2, 1, lambda ax: _panel_residuals(ax, data))
    specs["loss_history"] = (("loss_history", "Loss history", 2, 1, lambda ax: _panel_history(ax, p))
                             if (p.get("losses") or {}).get("history") else "no loss history in params['losses']")
    if data.error_map is not None:
        specs["error_map"] = ("error_map", "Angular error against ground truth", 2, 1,
                              lambda ax: _panel_error(ax, data))
    return specs


def _img(spec: _Spec | str, title: str) -> str:
    if isinstance(spec, str):
        return _missing(title, spec)
    name, title = spec[0], spec[1]
    return f'<h2>{_esc(title)}</h2><img src="report/{_esc(name)}.png" alt="{_esc(title)}">'


def _warnings_box(params: dict[str, Any]) -> str:
    items = warning_items(params)
    if not items:
        checked = "self-checks ran" if "checks" in params else "no self-check section in params.json"
        return f"<div class='ok'><b>no warnings</b> ({_esc(checked)})</div>"
    rows = "".join(f"<li><b>{_esc(name)}</b>: {_esc(message)}</li>" for name, message in items)
    return f"<div class='warn'><b>{len(items)} warning(s)</b><ul>{rows}</ul></div>"


def _model_table(params: dict[str, Any]) -> str:
    validation = params.get("validation") or {}
    models = validation.get("models") or {}
    if not models:
        return _missing("Model comparison (held-out lights)", validation_line(params))
    floor = _number(validation.get("noise_floor_s0_rel"))
    rows = []
    for rank, name in enumerate(_model_order(validation), start=1):
        m = models[name]
        label = MODEL_NAMES.get(name, name) + (" ★ this run" if name == params.get("model") else "")
        rows.append((str(rank), label, _fmt(_number(m.get("s0_rel_rmse"))), _fmt(_number(m.get("dolp_rmse"))),
                     _fmt(_number(m.get("aolp_mae_deg"))), _fmt(_number(m.get("seconds")))))
    note = (f"lights held out: {validation.get('holdout')}; noise floor of the s0 relative RMSE (noise alone): "
            f"{_fmt(floor)}; normals re-fitted for each model; warm start: {validation.get('warm_start') or 'n/a'}")
    return _table("Model comparison (held-out lights)", rows,
                  ["rank", "model", "s0 rel. RMSE", "DoLP RMSE", "AoLP MAE, deg", "fit time, s"], note)


def _parameter_table(data: ReportData) -> str:
    p = data.params
    truth = ["true"] if data.truth is not None else []
    header = ["name", "symbol", "value", *truth, "meaning", "units / relative to"]
    note = f"model {p.get('model')}"
    if data.truth is not None:
        scale = data.truth.get("radiance_to_full_scale")
        note += ("; true: the simulated scene's material" + (f", k_s and k_b × {scale:.4g} (the simulated camera's "
                 "full scale per unit radiance) to compare with the fit" if scale else ""))
    return _table("Parameters", _parameter_rows(p, data.truth), header, note)


def _colour_table(params: dict[str, Any]) -> str:
    """A colour capture's body albedo per channel (params.json ``colour``); nothing for mono."""
    colour = params.get("colour")
    if not colour:
        return ""
    keys = ("median", "mean", "p05", "p95", "chromaticity")
    rows = [(name, *(_fmt(colour[k][c]) for k in keys)) for c, name in enumerate(colour["channels"])]
    return _table("Body albedo per colour channel", rows, ["channel", *keys],
                  f"camera.mosaic.bayer {params.get('capture', {}).get('bayer')}; chromaticity: the channel's median "
                  "over the mean of the three medians (the albedo's scale follows the irradiance units)")


def _materials_table(params: dict[str, Any]) -> str:
    """Every material of a run (``params["materials"]``, :mod:`polarshape.recover.materials`): its
    colour in materials.png, pixels and parameters; the splits the model choice tried."""
    materials = params.get("materials")
    if not isinstance(materials, list) or not materials:
        return ""
    names = [n for n in ("ior", "alpha", "beta", "kappa", "k_s", "k_b") if any(n in m for m in materials)]
    rows = [(str(i), "rgb({}, {}, {})".format(*MATERIAL_COLOURS[i % len(MATERIAL_COLOURS)]),
             _fmt(m.get("pixels")), *(_fmt(m.get(n)) for n in names)) for i, m in enumerate(materials)]
    tried = "; ".join(f"{r.get('materials')} materials: gain {_fmt(r.get('gain_nll'))} vs penalty "
                      f"{_fmt(r.get('penalty'))} ({'kept' if r.get('kept') else 'not kept'})"
                      for r in params.get("material_selection") or [])
    note = (f"{len(materials)} material(s) (materials.png / materials.npy; 'params' is the one with the most "
            f"pixels); {_fmt(params.get('mixed_pixels'))} pixels on material or albedo edges (mixed.png), left out of the "
            f"material fits" + (f"; splits tried: {tried}" if tried else ""))
    return _table("Materials", rows, ["material", "colour in materials.png", "pixels",
                                      *(_SYMBOLS.get(n, n) for n in names)], note)


def _timing_table(params: dict[str, Any]) -> str:
    rows = [(k, f"{v:.3f}") for k, v in (params.get("timings_s") or {}).items() if _number(v) is not None]
    timings = params.get("timings_s") or {}
    if "total" not in timings:
        rows.append(("report, total", "not known yet when this page was written: see params.json timings_s"))
    rows += [(f"recovery.{k}", f"{v:.3f}") for k, v in (params.get("recovery_timings_s") or {}).items()
             if _number(v) is not None]
    validation = (params.get("validation") or {}).get("timings_s") or {}
    rows += [(f"validation.{k}", f"{v:.3f}") for k, v in validation.items() if _number(v) is not None]
    return _table("Timings (s)", rows)


#: The near-field rounds' columns (params.json ``nearfield.iterations`` keys: header), in order; keys a round has
#: beyond these follow under their own names.
_NEARFIELD_COLUMNS: tuple[tuple[str, str], ...] = (
    ("iteration", "round"), ("normals", "normals"), ("median_depth_m", "median depth, m"), ("placement", "placement"),
    ("normal_change_deg", "normal change, deg"), ("depth_change", "depth change"), ("residual", "residual"),
    ("relaxation", "relaxation (share of the searched move taken)"), ("seconds", "seconds"),
)


def _nearfield_table(params: dict[str, Any]) -> str:
    """The near-field rounds (params.json ``nearfield``): depth placement and changes per round."""
    record = params.get("nearfield") or {}
    if not record.get("enabled"):
        return ""
    rounds = [it for it in record.get("iterations") or [] if isinstance(it, dict)]
    known = dict(_NEARFIELD_COLUMNS)
    extra = list(dict.fromkeys(k for it in rounds for k in it if k not in known))
    keys = [k for k, _ in _NEARFIELD_COLUMNS] + extra
    header = [known.get(k, k) for k in keys]
    rows = [tuple(_fmt(it.get(k)) for k in keys) for it in rounds]
    how = "estimated from the shading" if record.get("depth_estimated") else "integration.reference_depth_m"
    note = (f"object at {_fmt(record.get('median_depth_m'))} m ({how}; first guess {_fmt(record.get('reference_depth_m'))} "
            f"m); placement: {(record.get('placement') or {}).get('kind')}; converged: {record.get('converged')}; "
            "relaxation: n/a outside the model rounds")
    return _table("Near-field lights: normals, depth and per-pixel lights", rows, header, note)


def _checks_table(params: dict[str, Any]) -> str:
    checks = params.get("checks")
    if not isinstance(checks, dict):
        return _missing("Self-checks", "no params['checks'] (the self-checks did not run)")
    rows = [(k, _fmt(v)) for k, v in checks.items() if k != "warnings"]
    return _table("Self-checks", rows, note="what each check measured (1 = residual at the noise floor)")


_STYLE = ("body{font-family:sans-serif;margin:2em;max-width:1100px}table{border-collapse:collapse}"
          "td,th{border:1px solid #ccc;padding:2px 8px;font-size:90%;vertical-align:top}th{background:#f4f4f4}"
          "img{max-width:100%}.note{color:#555;font-size:90%}"
          ".warn{background:#fdecea;border:2px solid #d93025;padding:0.5em 1em;margin:1em 0}"
          ".ok{background:#e6f4ea;border:2px solid #1e8e3e;padding:0.5em 1em;margin:1em 0}")


def _page(data: ReportData) -> str:
    """The HTML text of the report (figures by file name: they are written separately)."""
    p = data.params
    specs = _figure_specs(data)
    metrics = (_table("Metrics against ground truth", _flat_metrics(p["metrics"])) if p.get("metrics")
               else _missing("Metrics against ground truth", "the capture has no ground truth"))
    sections = [
        "<h1>polarshape run report</h1>",
        f"<p><b>{_esc(p.get('summary', ''))}</b></p>",
        f"<p>ran: {_esc(model_line(p))}<br>{_esc(validation_line(p))}</p>",
        _warnings_box(p),
        _img(specs["maps"], "Normal map and albedo"),
        _img(specs["surface"], "Surface: shaded preview and depth"),
        _model_table(p),
        _img(specs["models"], "Model comparison on the held-out lights"),
        _img(specs["holdout"], "Held-out lights: prediction vs photo"),
        _parameter_table(data),
        _colour_table(p),
        _materials_table(p),
        _img(specs["polarisation"], "DoLP and AoLP"),
        _img(specs["fit_curves"], "Fit curves"),
        _img(specs["residuals"], "Residual maps"),
        _img(specs["loss_history"], "Loss history"),
    ]
    if "error_map" in specs:
        sections.append(_img(specs["error_map"], "Angular error against ground truth"))
    sections += [
        metrics, _nearfield_table(p), _checks_table(p), _timing_table(p),
        _table("Skipped", [(s.split(":", 1)[0], s.split(":", 1)[-1].strip()) for s in p.get("skipped") or []]),
        _table("Capture", [(k, _fmt(v)) for k, v in (p.get("capture") or {}).items()]),
        f"<h2>params.json (at report time)</h2><pre>{_esc(json.dumps(p, indent=1, default=str)[:20000])}</pre>",
    ]
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>polarshape report</title><style>{_STYLE}"
            f"</style></head><body>{''.join(sections)}</body></html>")


def _write_html(folder: Path, data: ReportData) -> list[Path]:
    plots = []
    for spec in _figure_specs(data).values():
        if isinstance(spec, str):
            continue
        name, _, ncols, nrows, draw = spec
        fig, axes = _figure(ncols, nrows, size=3.0 if ncols > 2 else 3.6, margins=_MARGINS.get(name))
        draw(axes)
        plots.append(_save(fig, folder / "report" / f"{name}.png"))
    report = atomic_write_text(folder / "report.html", _page(data))
    return [report] + plots


def rewrite_report_page(folder: str | Path, data: ReportData) -> Path:
    """Write ``folder/report.html`` again from ``data.params`` as it is now (the final timings,
    warnings and summary), over the one :func:`write_report` wrote; the plots are not redrawn.

    Returns:
        The page's path.
    """
    return atomic_write_text(Path(folder) / "report.html", _page(data), overwrite=True)


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
    lines = [part for line in _text_lines(data.params)
             for part in textwrap.wrap(line, 46, subsequent_indent="    ") or [""]]
    per = math.ceil(len(lines) / len(text_axes))
    for i, ax in enumerate(text_axes):
        ax.axis("off")
        ax.text(0.0, 1.0, "\n".join(lines[i * per:(i + 1) * per]), va="top", ha="left", family="monospace", fontsize=7,
                in_layout=False)  # long text must not squeeze the panels (constrained layout)
    return [_save(fig, folder / "report.png", tight=True)]


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Pause Python's cyclic garbage collector inside (restored after, as it was): matplotlib makes
    many small objects, and the collections they trigger scan the run's whole heap (a quarter of
    the report's time in a pipeline process). The figures' cycles are collected afterwards."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


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
    if fmt not in ("html", "png"):
        raise ValueError(f"report format must be 'html' or 'png'; got {fmt!r}")
    with _collector_paused():
        files = _write_html(folder, data) if fmt == "html" else _write_png(folder, data)
    logger.info("report: %s", ", ".join(f.name for f in files))
    return files
