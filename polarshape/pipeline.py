"""``polarshape run``: capture → normals, reflectance, depth, mesh, report, in one result folder.

Stages (each logs its time and what it skipped; params.json records both):

1. ``input`` — load a capture folder, or record one first (simulated camera or a capture session);
2. ``preprocess`` — super-pixel Stokes images, observation validity, object mask, lights
   (:func:`polarshape.recover.preprocess.preprocess_capture`);
3. ``initial_normals`` — robust Lambertian photometric stereo on s0;
4. ``recovery`` — reflectometry and joint refinement of normals and FMBRDF parameters
   (:func:`polarshape.recover.joint.recover_capture`); with ``recovery.model: lambertian`` the
   initial normals and albedo are the result (intensity-only mode);
5. ``integration`` — depth from the normals (:func:`polarshape.surface.integrate.integrate_normals`);
6. ``mesh`` — grid mesh of the depth map (and screened Poisson if asked);
7. ``export`` — result files (below);
8. ``evaluation`` — errors against the capture's ground truth, when it has some;
9. ``report`` — report.html with PNG plots (or report.png).

Result folder (spec capture-format.md), built under a temporary name and renamed into place only
when complete, so an interrupted run leaves nothing half-written, never over the input, and over an
existing result only with ``overwrite``:

- ``normals.npy`` (H, W, 3) float32 camera-frame unit normals (x right, y down, z forward), NaN
  outside the mask; ``normal_map.png`` (16-bit RGB, (n + 1)/2, convention in params.json and the
  README); ``normals.exr`` (float32 R, G, B = n_x, n_y, n_z);
- ``albedo.npy`` / ``albedo.png`` (per-pixel body albedo or Lambertian albedo, when estimated);
- ``depth.npy`` (H, W) float32 camera-frame z, NaN outside the mask; ``mesh.ply`` / ``mesh.obj``
  (vertex normals, vertex colours from the albedo); ``mesh_poisson.ply`` (optional);
- ``mask.png``; ``filled.png`` (FMBRDF recovery: mask pixels with fewer than 3 usable
  observations, whose normal was filled in from their neighbours); ``params.json`` (model,
  parameters, losses, timings per stage, skipped steps, metrics); ``config.yaml`` (the validated configuration); ``error_map.npy`` (degrees, with ground
  truth); the report; ``capture/`` (a simulated or session capture, when kept).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm import tqdm

from polarshape.config import ConfigError, RunConfig, resolve_device
from polarshape.export import write_exr, write_normal_map_png, write_npy, write_scalar_map_png
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.pixels import counts_to_float
from polarshape.io.atomic import atomic_directory, atomic_write_text
from polarshape.io.capture import Capture, load_capture, write_capture
from polarshape.io.images import write_image
from polarshape.recover.photometric import RobustPSResult, robust_lambertian_ps
from polarshape.recover.preprocess import RecoveryInputs, preprocess_capture
from polarshape.report import ReportData, write_report
from polarshape.surface.integrate import IntegrationReport, integrate_normals
from polarshape.surface.mesh import depth_to_mesh, depth_to_points, poisson_mesh, write_mesh

logger = logging.getLogger(__name__)

__all__ = [
    "RESULT_FORMAT",
    "STAGES",
    "PipelineError",
    "PipelineResult",
    "RecoveryOutcome",
    "angular_error_deg",
    "angular_error_stats",
    "depth_rmse_aligned",
    "lambertian_recovery",
    "run_pipeline",
]

RESULT_FORMAT = "polarshape-result/1"
STAGES: tuple[str, ...] = (
    "input", "preprocess", "initial_normals", "recovery", "integration", "mesh", "export", "evaluation", "report",
)
_PERCENTILES = (25, 75, 90, 95)


class PipelineError(RuntimeError):
    """A stage cannot run with this capture and configuration; the message names the key to change."""


@dataclass
class RecoveryOutcome:
    """What the recovery stage hands on, as numpy arrays (H, W super-pixels, K lights).

    Attributes:
        normals: (H, W, 3) float32 camera-frame unit normals, NaN outside ``mask``.
        albedo: (H, W) float32 albedo map (NaN outside the mask) or None.
        params: estimated material parameters by name.
        model: "fmbrdf" or "lambertian".
        mask: (H, W) bool pixels with a normal.
        rendered: (K, 3, H, W) float32 Stokes the fitted model predicts, or None.
        observed: (K, 3, H, W) float32 observed Stokes (fraction of full scale, pixel frames).
        history: per-iteration records (losses).
        timings: seconds per recovery sub-step.
        skipped: what the recovery left out, with the reason.
        filled: (H, W) bool mask pixels whose normal came from their neighbours (fewer than 3 usable
            observations), or None (the ``lambertian`` model leaves such pixels invalid instead).
    """

    normals: np.ndarray
    albedo: np.ndarray | None
    params: dict[str, float]
    model: str
    mask: np.ndarray
    rendered: np.ndarray | None
    observed: np.ndarray
    history: list[dict[str, Any]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    filled: np.ndarray | None = None


@dataclass(frozen=True)
class PipelineResult:
    """What :func:`run_pipeline` returns.

    Attributes:
        out_dir: the result folder.
        summary: one line: where, model, error against ground truth (if any), time.
        params: the content of params.json.
    """

    out_dir: Path
    summary: str
    params: dict[str, Any]


def _numpy(x: Any) -> np.ndarray | None:
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu").numpy()
    return np.asarray(x)


class _StageLog:
    """Times the stages, records what they skipped, and drives the stage progress bar."""

    def __init__(self, progress: bool) -> None:
        self.timings: dict[str, float] = {}
        self.skipped: list[str] = []
        self._bar = tqdm(total=len(STAGES), desc="polarshape run", unit="stage", disable=not progress, leave=False)

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._bar.set_postfix_str(name)
        logger.info("stage %s: start", name)
        before = len(self.skipped)
        t0 = time.perf_counter()
        yield
        seconds = time.perf_counter() - t0
        self.timings[name] = seconds
        skipped = self.skipped[before:]
        logger.info("stage %s: %.2f s%s", name, seconds, f"; skipped: {'; '.join(skipped)}" if skipped else "")
        self._bar.update(1)

    def skip(self, stage: str, reason: str) -> None:
        self.skipped.append(f"{stage}: {reason}")

    def close(self) -> None:
        self._bar.close()


# --- input -------------------------------------------------------------------------------------


def _acquire(config: RunConfig, work: Path, device: str) -> Capture:
    """The capture of the run: loaded, simulated, or recorded by a session (into ``work/capture``)."""
    source = config.input
    if source.type == "capture":
        assert source.path is not None
        return load_capture(source.path)
    target = work / "capture"
    if source.type == "simulated":
        from polarshape.acquisition.simulated import SimulatedCamera

        assert source.scene is not None
        with SimulatedCamera(source.scene, device=device, seed=source.seed) as camera:
            capture = camera.render_capture(progress=config.progress)
        if source.save_capture:
            write_capture(target, capture)
            capture = dataclasses.replace(capture, root=target)
        return capture
    from polarshape.acquisition.session import capture_session

    assert source.session is not None
    capture_session(source.session, target)
    capture = load_capture(target)
    if not source.save_capture:
        shutil.rmtree(target)
        capture = dataclasses.replace(capture, root=None)
    return capture


# --- preprocess --------------------------------------------------------------------------------


def _threshold_mask(capture: Capture, threshold: float) -> np.ndarray:
    """(H, W) bool: super-pixels whose brightest s0 over the lights exceeds ``threshold`` of full scale."""
    mosaic = counts_to_float(capture.frames, capture.bit_depth, capture.spec.camera.black_level)  # (K, 2H, 2W)
    s0 = stokes_from_mosaic(mosaic, capture.layout, "superpixel")[:, 0]  # (K, H, W)
    return (s0.amax(0) > threshold).numpy()


def _clean_mask(mask: np.ndarray, erode_px: int, min_component_px: int) -> np.ndarray:
    import scipy.ndimage

    out = mask.copy()
    if erode_px:
        out = scipy.ndimage.binary_erosion(out, iterations=erode_px)
    labels, n = scipy.ndimage.label(out)
    if n:
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        out &= sizes[labels] >= min_component_px
    return out


def _object_mask(capture: Capture, config: RunConfig, log: _StageLog) -> np.ndarray:
    mode = config.preprocess.mask
    if mode == "capture" and capture.mask is None:
        raise PipelineError(
            "preprocess.mask is 'capture' but the capture has no mask.png; add one or set preprocess.mask: auto"
        )
    if capture.mask is not None and mode != "threshold":
        mask = np.asarray(capture.mask, dtype=bool)
    else:
        mask = _threshold_mask(capture, config.preprocess.mask_threshold)
        log.skip("preprocess", "capture mask not used (threshold mask)" if capture.mask is not None else
                 "capture has no mask.png: threshold mask on the brightest s0")
    mask = _clean_mask(mask, config.preprocess.erode_px, config.preprocess.min_component_px)
    if not mask.any():
        raise PipelineError(
            "the object mask is empty: lower preprocess.mask_threshold, preprocess.erode_px or "
            "preprocess.min_component_px, or check the exposure"
        )
    return mask


def _orthographic_pixel_size(capture: Capture, config: RunConfig, log: _StageLog) -> float:
    """Metres per super-pixel: the config's, else the simulated scene's, else 1 (super-pixel units)."""
    if config.integration.pixel_size_m is not None:
        return float(config.integration.pixel_size_m)
    scene = capture.ground_truth.get("scene")
    raw = None
    if isinstance(scene, dict):
        raw = (scene.get("scene") or {}).get("camera", {}).get("pixel_size_m")
    if isinstance(raw, (int, float)) and raw > 0:
        return 2.0 * float(raw)  # a super-pixel spans two raw pixels
    log.skip("integration", "metric scale: no integration.pixel_size_m, depth in super-pixel units")
    return 1.0


def _superpixel_intrinsics(capture: Capture) -> np.ndarray:
    """(3, 3) K at super-pixel resolution: super-pixel x covers raw columns 2x, 2x+1 (centre 2x + 0.5)."""
    k = capture.spec.camera.intrinsics
    assert k is not None  # validated by the capture format for perspective cameras
    return np.array([[k.fx / 2, 0.0, (k.cx - 0.5) / 2], [0.0, k.fy / 2, (k.cy - 0.5) / 2], [0.0, 0.0, 1.0]])


def _reference_points(capture: Capture, config: RunConfig, shape: tuple[int, int], pixel_size: float) -> np.ndarray:
    """(H, W, 3) points on the plane z = reference depth (locates point lights before any depth exists)."""
    depth = np.full(shape, config.integration.reference_depth_m)
    if capture.spec.camera.projection == "perspective":
        return depth_to_points(depth, projection="perspective", K=_superpixel_intrinsics(capture))
    return depth_to_points(depth, projection="orthographic", pixel_size=pixel_size)


# --- recovery ----------------------------------------------------------------------------------


def _render_lambertian(normals: torch.Tensor, albedo: torch.Tensor, inputs: RecoveryInputs) -> torch.Tensor:
    """(K, 3, H, W) Stokes of the Lambertian model: s0 = albedo · E · max(0, N·L), unpolarised."""
    k = inputs.num_lights
    lights = inputs.lights if inputs.lights.ndim == 4 else inputs.lights[:, None, None, :]  # (K, H|1, W|1, 3)
    irr = inputs.irradiance if inputs.irradiance.ndim == 3 else inputs.irradiance[:, None, None]  # (K, H|1, W|1)
    shading = (lights * normals.unsqueeze(0)).sum(-1).clamp_min(0.0)  # (K, H, W)
    s0 = albedo.unsqueeze(0) * irr * shading  # (K, H, W)
    zeros = torch.zeros_like(s0)
    return torch.stack([s0, zeros, zeros], dim=1).reshape(k, 3, *s0.shape[-2:])


def lambertian_recovery(inputs: RecoveryInputs, ps: RobustPSResult) -> RecoveryOutcome:
    """The intensity-only result: robust Lambertian PS normals and albedo, with the rendered s0.

    Args:
        inputs: preprocessed capture (K lights, H × W super-pixels).
        ps: :func:`robust_lambertian_ps` on ``inputs.stokes[:, 0]``.

    Returns:
        :class:`RecoveryOutcome` with model "lambertian", params ``albedo_median`` and
        ``valid_fraction`` (PS-valid share of the mask), and the s0 RMS residual as the loss.
    """
    mask = inputs.mask
    normals = torch.where(mask[..., None], ps.normals, torch.full_like(ps.normals, math.nan))
    albedo = torch.where(mask, ps.albedo, torch.full_like(ps.albedo, math.nan))
    rendered = _render_lambertian(ps.normals, ps.albedo, inputs)
    rendered = torch.where(mask[None, None], rendered, torch.full_like(rendered, math.nan))
    used = inputs.valid  # (K, H, W)
    residual = (rendered[:, 0] - inputs.stokes[:, 0])[used]
    rms = float(residual.pow(2).mean().sqrt()) if residual.numel() else math.nan
    n_mask = int(mask.sum())
    params = {
        "albedo_median": float(ps.albedo[mask].median()) if n_mask else math.nan,
        "valid_fraction": float((ps.valid & mask).sum()) / max(n_mask, 1),
    }
    return RecoveryOutcome(
        normals=_numpy(normals).astype(np.float32),
        albedo=_numpy(albedo).astype(np.float32),
        params=params,
        model="lambertian",
        mask=_numpy(mask).astype(bool),
        rendered=_numpy(rendered).astype(np.float32),
        observed=_numpy(inputs.stokes).astype(np.float32),
        history=[{"iteration": 0, "loss": rms, "loss_name": "rms_s0_residual"}],
        skipped=["reflectometry: the lambertian model has no material fit", "joint refinement: lambertian model"],
    )


def _number(value: Any) -> Any:
    """A parameter value as a Python float when it is numeric (tensor, numpy or Python), else as is."""
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        return float(value.detach().cpu())
    if isinstance(value, (int, float, np.generic)) and not isinstance(value, bool):
        return float(value)
    return value


def _joint_recovery(inputs: RecoveryInputs, config: RunConfig, device: str, dtype: torch.dtype) -> RecoveryOutcome:
    """FMBRDF reflectometry and joint refinement (:func:`polarshape.recover.joint.recover_inputs`) on
    the inputs this pipeline preprocessed (its mask, thresholds, point-light directions)."""
    from polarshape.recover import joint

    options = config.recovery
    result = joint.recover_inputs(
        inputs,
        joint.RecoveryConfig(
            model=options.model,
            per_pixel_albedo=options.per_pixel_albedo,
            fit_kappa=options.fit_kappa,
            max_outer_iterations=options.max_outer_iterations,
            subsample_pixels=options.subsample_pixels,
            coarse_to_fine=options.coarse_to_fine,
            smoothness=options.smoothness,
            propagate=options.propagate,
            demosaic=config.preprocess.demosaic,
            sample_at=config.preprocess.sample_at,
            device=device,
            dtype=dtype,
            seed=config.seed,
            progress=config.progress,
        ),
    )
    albedo = _numpy(result.albedo)
    rendered = _numpy(result.rendered)
    return RecoveryOutcome(
        normals=_numpy(result.normals).astype(np.float32),
        albedo=None if albedo is None else albedo.astype(np.float32),
        params={str(k): _number(v) for k, v in dict(result.params).items()},
        model=str(result.model),
        mask=_numpy(result.mask).astype(bool),
        rendered=None if rendered is None else rendered.astype(np.float32),
        observed=_numpy(result.observed).astype(np.float32),
        history=list(result.history),
        timings={str(k): float(v) for k, v in dict(result.timings).items()},
        skipped=list(result.skipped),
        filled=None if result.filled is None else _numpy(result.filled).astype(bool),
    )


def _mirror_closure(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Close a one-view surface into a solid: add its mirror image across the plane z = z_max.

    The plane through the deepest visible point (for a sphere: its silhouette, the equator) turns the
    visible shell and its mirror into one closed oriented point set, whose Poisson surface is
    watertight. Points and normals (N, 3), camera frame; returns (2N, 3) each.
    """
    plane = float(points[:, 2].max())
    back = points.copy()
    back[:, 2] = 2.0 * plane - back[:, 2]
    back_normals = normals.copy()
    back_normals[:, 2] = -back_normals[:, 2]
    return np.concatenate([points, back]), np.concatenate([normals, back_normals])


