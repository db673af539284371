"""``polarshape run``: capture → normals, reflectance, depth, mesh, report, in one result folder.

:func:`run_pipeline` composes one short function per stage (each logs its time and what it skipped;
params.json records both):

1. ``input`` — :func:`acquire`: load a capture folder, or record one first (simulated camera or a
   capture session);
2. ``preprocess`` — :func:`preprocess`: object mask, Stokes images, observation validity, per-pixel
   lights and view directions (:func:`polarshape.recover.preprocess.preprocess_capture`);
3. ``recovery`` — :func:`polarshape.normals.recover_normals`: initial normals (robust Lambertian
   PS), model choice, the FMBRDF joint fit or the Lambertian answer (with ``recovery.material``:
   a known material, fixed or as the start; params.json's ``material`` records which);
   ``nearfield`` — :func:`near_field`: under point lights, per-pixel L and E moved to the recovered
   surface and the object's distance estimated from the shading, the model refitted
   (:mod:`polarshape.nearfield`; params.json's ``nearfield``);
   ``validation`` — :func:`validate`: fit without a few lights, predict them, compare the models
   (params.json's ``validation``; :mod:`polarshape.recover.validation`);
   ``checks`` — :func:`polarshape.recover.selfcheck.run_self_checks`: fit residual against the noise,
   conventions, frame order, parameter bounds, filled/frozen pixels, model evidence, each a named
   warning (params.json's ``checks``; ``strict``: an error once the result is written);
4. ``integration`` — :func:`integrate`: depth from the normals (:mod:`polarshape.surface.integrate`);
5. ``mesh`` — :func:`build_meshes`: grid mesh of the depth map (and screened Poisson if asked);
6. ``export`` — result files (:func:`polarshape.io.results.write_maps`; a colour capture's albedo.png
   and albedo.npy are RGB, :func:`albedo_map`);
7. ``evaluation`` — :func:`evaluate`: errors against the capture's ground truth, when it has some;
8. ``report`` — report.html with PNG plots (or report.png).

The result folder (:mod:`polarshape.io.results`) is built under a temporary name and renamed into
place only when complete, so an interrupted run leaves nothing half-written; never over the input,
and over an existing result only with ``overwrite``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import shutil
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.ndimage
import torch
from torch import Tensor
import yaml
from tqdm import tqdm

from polarshape import __version__
from polarshape.cameras import Camera
from polarshape.config import RecoveryOptions, RunConfig
from polarshape.errors import (
    CaptureError, ConfigError, InterreflectionWarning, NearFieldDepthWarning, PipelineError, PolarshapeWarning,
    SelfCheckError,
)
from polarshape.io.export import write_npy
from polarshape.io.material import load_material
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.pixels import counts_to_float, max_count
from polarshape.checks import resolve_device, to_numpy, wait_for_device
from polarshape.io.atomic import atomic_directory, atomic_write_text
from polarshape.io.capture import Capture, load_capture, write_capture
from polarshape.io.polarimetric import polarimetric_calibration_record
from polarshape.io.results import RESULT_FORMAT, output_refusal, write_maps, write_material_maps, write_params
from polarshape.metrics import angular_error_deg, angular_error_stats, depth_rmse_absolute, depth_rmse_aligned
from polarshape.nearfield import NearFieldResult, near_field_active, refine_near_field
from polarshape.surface.interreflection import estimate_one_bounce
from polarshape.normals import NormalsResult, recover_normals
from polarshape.recover.coarse_to_fine import KnownMaterial
from polarshape.recover.diagnose import dark_capture_cause
from polarshape.recover.observations import RecoveryInputs
from polarshape.recover.colour import colour_albedo_summary
from polarshape.recover.preprocess import capture_camera, colour_superpixel_stokes, preprocess_capture
from polarshape.recover.selfcheck import run_self_checks
from polarshape.recover.validation import Validation, model_evidence, validate_holdout
from polarshape.report import ReportData, material_truth, rewrite_report_page, write_report
from polarshape.surface.integrate import IntegrationReport, integrate_normals
from polarshape.surface.mesh import FRAME_AXES, MESH_FRAMES, depth_to_mesh, mesh_file_checks, poisson_mesh, write_mesh

logger = logging.getLogger(__name__)

__all__ = [
    "STAGES", "PipelineError", "PipelineResult", "Surface", "acquire", "albedo_map", "build_meshes", "evaluate",
    "integrate", "interreflection", "near_field", "preprocess", "run_pipeline", "validate",
]

STAGES: tuple[str, ...] = ("input", "preprocess", "recovery", "nearfield", "interreflection", "validation", "checks", "integration", "mesh", "export",
                           "evaluation", "report")


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


@dataclass(frozen=True)
class Surface:
    """The integration stage's output: depth (H, W) (NaN outside), the camera it was integrated with,
    and what the solver reported."""

    depth: np.ndarray
    camera: Camera
    report: IntegrationReport
    #: where the absolute depth comes from when not from ``integration.reference_depth_m`` (near-field lights)
    scale_from: str | None = None

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self.depth)


class _StageLog:
    """Times the stages, records what they skipped, and drives the stage progress bar. On a GPU each
    stage's time waits for its queued kernels (:func:`~polarshape.checks.wait_for_device`), so the
    time is the stage's, not the next one's."""

    def __init__(self, progress: bool, device: str = "cpu") -> None:
        self.device = device
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
        wait_for_device(self.device)
        self.timings[name] = seconds = time.perf_counter() - t0
        skipped = self.skipped[before:]
        logger.info("stage %s: %.2f s%s", name, seconds, f"; skipped: {'; '.join(skipped)}" if skipped else "")
        self._bar.update(1)

    def skip(self, stage: str, reason: str) -> None:
        self.skipped.append(f"{stage}: {reason}")

    def close(self) -> None:
        self._bar.close()


# --- input -------------------------------------------------------------------------------------


def acquire(config: RunConfig, work: Path, device: str) -> Capture:
    """The capture of the run: loaded, simulated, or recorded by a session (into ``work/capture``)."""
    source = config.input
    if source.type == "capture":
        return load_capture(source.path)
    target = work / "capture"
    if source.type == "simulated":
        from polarshape.acquisition.simulated import SimulatedCamera

        with SimulatedCamera(source.scene, device=device, seed=source.seed) as camera:
            capture = camera.render_capture(progress=config.progress)
        if source.save_capture:
            write_capture(target, capture)
            capture = dataclasses.replace(capture, root=target)
        return capture
    from polarshape.acquisition.session import capture_session

    capture_session(source.session, target)
    capture = load_capture(target)
    if not source.save_capture:
        shutil.rmtree(target)
        capture = dataclasses.replace(capture, root=None)
    return capture


# --- preprocess --------------------------------------------------------------------------------


def _threshold_mask(capture: Capture, threshold: float) -> np.ndarray:
    """(H, W) bool: super-pixels whose brightest s0 over the lights exceeds ``threshold`` of full scale
    (a colour capture: the channel mean's s0, not the block's own colour's)."""
    mosaic = counts_to_float(capture.frames, capture.bit_depth, capture.spec.camera.black_level)  # (K, 2H, 2W)
    bayer = capture.spec.camera.mosaic.bayer
    if bayer is None:
        s0 = stokes_from_mosaic(mosaic, capture.layout, "superpixel")[:, 0]  # (K, H, W)
    else:
        s0 = colour_superpixel_stokes(mosaic, capture.layout, bayer)[1][:, 0]  # (K, H, W)
    return (s0.amax(0) > threshold).numpy()


def _clean_mask(mask: np.ndarray, erode_px: int, min_component_px: int) -> np.ndarray:
    """Erode ``mask`` by ``erode_px`` and drop its 4-connected components under ``min_component_px``."""
    out = scipy.ndimage.binary_erosion(mask, iterations=erode_px) if erode_px else mask.copy()
    labels, n = scipy.ndimage.label(out)
    if n:
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        out &= sizes[labels] >= min_component_px
    return out


def _refuse_dark_capture(capture: Capture, threshold: float) -> None:
    """An empty threshold mask: a capture dark everywhere (or below its black level) is refused, naming the cause."""
    camera = capture.spec.camera
    full, black = max_count(camera.bit_depth), float(camera.black_level)
    top = int(capture.frames.max()) if capture.frames.size else 0
    if top <= black or (top - black) / (full - black) <= threshold:
        cause = dark_capture_cause(capture, top, threshold, "preprocess.mask_threshold")
        raise CaptureError(f"capture (no mask.png: the object is where the frames are bright): {cause}")


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
    if not mask.any():
        _refuse_dark_capture(capture, config.preprocess.mask_threshold)
    mask = _clean_mask(mask, config.preprocess.erode_px, config.preprocess.min_component_px)
    if not mask.any():
        raise PipelineError(
            "the object mask is empty: lower preprocess.mask_threshold, preprocess.erode_px or "
            "preprocess.min_component_px, or check the exposure"
        )
    return mask


#: What the integration stage records when an orthographic run has no pixel size (depth, meshes in super-pixels).
_NO_METRIC_SCALE = "metric scale: no integration.pixel_size_m, depth in super-pixel units"


def _pixel_size(capture: Capture, config: RunConfig, log: _StageLog) -> float | None:
    """Orthographic: metres per super-pixel — the config's, else the simulated scene's, else 1
    (super-pixel units). Perspective: None (the intrinsics set the scale)."""
    if capture.spec.camera.projection != "orthographic":
        return None
    if config.integration.pixel_size_m is not None:
        return float(config.integration.pixel_size_m)
    scene = capture.ground_truth.get("scene")
    raw = (scene.get("scene") or {}).get("camera", {}).get("pixel_size_m") if isinstance(scene, dict) else None
    if isinstance(raw, (int, float)) and raw > 0:
        return 2.0 * float(raw)  # a super-pixel spans two raw pixels
    log.skip("integration", _NO_METRIC_SCALE)
    return 1.0


def preprocess(capture: Capture, config: RunConfig, log: _StageLog, *, device: str, dtype: torch.dtype
               ) -> tuple[RecoveryInputs, Camera]:
    """The recovery's inputs and the super-pixel camera (block centres) the surface is built with.

    Point lights are placed from the plane z = ``integration.reference_depth_m`` (no depth exists yet; the
    ``nearfield`` stage then moves them to the recovered surface).
    Frames without a polarisation signal (a demosaiced or plain image saved as a frame) are refused
    unless ``preprocess.polarisation_check`` is false
    (:func:`polarshape.recover.diagnose.check_polarisation_signal`).
    """
    mask = _object_mask(capture, config, log)
    camera = capture_camera(capture, "centre", _pixel_size(capture, config, log))
    points = camera.unproject(np.full(mask.shape, config.integration.reference_depth_m))  # (H, W, 3)
    if capture.lights().has_point_lights:
        log.skip("preprocess", "point lights located from the plane at integration.reference_depth_m")
    options = config.preprocess
    inputs = preprocess_capture(
        dataclasses.replace(capture, mask=mask), dtype=dtype, device=device, dark_threshold=options.dark_threshold,
        saturation_margin=options.saturation_margin_counts, points=points, demosaic=options.demosaic,
        sample_at=options.sample_at, polarisation_check=options.polarisation_check, albedo_edges=options.albedo_edges,
    )
    if not options.polarisation_check:
        log.skip("preprocess", "polarisation check off (preprocess.polarisation_check: false)")
    return inputs, camera


# --- integration, meshes -----------------------------------------------------------------------


def _integrate_map(normals: np.ndarray, mask: np.ndarray, camera: Camera, config: RunConfig,
                   depth_init: np.ndarray | None = None, report: IntegrationReport | None = None) -> np.ndarray:
    """(H, W) depth of a normal map (H, W, 3) on ``mask`` with the run's integration options."""
    options = config.integration
    return integrate_normals(
        normals, mask, camera=camera, method=options.method, reference_depth=options.reference_depth_m,
        depth_init=depth_init, k=options.bilateral_k, max_iter=options.max_iter,
        min_component_size=config.preprocess.min_component_px, report=report,
    )


def _integrated_surface(result: NormalsResult, camera: Camera, config: RunConfig, nearfield: NearFieldResult | None,
                        integrated: dict[str, Any]) -> Surface:
    """:func:`integrate`, or the surface an earlier stage integrated from these very normals and mask (the
    interreflection stage's, when it changed neither: a full frame's integration is seconds)."""
    if (integrated.get("normals") is result.normals and integrated.get("mask") is result.mask
            and integrated.get("nearfield") is nearfield):
        return integrated["surface"]
    return integrate(result, camera, config, nearfield)


def integrate(result: NormalsResult, camera: Camera, config: RunConfig, nearfield: NearFieldResult | None = None
              ) -> Surface:
    """Depth of the recovered normals (the pixels with a finite normal); with near-field lights, placed
    where :func:`near_field` found the surface (its depth is the gauge)."""
    normals = to_numpy(result.normals)
    surface = to_numpy(result.mask) & np.all(np.isfinite(normals), axis=-1)
    report = IntegrationReport()
    depth = _integrate_map(normals, surface, camera, config, None if nearfield is None else nearfield.depth, report)
    scale_from = "the point lights' shading (near-field)" if nearfield is not None and nearfield.estimated else None
    return Surface(depth, camera, report, scale_from)


# --- near-field lights -------------------------------------------------------------------------


def _first_recovery(capture: Capture, config: RunConfig, log: _StageLog) -> RecoveryOptions:
    """The recovery stage's options. When the ``nearfield`` stage will run, it fits the run's model again at the
    lights it moves to the surface, and a fit at the lights placed from the reference plane would be discarded:
    the stage then gives a Lambertian start (robust PS, milliseconds)."""
    if near_field_active(config.nearfield, capture.lights()) and f"integration: {_NO_METRIC_SCALE}" not in log.skipped:
        log.skip("recovery", "a Lambertian start: the model is fitted in the nearfield stage, at the lights moved to "
                 "the surface")
        return config.recovery.model_copy(update={"model": "lambertian"})
    return config.recovery


def near_field(capture: Capture, inputs: RecoveryInputs, result: NormalsResult, camera: Camera, config: RunConfig,
               log: _StageLog) -> tuple[RecoveryInputs, NormalsResult, NearFieldResult | None]:
    """Point lights: L and E moved to the recovered surface and the absolute depth estimated from the
    shading (:func:`polarshape.nearfield.refine_near_field`); returns the final inputs and result.
    Skipped (recorded) under directional lights, with ``nearfield.enabled: false``, and for an
    orthographic camera without a metric pixel size (:class:`NearFieldDepthWarning`)."""
    lights = capture.lights()
    if not near_field_active(config.nearfield, lights):
        log.skip("nearfield", "no point lights" if not lights.has_point_lights else "nearfield.enabled is false")
        return inputs, result, None
    if f"integration: {_NO_METRIC_SCALE}" in log.skipped:
        warnings.warn(NearFieldDepthWarning(
            "near-field lights need metric surface points, but this orthographic run has no pixel size: set "
            "integration.pixel_size_m (metres per super-pixel); lights stay placed from integration.reference_depth_m"
        ), stacklevel=2)
        log.skip("nearfield", "orthographic camera without integration.pixel_size_m")
        return inputs, result, None

    def recover(new_inputs: RecoveryInputs, material: KnownMaterial | None = None, **changes: Any) -> NormalsResult:
        options = config.recovery.model_copy(update=changes) if changes else config.recovery
        return recover_normals(new_inputs, options, config.initial_normals, seed=config.seed, progress=False,
                               material=material)

    found = refine_near_field(
        inputs, result, camera, lights, recover=recover,
        integrate=lambda n, m, init: _integrate_map(n, m, camera, config, init),
        reference_depth=config.integration.reference_depth_m, options=config.nearfield, initial=config.initial_normals,
    )
    for item in found.skipped:
        log.skip("nearfield", item)
    for item in found.result.skipped:  # the fit the run keeps (the recovery stage's was a Lambertian start)
        log.skip("recovery", item)
    return found.inputs, found.result, found


def interreflection(inputs: RecoveryInputs, result: NormalsResult, camera: Camera, capture: Capture, config: RunConfig,
                    log: _StageLog, nearfield: NearFieldResult | None = None, *,
                    integrated: dict[str, Any] | None = None
                    ) -> tuple[RecoveryInputs, NormalsResult, dict[str, Any], Tensor | None]:
    """Light the object sends onto itself (``interreflection:``): taken out and re-fitted, or marked.

    The current normals are integrated and one bounce B off that surface is rendered with the current
    material (:func:`polarshape.surface.interreflection.estimate_one_bounce`). The albedos are in the
    capture's units — c times the physical ones, for an unknown c (exposure, gain, light power) — and
    a bounce scales with the albedo twice, so the bounce in the photos is B / c:

    - with ``albedo_scale`` (c, from a white reference target) the bounce B / c is subtracted from the
      observed Stokes and the normals and material are recovered again, ``iterations`` times;
    - without it c is not known (a fit of direct light absorbs the excess into normals and albedo, so
      the residual does not reveal it): the pixels where the bounce could exceed ``min_fraction`` of
      the light — with c at its physical lower bound, the brightest albedo white — are marked
      (``interreflection.npy``) and, on more than ``min_area`` of the object, a named
      :class:`InterreflectionWarning` says so.

    ``auto`` stops after the first estimate when the bounce exceeds ``min_fraction`` of the light on less
    than ``min_area`` of the object (a convex object sees nothing of itself); ``on`` always corrects
    (needs ``albedo_scale``). Under point lights the surface is placed where ``nearfield`` found it
    (the bounce points must be lit from where the lights really are).

    ``integrated`` (a dict, optional) receives the last surface integrated and the result it was integrated from
    (:func:`_integrated_surface`: the integration stage reuses it when the normals did not change).

    Returns:
        the inputs the final result was fitted to, that result, the record for params.json
        (``interreflection``) and the (H, W) map of the largest bounce fraction over the lights (None
        when not estimated).
    """
    options = config.interreflection
    record: dict[str, Any] = {"mode": options.mode, "applied": False, "albedo_scale": options.albedo_scale, "rounds": []}
    if options.mode == "off":
        log.skip("interreflection", "interreflection.mode: off")
        return inputs, result, record, None
    if result.model != "fmbrdf" or not all(k in result.params for k in ("ior", "k_s", "alpha", "beta")):
        log.skip("interreflection", f"needs the FMBRDF material (the run's model is {result.model})")
        return inputs, result, record, None
    observed = inputs.stokes  # (K, 3, H, W)
    usable = inputs.valid & inputs.mask.unsqueeze(0)  # (K, H, W)
    fraction_map: Tensor | None = None
    for round_index in range(options.iterations if options.albedo_scale is not None else 1):
        surface = integrate(result, camera, config, nearfield)
        if integrated is not None:
            integrated.update(surface=surface, normals=result.normals, mask=result.mask, nearfield=nearfield)
        bounce = estimate_one_bounce(
            result.normals, result.albedo, surface.depth, camera, inputs.view, capture.lights(), result.params,
            samples=options.samples, max_pixels=options.max_pixels, seed=config.seed,
        ).stokes.to(observed)  # (K, 3, H, W) with c = 1
        if options.albedo_scale is not None:
            scale = options.albedo_scale
        else:  # c ≥ the brightest body albedo (no physical albedo above 1)
            albedo = result.albedo[inputs.mask & torch.isfinite(result.albedo)]
            scale = max(float(torch.quantile(albedo.double(), 0.99)), 1e-12) if albedo.numel() else math.inf
        fraction = torch.where(usable, bounce[:, 0] / scale / observed[:, 0].clamp_min(1e-6), 0.0)  # (K, H, W)
        fraction_map = fraction.amax(0)  # (H, W)
        marked = (fraction_map > options.min_fraction) & inputs.mask
        area = float(marked.sum()) / max(int(inputs.mask.sum()), 1)
        record["rounds"].append({"albedo_scale": scale, "area": area, "max_fraction": float(fraction_map.max())})
        if round_index == 0 and options.mode == "auto" and area < options.min_area:
            log.skip("interreflection", f"no concavity: the bounce exceeds {options.min_fraction:.0%} of the light on "
                     f"{area:.1%} of the object (< {options.min_area:.0%})")
            return inputs, result, record, fraction_map
        if options.albedo_scale is None:
            record["marked_pixels"] = int(marked.sum())
            warnings.warn(InterreflectionWarning(
                f"{area:.0%} of the object sees itself and may receive up to {float(fraction_map.max()):.0%} of its "
                "light from itself; the normals there may be bent: set interreflection.albedo_scale (the capture's "
                "albedo per physical albedo, from a white reference) to take the bounce out (marked pixels: "
                "interreflection.npy)"), stacklevel=2)
            return inputs, result, record, fraction_map
        inputs = dataclasses.replace(inputs, stokes=observed - bounce / scale)
        result = recover_normals(inputs, config.recovery, config.initial_normals, seed=config.seed,
                                 progress=config.progress)
        record["applied"] = True
    logger.info("interreflection: %d rounds with albedo scale %.4g; the bounce exceeded %.0f %% of the light on "
                "%.1f %% of the object", options.iterations, options.albedo_scale, 100 * options.min_fraction,
                100 * record["rounds"][-1]["area"])
    return inputs, result, record, fraction_map


def _mirror_closure(points: np.ndarray, normals: np.ndarray, colours: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Close a one-view surface into a solid: add its mirror image across the plane z = z_max.

    The plane through the deepest visible point (for a sphere: its silhouette, the equator) turns the
    visible shell and its mirror into one closed oriented point set, whose Poisson surface is
    watertight. Points and normals (N, 3), camera frame, colours (N, ...) or None; returns (2N, ...)
    each, the mirror image with the colours of the points it mirrors.
    """
    plane = float(points[:, 2].max())
    back = points.copy()
    back[:, 2] = 2.0 * plane - back[:, 2]
    back_normals = normals.copy()
    back_normals[:, 2] = -back_normals[:, 2]
    both_colours = None if colours is None else np.concatenate([colours, colours])
    return np.concatenate([points, back]), np.concatenate([normals, back_normals]), both_colours


def albedo_map(result: NormalsResult) -> np.ndarray:
    """The albedo the result files show: (H, W, 3) R, G, B for a colour capture, else (H, W)."""
    return to_numpy(result.albedo if result.albedo_rgb is None else result.albedo_rgb)


def _vertex_colours(albedo: np.ndarray | None, surface: Surface, config: RunConfig, log: _StageLog) -> np.ndarray | None:
    """Albedo scaled to [0, 1] by its 99th percentile ((H, W) or (H, W, 3)), or None."""
    if config.mesh.colors != "albedo":
        return None
    if albedo is None:
        log.skip("mesh", "vertex colours: no albedo map")
        return None
    top = np.nanpercentile(albedo[surface.mask], 99) if surface.mask.any() else 1.0
    return np.clip(np.nan_to_num(albedo / max(float(top), 1e-12)), 0.0, 1.0)


def _mesh_units(surface: Surface, log: _StageLog) -> tuple[str, str]:
    """(units, where the scale comes from) of the meshes: ``metres``, or ``superpixels`` when an
    orthographic run had no pixel size (:func:`_pixel_size` recorded that it fell back to 1)."""
    if surface.scale_from is not None:
        return "metres", f"{surface.camera.projection} camera; absolute depth from {surface.scale_from}"
    if surface.camera.projection != "orthographic":
        return "metres", "perspective intrinsics; absolute scale from integration.reference_depth_m"
    if f"integration: {_NO_METRIC_SCALE}" in log.skipped:
        return "superpixels", "no metric scale: integration.pixel_size_m unset (x, y, z in super-pixels)"
    return "metres", f"orthographic, {surface.camera.pixel_size_m:.6g} m per super-pixel"


def _poisson(work: Path, normals: np.ndarray, colours: np.ndarray | None, surface: Surface, config: RunConfig,
             frame: str, units: str) -> dict[str, Any]:
    """mesh_poisson.ply (albedo-coloured points, mirror-closed with ``mesh.watertight``); returns open3d's
    verdict on the file as written, what the repair removed, and the time of each step."""
    t0 = time.perf_counter()
    pts = surface.camera.unproject(surface.depth)[surface.mask]  # (N, 3)
    nrm = normals[surface.mask].astype(np.float64)  # (N, 3)
    cols = None if colours is None else colours[surface.mask]  # (N,) or (N, 3)
    if config.mesh.watertight:
        pts, nrm, cols = _mirror_closure(pts, nrm, cols)
    poisson = poisson_mesh(pts, nrm, depth=config.mesh.poisson_depth, colors=cols, watertight=config.mesh.watertight,
                           repair=config.mesh.repair)
    path = write_mesh(poisson, work / "mesh_poisson.ply", frame=frame, units=units)
    t1 = time.perf_counter()
    checks = mesh_file_checks(path)  # vertices, triangles, watertight, ... of the file
    return {
        **checks, "colours": poisson.visual.kind == "vertex", "mirror_closed": config.mesh.watertight,
        "octree_depth": config.mesh.poisson_depth, "repair": poisson.metadata.get("repair"),
        "timings_s": {"reconstruct_and_write": t1 - t0, "checks": time.perf_counter() - t1},
    }


def build_meshes(work: Path, result: NormalsResult, surface: Surface, config: RunConfig, log: _StageLog) -> dict[str, Any]:
    """mesh.ply (+ mesh.obj) of the depth map and, with ``mesh.poisson``, mesh_poisson.ply, all in
    ``mesh.frame`` with the units in their headers; returns params.json's ``mesh`` section (frame,
    units, sizes, open3d's checks of mesh_poisson.ply)."""
    normals = to_numpy(result.normals)
    colours = _vertex_colours(albedo_map(result), surface, config, log)
    frame = config.mesh.frame
    units, scale = _mesh_units(surface, log)
    mesh = depth_to_mesh(surface.depth, surface.mask, camera=surface.camera, normals=normals, colors=colours)
    info: dict[str, Any] = {
        "frame": frame, "axes": FRAME_AXES[frame], "from_camera_frame": MESH_FRAMES[frame].tolist(), "units": units,
        "scale": scale, "files": ["mesh.ply"], "vertices": len(mesh.vertices), "faces": len(mesh.faces),
    }
    write_mesh(mesh, work / "mesh.ply", frame=frame, units=units)
    if config.mesh.obj:
        write_mesh(mesh, work / "mesh.obj", frame=frame, units=units)
        info["files"].append("mesh.obj")
    if not config.mesh.poisson:
        log.skip("mesh", "mesh_poisson.ply: mesh.poisson is false")
        return info
    info["poisson"] = _poisson(work, normals, colours, surface, config, frame, units)
    info["files"].append("mesh_poisson.ply")
    if config.mesh.watertight and not info["poisson"]["watertight"]:
        logger.warning("mesh_poisson.ply is not watertight by open3d's checks: see mesh.poisson in params.json")
    return info


# --- validation --------------------------------------------------------------------------------


def validate(inputs: RecoveryInputs, result: NormalsResult, config: RunConfig, log: _StageLog
             ) -> tuple[NormalsResult, Validation]:
    """Held-out-light validation (:func:`polarshape.recover.validation.validate_holdout`) and
    ``recovery.model: auto``'s use of it (:func:`~polarshape.recover.validation.model_evidence`): when
    the other of fmbrdf / lambertian predicts the held-out lights clearly better, the run is redone
    with it (the returned result)."""
    validation = validate_holdout(inputs, result, config.recovery, config.initial_normals, config.validation,
                                  seed=config.seed)
    if not validation.ran or validation.reason:
        log.skip("validation", validation.reason or "no light held out")
    if not validation.ran:
        return result, validation
    choice = validation.model_choice = model_evidence(validation, result.model, config.recovery.model)
    if choice is None or choice["switch_to"] is None:
        return result, validation
    switch = choice["switch_to"]
    logger.info("validation: %s", choice["verdict"])
    log.skip("validation", f"recovery.model auto: {choice['verdict']}")
    redone = recover_normals(inputs, config.recovery.model_copy(update={"model": switch}), config.initial_normals,
                             seed=config.seed, progress=config.progress)
    for item in redone.skipped:
        log.skip("recovery", item)
    validation.predicted = validation.predictions.get(switch, validation.predicted)
    return redone, validation


def _holdout_fields(validation: Validation | None) -> dict[str, Any]:
    """ReportData's held-out fields (empty when the validation did not run)."""
    if validation is None or not validation.ran:
        return {}
    return {"holdout_lights": list(validation.holdout), "holdout_observed": validation.observed,
            "holdout_predicted": validation.predicted}


# --- evaluation --------------------------------------------------------------------------------


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


def evaluate(capture: Capture, result: NormalsResult, surface: Surface, log: _StageLog
             ) -> tuple[dict[str, Any], np.ndarray | None]:
    """Errors against the capture's ground truth (normals, initial normals, depth); and the (H, W)
    angular error map in degrees, or None without ground-truth normals."""
    mask = to_numpy(result.mask)
    metrics: dict[str, Any] = {}
    error_map = None
    gt_normals = _reference_normals(capture, mask.shape)
    if gt_normals is None:
        log.skip("evaluation", "the capture has no ground_truth/normals.npy")
    else:
        error_map = angular_error_deg(to_numpy(result.normals), gt_normals, mask)
        metrics["normals"] = angular_error_stats(error_map, int(mask.sum()))
        initial = angular_error_deg(to_numpy(result.initial_normals), gt_normals, mask)
        metrics["initial_normals"] = angular_error_stats(initial, int(mask.sum()))
    gt_depth = capture.ground_truth.get("depth")
    if isinstance(gt_depth, np.ndarray) and gt_depth.shape == mask.shape:
        metrics["depth"] = depth_rmse_aligned(surface.depth, gt_depth, surface.mask)
        if not _metric_depth_unknown(log):
            metrics["depth_absolute"] = depth_rmse_absolute(surface.depth, gt_depth, surface.mask)
    else:
        log.skip("evaluation", "depth: the capture has no ground_truth/depth.npy at super-pixel size")
    if result.albedo_rgb is not None:
        colour = _colour_metrics(capture, result)
        if colour is None:
            log.skip("evaluation", "colour: the capture has no ground_truth/albedo_rgb.npy at super-pixel size")
        else:
            metrics["albedo_rgb"] = colour
    return metrics, error_map


def _colour_metrics(capture: Capture, result: NormalsResult) -> dict[str, Any] | None:
    """The recovered per-channel albedo against ground_truth/albedo_rgb.npy: the chromaticity (median
    per channel over the mask divided by the mean of the medians; the albedo's scale depends on the
    irradiance units) and its relative error per channel, in %; None without the truth."""
    mask = to_numpy(result.mask)
    truth = capture.ground_truth.get("albedo_rgb")
    if not isinstance(truth, np.ndarray) or truth.shape != (*mask.shape, 3):
        return None
    ok = mask & np.isfinite(truth).all(-1)
    got = colour_albedo_summary(to_numpy(result.albedo_rgb), ok)["chromaticity"]
    want = colour_albedo_summary(truth, ok)["chromaticity"]
    if None in got or None in want:
        return None
    error = [100.0 * (g - t) / t for g, t in zip(got, want)]
    return {"chromaticity": got, "truth_chromaticity": want, "chromaticity_error_pct": error,
            "max_abs_chromaticity_error_pct": max(abs(e) for e in error)}


def _metric_depth_unknown(log: _StageLog) -> bool:
    """Whether the depth is in super-pixel units (orthographic without a pixel size): no absolute error."""
    return f"integration: {_NO_METRIC_SCALE}" in log.skipped


# --- params.json, report -----------------------------------------------------------------------


def _what_ran(result: NormalsResult, params: dict[str, Any], has_polarisation: bool) -> str:
    """The model that actually ran, and why when it was not the one asked for."""
    if result.model == "fmbrdf":
        return "model fmbrdf" if has_polarisation else "intensity-only FMBRDF: no polarisation above noise"
    choice = (params.get("validation") or {}).get("model_choice") or {}
    if choice.get("switch_to") == "lambertian":
        return "lambertian (auto: predicts the held-out lights better than fmbrdf)"
    if any("model 'lambertian' chosen" in item for item in result.skipped):
        return "lambertian (auto: Lambertian PS explains the data, no polarisation)"
    return f"model {result.model}"


def _held_out_part(params: dict[str, Any], model: str) -> str | None:
    """"held-out s0 error 2.1 % (noise 1.9 %)" of the run's model, or why there is none."""
    validation = params.get("validation")
    if not validation or validation.get("mode") == "none":  # none: the user's choice, nothing to report
        return None
    record = (validation.get("models") or {}).get(model) or {}
    error, floor = record.get("s0_rel_rmse"), validation.get("noise_floor_s0_rel")
    if error is None:
        return f"no held-out validation ({validation['reason']})" if validation.get("reason") else None
    noise = f" (noise {100 * floor:.1f} %)" if floor is not None else ""
    return f"held-out s0 error {100 * error:.1f} %{noise}"


def _warnings_part(warned: list[str]) -> str | None:
    """"2 warnings: FitResidualWarning, ConventionWarning" (each kind once), or None without any."""
    if not warned:
        return None
    kinds = list(dict.fromkeys(w.partition(": ")[0] for w in warned))
    return f"{len(warned)} warning{'s' if len(warned) != 1 else ''}: {', '.join(kinds)}"


def _summary_line(out: Path, result: NormalsResult, metrics: dict[str, Any], total_s: float, *,
                  params: dict[str, Any] | None = None, has_polarisation: bool = True,
                  warned: list[str] | None = None) -> str:
    """One line: where, what ran, held-out error, ground-truth errors (if any), warnings, time."""
    params = params or {}
    parts = [f"result in {out}", _what_ran(result, params, has_polarisation), f"{int(result.mask.sum())} px"]
    held_out = _held_out_part(params, result.model)
    if held_out:
        parts.append(held_out)
    normal = metrics.get("normals", {})
    if "mean_deg" in normal:
        parts.append(f"normal error mean {normal['mean_deg']:.2f}° median {normal['median_deg']:.2f}° vs ground truth")
    depth = metrics.get("depth", {})
    if "rmse" in depth:
        parts.append(f"depth RMSE {depth['rmse']:.3g} ({100 * depth['relative']:.2f} % of range, scale/offset aligned)")
    nearfield = params.get("nearfield") or {}
    if nearfield.get("enabled"):
        how = "estimated from the shading" if nearfield["depth_estimated"] else "integration.reference_depth_m"
        absolute = metrics.get("depth_absolute", {})
        error = (f", {100 * absolute['relative_to_distance']:.2f} % of the distance vs ground truth"
                 if "rmse" in absolute else "")
        parts.append(f"near-field: object at {nearfield['median_depth_m']:.4g} m ({how}{error}; "
                     f"{len(nearfield['iterations'])} rounds)")
    warned_part = _warnings_part(list(warned or []))
    if warned_part:
        parts.append(warned_part)
    parts.append(f"{total_s:.1f} s")
    return "; ".join(parts)


def _material_fixed(config: RunConfig) -> bool:
    """Whether ``recovery.material`` fixes the material (nothing fitted: no parameter-bound check)."""
    return config.recovery.material is not None and config.recovery.material_use == "fixed"


def _strict_failure(params: dict[str, Any], out: Path) -> SelfCheckError | None:
    """``--strict``: the error naming the self-check warnings of ``params["checks"]`` (None without any)."""
    found = (params.get("checks") or {}).get("warnings") or []
    if not found:
        return None
    names = ", ".join(dict.fromkeys(w["name"] for w in found))
    return SelfCheckError(f"self-check failed: {names}: {found[0]['message']} (result kept in {out})")


def _capture_source(capture: Capture, config: RunConfig, work: Path, out: Path) -> str:
    """Where the capture is: its folder, the result's ``capture/`` (not the temporary folder it is
    written in), or what it was when it was not saved."""
    if capture.root is None:
        return f"{config.input.type} (not saved)"
    root = Path(capture.root).absolute()
    if root.is_relative_to(work):
        return str(out / root.relative_to(work))
    return str(root)


def _material_record(config: RunConfig, result: NormalsResult) -> dict[str, Any] | None:
    """params.json's ``material``: the known material's file, use and parameters (None without one)."""
    options = config.recovery
    if options.material is None:
        return None
    material = load_material(options.material)
    return {"file": options.material, "use": options.material_use, "model": material.model,
            "parameters": dict(material.parameters), "applied": result.model == "fmbrdf"}


def _colour_capture_record(capture: Capture) -> dict[str, Any]:
    """params.json's ``capture.bayer`` (``camera.mosaic.bayer``) for a colour capture; nothing for mono."""
    bayer = capture.spec.camera.mosaic.bayer
    return {} if bayer is None else {"bayer": bayer}


def _mark_albedo_edges(result: NormalsResult, inputs: RecoveryInputs) -> NormalsResult:
    """The pixels on an albedo step (preprocessing left their observations out: polarshape.recover.edges)
    join the material edges' ``mixed`` (mixed.png, params.json's ``mixed_pixels``)."""
    if inputs.albedo_edges is None or result.materials is None:
        return result
    edges = inputs.albedo_edges.to(result.mask.device) & result.mask
    return dataclasses.replace(result, mixed=edges if result.mixed is None else result.mixed | edges)


def _materials_record(result: NormalsResult) -> dict[str, Any]:
    """params.json's ``materials`` (every material's parameters and pixel count; ``params`` is the
    one with the most pixels), ``material_selection`` (the splits tried) and ``mixed_pixels``."""
    if result.materials is None:
        return {}
    return {
        "materials": [{**p, "pixels": int((result.materials == m).sum())} for m, p in enumerate(result.material_params)],
        "material_selection": result.material_selection,
        "mixed_pixels": None if result.mixed is None else int(result.mixed.sum()),
    }


def _params(config: RunConfig, capture: Capture, inputs: RecoveryInputs, result: NormalsResult, surface: Surface,
            mesh_info: dict[str, Any], metrics: dict[str, Any], device: str, work: Path, out: Path) -> dict[str, Any]:
    """The content of params.json (format :data:`polarshape.io.results.RESULT_FORMAT`)."""
    if config.mesh.poisson and "poisson" in mesh_info:  # open3d's verdict on the written file
        metrics["mesh_poisson_watertight"] = mesh_info["poisson"]["watertight"]
    pixel_size = getattr(surface.camera, "pixel_size_m", None)
    return {
        "format": RESULT_FORMAT,
        "polarshape_version": __version__,
        "model": result.model,
        "params": dict(result.params),
        "losses": {"final": result.history[-1] if result.history else None, "history": result.history},
        "metrics": metrics,
        "recovery_timings_s": {str(k): float(v) for k, v in result.timings.items()},
        "recovery_counts": {str(k): int(v) for k, v in result.counts.items()},
        "material": _material_record(config, result),
        **_materials_record(result),
        "capture": {
            "source": _capture_source(capture, config, work, out),
            "input_type": config.input.type,
            "lights": capture.num_lights,
            "superpixels_hw": list(inputs.shape),
            "projection": surface.camera.projection,
            "mask_pixels": int(result.mask.sum()),
            "filled_pixels": None if result.filled is None else int(result.filled.sum()),
            "has_polarisation": bool(inputs.has_polarisation),
            "polarimetric_calibration": polarimetric_calibration_record(capture),
            **_colour_capture_record(capture),
        },
        **({} if result.albedo_rgb is None else {"colour": colour_albedo_summary(result.albedo_rgb, result.mask)}),
        "integration": {
            "method": config.integration.method, "pixel_size_m": pixel_size, "solver": surface.report.solver,
            "components": surface.report.components, "iterations": surface.report.iterations,
        },
        "mesh": mesh_info,
        "initial_normals": {"valid_pixels": int(result.initial_valid.sum())},
        "normal_map_convention": config.export.normal_convention,
        "device": device,
        "dtype": config.dtype,
    }


def _report(work: Path, config: RunConfig, inputs: RecoveryInputs, result: NormalsResult, params: dict[str, Any],
            error_map: np.ndarray | None, log: _StageLog, surface: Surface, capture: Capture, *,
            validation: Validation | None = None) -> ReportData | None:
    """Write the report; returns what it showed (None when disabled), for :func:`rewrite_report_page`."""
    if not config.report.enabled:
        log.skip("report", "report.enabled is false")
        return None
    data = ReportData(
        normals=to_numpy(result.normals), albedo=to_numpy(result.albedo), mask=to_numpy(result.mask),
        albedo_rgb=None if result.albedo_rgb is None else to_numpy(result.albedo_rgb),
        observed=to_numpy(result.observed), rendered=to_numpy(result.rendered), lights=to_numpy(inputs.lights),
        irradiance=to_numpy(inputs.irradiance), view=to_numpy(inputs.view), valid=to_numpy(inputs.valid),
        params=params, error_map=error_map, seed=config.seed, max_curve_pixels=config.report.max_curve_pixels,
        depth=surface.depth, truth=material_truth(capture.ground_truth.get("scene")),
        **_holdout_fields(validation),
    )
    params["report"] = [f.name for f in write_report(work, data, fmt=config.report.format)]
    return data


# --- the run -----------------------------------------------------------------------------------


def run_pipeline(
    config: RunConfig,
    out_dir: str | os.PathLike[str] | None = None,
    *,
    overwrite: bool = False,
    config_path: str | os.PathLike[str] | None = None,
    log_file: str | None = None,
    strict: bool = False,
) -> PipelineResult:
    """Run every stage and write the result folder atomically (module docstring: stages and files).

    Args:
        config: the validated run configuration.
        out_dir: the result folder (default ``config.output``).
        overwrite: replace an existing result folder (never an input capture).
        config_path: the configuration file, protected from being overwritten.
        log_file: a file name (e.g. ``run.log``) inside the result folder that receives this run's
            records of the ``polarshape`` logger at INFO and above (as far as its level lets them
            through); written in the temporary folder, so it is part of the atomic result.
        strict: a self-check warning (params.json ``checks``) becomes a :class:`SelfCheckError`, raised
            after the result folder is complete (it is kept: the user wants to look at it).

    Returns:
        :class:`PipelineResult` (folder, one-line summary, params.json content).

    Raises:
        ConfigError: no output folder.
        DeviceError: ``device: cuda`` without a GPU (checked before anything is read or written).
        OutputExistsError: the folder exists and ``overwrite`` is False; or it is, holds or lies inside
            an input; or it exists and is not a polarshape result (``overwrite`` replaces results only).
        PipelineError, CaptureError, ValueError: a stage cannot run (message names the fix).
        SelfCheckError: ``strict`` and a self-check warned (the result folder is written).
    """
    t_start = time.perf_counter()
    target = out_dir if out_dir is not None else config.output
    if target is None:
        raise ConfigError("output: no result folder; pass --out DIR or set output: in the config")
    out = Path(target).absolute()
    device = str(resolve_device(config.device, "device"))
    torch.manual_seed(config.seed)
    inputs_paths = [config.input.path, config.input.scene, config.input.session, config.recovery.material,
                    config_path]
    log = _StageLog(config.progress, device)
    try:
        refusal = lambda p: output_refusal(p, inputs_paths, overwrite=overwrite)  # noqa: E731
        with atomic_directory(out, overwrite=overwrite, protect=refusal) as work, _recorded_warnings() as warned, \
                _logged_to(work / log_file if log_file else None):
            params = _run_stages(config, work, out, device, log, t_start, warned)
    finally:
        log.close()
    logger.info("result written to %s (%.1f s)", out, params["timings_s"]["total"])
    failure = _strict_failure(params, out) if strict else None
    if failure is not None:
        raise failure
    return PipelineResult(out_dir=out, summary=params["summary"], params=params)


@contextlib.contextmanager
def _logged_to(path: Path | None) -> Iterator[None]:
    """While inside, the ``polarshape`` logger's records at INFO and above also go to ``path`` (None: nowhere)."""
    if path is None:
        yield
        return
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    package = logging.getLogger("polarshape")
    package.addHandler(handler)
    try:
        yield
    finally:
        package.removeHandler(handler)
        handler.close()


@contextlib.contextmanager
def _recorded_warnings() -> Iterator[list[str]]:
    """Collect the text of every :class:`~polarshape.errors.PolarshapeWarning` issued inside, each
    still shown as usual (params.json records them: a result says what looked wrong in its input)."""
    warned: list[str] = []
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def record(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> None:
            if issubclass(category, PolarshapeWarning):
                warned.append(f"{category.__name__}: {message}")
            shown(message, category, *args, **kwargs)

        warnings.simplefilter("always", PolarshapeWarning)  # once per run, not once per process
        warnings.showwarning = record
        yield warned


def _run_stages(config: RunConfig, work: Path, out: Path, device: str, log: _StageLog, t_start: float,
                warned: list[str]) -> dict[str, Any]:
    dtype = torch.float64 if config.dtype == "float64" else torch.float32
    with log.stage("input"):
        capture = acquire(config, work, device)
    with log.stage("preprocess"):
        inputs, camera = preprocess(capture, config, log, device=device, dtype=dtype)
    with log.stage("recovery"):
        recovery = _first_recovery(capture, config, log)
        result = recover_normals(inputs, recovery, config.initial_normals, seed=config.seed, progress=config.progress)
        for item in result.skipped if recovery is config.recovery else ():  # else: the nearfield stage's fit's
            log.skip("recovery", item)
    with log.stage("nearfield"):
        inputs, result, nearfield = near_field(capture, inputs, result, camera, config, log)
    integrated: dict[str, Any] = {}
    with log.stage("interreflection"):
        inputs, result, bounce_record, bounce_map = interreflection(inputs, result, camera, capture, config, log,
                                                                    nearfield, integrated=integrated)
    with log.stage("validation"):
        result, validation = validate(inputs, result, config, log)
    with log.stage("checks"):
        checks = run_self_checks(capture, inputs, result, validation.as_dict() if validation.ran else None,
                                 earlier=list(warned), fitted_material=not _material_fixed(config))
    result = _mark_albedo_edges(result, inputs)
    with log.stage("integration"):
        surface = _integrated_surface(result, camera, config, nearfield, integrated)
    with log.stage("mesh"):
        mesh_info = build_meshes(work, result, surface, config, log)
    with log.stage("export"):
        for item in write_maps(work, normals=to_numpy(result.normals), mask=to_numpy(result.mask),
                               depth=surface.depth, albedo=albedo_map(result),
                               filled=None if result.filled is None else to_numpy(result.filled),
                               normal_convention=config.export.normal_convention, exr=config.export.exr):
            log.skip("export", item)
        if bounce_map is not None:  # the largest share of each pixel's light that came off the object itself
            write_npy(to_numpy(bounce_map).astype(np.float32), work / "interreflection.npy")
        if result.materials is not None:
            write_material_maps(work, materials=to_numpy(result.materials),
                                mixed=None if result.mixed is None else to_numpy(result.mixed))
        atomic_write_text(work / "config.yaml", yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    with log.stage("evaluation"):
        metrics, error_map = evaluate(capture, result, surface, log)
        if error_map is not None:
            write_npy(error_map.astype(np.float32), work / "error_map.npy")
    params = _params(config, capture, inputs, result, surface, mesh_info, metrics, device, work, out)
    params["validation"] = validation.as_dict()
    params["interreflection"] = bounce_record
    params["checks"] = checks.as_dict()
    params["nearfield"] = nearfield.as_dict() if nearfield is not None else {"enabled": False}
    params["summary"] = _summary_line(out, result, metrics, time.perf_counter() - t_start, params=params,
                                      has_polarisation=inputs.has_polarisation, warned=warned)
    with log.stage("report"):
        report_data = _report(work, config, inputs, result, params, error_map, log, surface, capture,
                              validation=validation)
    total = time.perf_counter() - t_start
    params.update(timings_s={**log.timings, "total": total}, skipped=log.skipped, warnings=list(warned),
                  summary=_summary_line(out, result, metrics, total, params=params,
                                        has_polarisation=inputs.has_polarisation, warned=warned))
    if report_data is not None and config.report.format == "html":  # the page again, with the final timings
        rewrite_report_page(work, report_data)
    return write_params(work, params)