# --- evaluation --------------------------------------------------------------------------------


def angular_error_deg(normals: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W) angle between two normal maps in degrees; NaN where either is missing or off ``mask``.

    Args:
        normals, reference: (H, W, 3) normals (need not be exactly unit); NaN or zero = missing.
        mask: optional (H, W) bool of the pixels to evaluate.
    """
    a = np.asarray(normals, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"normal maps must both be (H, W, 3); got {a.shape} and {b.shape}")
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    ok = np.isfinite(na) & np.isfinite(nb) & (na > 1e-6) & (nb > 1e-6)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    err = np.degrees(np.arctan2(cross, dot))  # robust near 0 and 180° (spec §3 numerics)
    return np.where(ok, err, np.nan)


def angular_error_stats(error_deg: np.ndarray, reference_pixels: int | None = None) -> dict[str, float]:
    """Mean, median, RMS, percentiles (25/75/90/95) and shares below 5°/10°/20° of an error map.

    Args:
        error_deg: (H, W) errors in degrees, NaN = not evaluated.
        reference_pixels: pixels that should have been evaluated (for ``coverage``).
    """
    e = error_deg[np.isfinite(error_deg)]
    if e.size == 0:
        return {"pixels": 0}
    out: dict[str, float] = {
        "pixels": int(e.size),
        "mean_deg": float(e.mean()),
        "median_deg": float(np.median(e)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
    }
    for q in _PERCENTILES:
        out[f"p{q}_deg"] = float(np.percentile(e, q))
    for t in (5, 10, 20):
        out[f"within_{t}deg"] = float(np.mean(e < t))
    if reference_pixels:
        out["coverage"] = float(e.size / reference_pixels)
    return out


def depth_rmse_aligned(depth: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """RMSE of ``depth`` against ``reference`` after the least-squares scale and offset alignment.

    ``reference ≈ a · depth + b`` over the pixels where both are finite (and ``mask``); the RMSE is in
    the reference's unit, ``relative`` divides it by the reference's depth range there.
    """
    d = np.asarray(depth, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(r)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    if ok.sum() < 3:
        return {"pixels": int(ok.sum())}
    x, y = d[ok], r[ok]
    design = np.stack([x, np.ones_like(x)], axis=1)
    (scale, offset), *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = scale * x + offset - y
    rmse = float(np.sqrt(np.mean(residual**2)))
    span = float(y.max() - y.min())
    return {
        "pixels": int(ok.sum()),
        "rmse": rmse,
        "relative": rmse / span if span > 0 else math.nan,
        "scale": float(scale),
        "offset": float(offset),
        "reference_range": span,
    }


def _reference_normals(capture: Capture, shape: tuple[int, int]) -> np.ndarray | None:
    """The capture's ground-truth normals at super-pixel resolution (2×2 mean if given per raw pixel)."""
    gt = capture.ground_truth.get("normals")
    if not isinstance(gt, np.ndarray):
        return None
    gt = gt.astype(np.float64)
    if gt.shape[:2] == (2 * shape[0], 2 * shape[1]):
        gt = gt.reshape(shape[0], 2, shape[1], 2, 3).mean(axis=(1, 3))
        gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    return gt if gt.shape[:2] == shape else None


# --- the run -----------------------------------------------------------------------------------


def _protected(path: Path, config: RunConfig, config_path: Path | None) -> bool:
    """True when replacing ``path`` would remove input data (a capture, the config, the scene)."""
    path = path.resolve()
    if (path / "capture.yaml").exists():
        return True
    inputs = [config.input.path, config.input.scene, config.input.session, config_path]
    for item in inputs:
        if item is None:
            continue
        p = Path(item).resolve()
        if p == path or path in p.parents:
            return True
    return False


def _summary_line(out: Path, outcome: RecoveryOutcome, metrics: dict[str, Any], total_s: float) -> str:
    parts = [f"result in {out}", f"model {outcome.model}", f"{int(outcome.mask.sum())} px"]
    normal = metrics.get("normals", {})
    if "mean_deg" in normal:
        parts.append(f"normal error mean {normal['mean_deg']:.2f}° median {normal['median_deg']:.2f}° vs ground truth")
    depth = metrics.get("depth", {})
    if "rmse" in depth:
        parts.append(f"depth RMSE {depth['rmse']:.3g} ({100 * depth['relative']:.2f} % of range, scale/offset aligned)")
    parts.append(f"{total_s:.1f} s")
    return "; ".join(parts)


def run_pipeline(
    config: RunConfig,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    overwrite: bool = False,
    config_path: str | os.PathLike[str] | None = None,
) -> PipelineResult:
    """Run every stage and write the result folder atomically (module docstring: stages and files).

    Args:
        config: the validated run configuration.
        out_dir: the result folder (default ``config.output``).
        overwrite: replace an existing result folder (never an input capture).
        config_path: the configuration file, protected from being overwritten.

    Returns:
        :class:`PipelineResult` (folder, one-line summary, params.json content).

    Raises:
        ConfigError: no output folder, or ``device: cuda`` without a GPU.
        OutputExistsError: the folder exists and ``overwrite`` is False, or it holds input data.
        PipelineError, CaptureError, ValueError: a stage cannot run (message names the fix).
    """
    t_start = time.perf_counter()
    target = out_dir if out_dir is not None else config.output
    if target is None:
        raise ConfigError("output: no result folder; pass --out DIR or set output: in the config")
    out = Path(target).absolute()
    device = resolve_device(config.device)
    dtype = torch.float64 if config.dtype == "float64" else torch.float32
    torch.manual_seed(config.seed)
    cfg_path = Path(config_path) if config_path is not None else None
    log = _StageLog(config.progress)
    try:
        with atomic_directory(out, overwrite=overwrite, protect=lambda p: _protected(p, config, cfg_path)) as work:
            params = _run_stages(config, work, out, device, dtype, log, t_start)
    finally:
        log.close()
    total = params["timings_s"]["total"]
    logger.info("result written to %s (%.1f s)", out, total)
    return PipelineResult(out_dir=out, summary=params["summary"], params=params)


def _run_stages(
    config: RunConfig, work: Path, out: Path, device: str, dtype: torch.dtype, log: _StageLog, t_start: float
) -> dict[str, Any]:
    with log.stage("input"):
        capture = _acquire(config, work, device)
    h, w = capture.frames.shape[1] // 2, capture.frames.shape[2] // 2
    projection = capture.spec.camera.projection

    with log.stage("preprocess"):
        mask = _object_mask(capture, config, log)
        pixel_size = _orthographic_pixel_size(capture, config, log) if projection == "orthographic" else 1.0
        point_lights = any(light.position is not None for light in capture.spec.lights)
        points = _reference_points(capture, config, (h, w), pixel_size) if point_lights else None
        if point_lights:
            log.skip("preprocess", "point lights located from the plane at integration.reference_depth_m")
        inputs = preprocess_capture(
            dataclasses.replace(capture, mask=mask),
            dtype=dtype,
            device=device,
            dark_threshold=config.preprocess.dark_threshold,
            saturation_margin=config.preprocess.saturation_margin_counts,
            points=points,
            demosaic=config.preprocess.demosaic,
            sample_at=config.preprocess.sample_at,
        )

    with log.stage("initial_normals"):
        noise = max(config.initial_normals.noise_std, inputs.noise_std)
        ps = robust_lambertian_ps(
            inputs.stokes[:, 0],
            inputs.lights,
            inputs.irradiance,
            mask=inputs.valid,
            view_dirs=inputs.view,
            dark_rel=config.initial_normals.dark_rel,
            outlier_rel=config.initial_normals.outlier_rel,
            noise_std=noise,
            allow_degenerate=True,
        )
        ps_valid = int((ps.valid & inputs.mask).sum())
        logger.info("initial normals: %d of %d mask pixels valid", ps_valid, int(inputs.mask.sum()))

    with log.stage("recovery"):
        model = config.recovery.model
        if model != "lambertian":
            outcome = _joint_recovery(inputs, config, device, dtype)
        else:
            outcome = lambertian_recovery(inputs, ps)
        for item in outcome.skipped:
            log.skip("recovery", item)

    with log.stage("integration"):
        surface = outcome.mask & np.all(np.isfinite(outcome.normals), axis=-1)
        kmat = _superpixel_intrinsics(capture) if projection == "perspective" else None
        report = IntegrationReport()
        depth = integrate_normals(
            outcome.normals,
            surface,
            projection=projection,
            pixel_size=pixel_size,
            K=kmat,
            method=config.integration.method,
            reference_depth=config.integration.reference_depth_m,
            k=config.integration.bilateral_k,
            max_iter=config.integration.max_iter,
            min_component_size=config.preprocess.min_component_px,
            report=report,
        )
        depth_mask = np.isfinite(depth)

    with log.stage("mesh"):
        colors = None
        if config.mesh.colors == "albedo" and outcome.albedo is not None:
            top = np.nanpercentile(outcome.albedo[depth_mask], 99) if depth_mask.any() else 1.0
            colors = np.clip(np.nan_to_num(outcome.albedo / max(float(top), 1e-12)), 0.0, 1.0)
        elif config.mesh.colors == "albedo":
            log.skip("mesh", "vertex colours: no albedo map")
        mesh = depth_to_mesh(depth, depth_mask, projection=projection, pixel_size=pixel_size, K=kmat,
                             normals=outcome.normals, colors=colors)
        mesh_info: dict[str, Any] = {"vertices": len(mesh.vertices), "faces": len(mesh.faces)}
        write_mesh(mesh, work / "mesh.ply")
        if config.mesh.obj:
            write_mesh(mesh, work / "mesh.obj")
        if config.mesh.poisson:
            pts = depth_to_points(depth, projection=projection, pixel_size=pixel_size, K=kmat)[depth_mask]
            pts, nrm = pts, outcome.normals[depth_mask].astype(np.float64)  # (N, 3) each
            if config.mesh.watertight:
                pts, nrm = _mirror_closure(pts, nrm)
            poisson = poisson_mesh(pts, nrm, depth=config.mesh.poisson_depth, watertight=config.mesh.watertight)
            write_mesh(poisson, work / "mesh_poisson.ply")
            mesh_info["poisson"] = {
                "vertices": len(poisson.vertices), "faces": len(poisson.faces),
                "watertight": bool(poisson.is_watertight),
            }
        else:
            log.skip("mesh", "mesh_poisson.ply: mesh.poisson is false")

    with log.stage("export"):
        write_npy(outcome.normals.astype(np.float32), work / "normals.npy")
        write_normal_map_png(outcome.normals, work / "normal_map.png", convention=config.export.normal_convention)
        if config.export.exr:
            write_exr(outcome.normals.astype(np.float32), work / "normals.exr")
        else:
            log.skip("export", "normals.exr: export.exr is false")
        write_npy(depth.astype(np.float32), work / "depth.npy")
        write_image(work / "mask.png", np.where(outcome.mask, 255, 0).astype(np.uint8))
        if outcome.filled is not None:
            write_image(work / "filled.png", np.where(outcome.filled, 255, 0).astype(np.uint8))
        if outcome.albedo is not None:
            write_npy(outcome.albedo.astype(np.float32), work / "albedo.npy")
            finite = outcome.albedo[np.isfinite(outcome.albedo)]
            vmax = float(np.percentile(finite, 99.5)) if finite.size else 1.0
            write_scalar_map_png(outcome.albedo, work / "albedo.png", 0.0, max(vmax, 1e-12))
        else:
            log.skip("export", "albedo.png: the model estimated no albedo map")
        atomic_write_text(work / "config.yaml", yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))

    metrics: dict[str, Any] = {}
    error_map = None
    with log.stage("evaluation"):
        gt_normals = _reference_normals(capture, (h, w))
        if gt_normals is None:
            log.skip("evaluation", "the capture has no ground_truth/normals.npy")
        else:
            error_map = angular_error_deg(outcome.normals, gt_normals, outcome.mask)
            metrics["normals"] = angular_error_stats(error_map, int(outcome.mask.sum()))
            ps_normals = _numpy(ps.normals).astype(np.float64)
            metrics["initial_normals"] = angular_error_stats(
                angular_error_deg(ps_normals, gt_normals, outcome.mask), int(outcome.mask.sum())
            )
            write_npy(error_map.astype(np.float32), work / "error_map.npy")
        gt_depth = capture.ground_truth.get("depth")
        if isinstance(gt_depth, np.ndarray) and gt_depth.shape == (h, w):
            metrics["depth"] = depth_rmse_aligned(depth, gt_depth, depth_mask)
        else:
            log.skip("evaluation", "depth: the capture has no ground_truth/depth.npy at super-pixel size")
        if config.mesh.poisson and "poisson" in mesh_info:
            metrics["mesh_poisson_watertight"] = mesh_info["poisson"]["watertight"]

    params: dict[str, Any] = {
        "format": RESULT_FORMAT,
        "model": outcome.model,
        "params": outcome.params,
        "losses": {"final": outcome.history[-1] if outcome.history else None, "history": outcome.history},
        "metrics": metrics,
        "timings_s": dict(log.timings),
        "recovery_timings_s": outcome.timings,
        "skipped": log.skipped,
        "capture": {
            "source": str(capture.root) if capture.root is not None else f"{config.input.type} (not saved)",
            "input_type": config.input.type,
            "lights": capture.num_lights,
            "superpixels_hw": [h, w],
            "projection": projection,
            "mask_pixels": int(outcome.mask.sum()),
            "filled_pixels": None if outcome.filled is None else int(outcome.filled.sum()),
            "has_polarisation": bool(inputs.has_polarisation),
        },
        "integration": {
            "method": config.integration.method, "pixel_size_m": pixel_size if projection == "orthographic" else None,
            "solver": report.solver, "components": report.components, "iterations": report.iterations,
        },
        "mesh": mesh_info,
        "initial_normals": {"valid_pixels": ps_valid},
        "normal_map_convention": config.export.normal_convention,
        "device": device,
        "dtype": config.dtype,
    }

    params["summary"] = _summary_line(out, outcome, metrics, time.perf_counter() - t_start)
    with log.stage("report"):
        if config.report.enabled:
            data = ReportData(
                normals=outcome.normals, albedo=outcome.albedo, mask=outcome.mask, observed=outcome.observed,
                rendered=outcome.rendered, lights=_numpy(inputs.lights), irradiance=_numpy(inputs.irradiance),
                view=_numpy(inputs.view), valid=_numpy(inputs.valid), params=params, error_map=error_map,
                seed=config.seed, max_curve_pixels=config.report.max_curve_pixels,
            )
            files = write_report(work, data, fmt=config.report.format)
            params["report"] = [f.name for f in files]
        else:
            log.skip("report", "report.enabled is false")

    total = time.perf_counter() - t_start
    params["timings_s"] = {**log.timings, "total": total}
    params["skipped"] = log.skipped
    params["summary"] = _summary_line(out, outcome, metrics, total)
    params = _plain_json(params)
    atomic_write_text(work / "params.json", json.dumps(params, indent=1, allow_nan=False))
    return params


def _plain_json(value: Any) -> Any:
    """JSON-ready copy: numpy/torch scalars and arrays to Python, paths to text, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): _plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain_json(v) for v in value]
    if isinstance(value, torch.Tensor):
        return _plain_json(value.detach().cpu().tolist())
    if isinstance(value, np.ndarray):
        return _plain_json(value.tolist())
    if isinstance(value, np.generic):
        return _plain_json(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    raise TypeError(f"params.json: cannot serialise a {type(value).__name__}")
