"""Self-checks of a finished recovery: does the answer fit the photographs as well as the noise allows,
and if not, which input slip explains it? Each check issues a named warning
(:mod:`polarshape.errors`) and records what it measured (``params.json`` ``checks``):

- **fit residual** (:class:`~polarshape.errors.FitResidualWarning`): per observation
  χ² = r² / σ² of s0 (and of s1, s2 where the FMBRDF fitted polarisation, with their own σ) over the
  usable observations of the mask, σ from the capture's noise model
  (:class:`polarshape.recover.noise.NoiseModel`). ``residual_to_noise`` = √(median χ² / 0.455)
  (0.455 is the median of χ²₁: 1 = at the noise) over observations whose 3×3 neighbourhood is usable
  too (:func:`_interior`): a few bad pixels (cast-shadow edges, a silhouette) do not move it, a wrong
  input moves every pixel. The RMS version √(mean χ²) is recorded beside it. Measured (32²
  super-pixel sphere, 8 lights unless said; ``tests/test_selfcheck.py``): clean 0.91 (4 lights 0.79,
  12 lights 0.91, 64² 0.92, perspective blob at 48² 0.94, checkered sphere at 64² 1.5); light y or
  x flipped 3.44, ``mosaic.angles`` reversed 3.44, frames shuffled 5.5 (12 lights: 3.47, 5.53) →
  :data:`RESIDUAL_RATIO_MAX` = 2. Not clean enough to pass: a 3-pixel checker at 32² (7.3: finer
  than the demosaic resolves), the textured scene's point lights placed from the default
  ``integration.reference_depth_m`` 1 m while the object is at 0.5 m (7.6: wrong light directions —
  36° normal error). A Lambertian fit leaves gloss unexplained
  (glossy sphere 3.2, shuffled 40.7; flips fit s0 exactly — the convention check sees them):
  :data:`RESIDUAL_RATIO_MAX_LAMBERTIAN` = 8.
- **convention** (:class:`~polarshape.errors.ConventionWarning`): the AoLP against the azimuth φ of
  the photometric-stereo normals (intensity only, so independent of the polarisation). Diffuse
  polarisation is parallel to φ, specular perpendicular (spec §1, §5): both agree with φ modulo
  π/2, so the score is the signal-weighted mean of cos 4(AoLP − φ) (clean 0.80–0.83); a mirrored
  relation AoLP = −φ scores with cos 4(AoLP + φ) (clean ≈ 0, y/x flip and reversed angles 0.80).
  A light-axis flip also mirrors the PS normals, so at the silhouette they point inward along that
  axis, while reversed ``mosaic.angles`` leave them outward: the boundary scores tell the three
  apart (x and y both flipped keep AoLP = φ but turn every boundary normal inward).
  A flipped z is refused before recovery (a light behind the object,
  :func:`polarshape.recover.diagnose.check_observations`, "flip the sign of z").
- **frame order** (:class:`~polarshape.errors.FrameOrderWarning`): Lambertian s0 = B Lᵀ is rank 3,
  so the (K,) columns of the true light matrix lie in the span of the three leading left singular
  vectors of s0 over pixels lit in every frame, whatever the albedo and normals (a linear ambiguity
  leaves that span alone; so do axis flips). The residual of projecting the declared lights onto it:
  clean 0.005, shuffled 0.47–0.51; a swap search finds the order that fits (0.005).
- **parameter bounds** (:class:`~polarshape.errors.ParameterBoundWarning`): ior, α, β, κ within 1 %
  of :data:`polarshape.recover.reflectometry.BOUNDS` (α, β on the log scale the solver uses; κ = 0
  is the default, not a bound), k_s = 0.
- **clipped lobe** (:class:`~polarshape.errors.ClippedLobeWarning`, :func:`clipped_lobe`): per light,
  the observation nearest the mirror direction of the fitted normals (where the fitted lobe peaks) is
  saturated (in every exposure, with brackets), under at least :data:`CLIPPED_CORE_FRACTION` of the
  ≥ :data:`LOBE_CORE_MIN_LIGHTS` lights whose lobe core (half vector within max(atan α,
  :data:`LOBE_CORE_MIN_DEG`) of the normal; the floor keeps a core when α sits at its lower bound)
  falls on the object: α, β and k_s are then fitted to the lobe's flanks only. Measured
  (``benchmarks/hdr_brackets.py``, a sphere α = 0.03 peaking ≈ 64× full scale, 10 lights): one
  exposure, the peak clipped under 10 of 10 lights (bilinear and super-pixel demosaic); bracketed
  ×1, ×1/8, ×1/64: under none.
- **filled / frozen pixels** (:class:`~polarshape.errors.FilledPixelsWarning`,
  :class:`~polarshape.errors.FrozenPixelsWarning`): more than :data:`FILLED_FRACTION_MAX` of the mask
  filled from neighbours; more than :data:`FROZEN_FRACTION_MAX` of the FMBRDF normals within 0.05°
  of their PS start.
- **model evidence** (:class:`~polarshape.errors.ModelEvidenceWarning`): the held-out s0 error of the
  Lambertian model below the FMBRDF's (params.json ``validation``).
- **bit depth** (:class:`~polarshape.errors.BitDepthWarning`): issued while loading and
  preprocessing (:func:`polarshape.recover.diagnose.check_observations`, the capture loader); passed
  in as ``earlier`` warnings, they are listed here without being issued twice.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.errors import (
    BitDepthWarning,
    ClippedLobeWarning,
    ConventionWarning,
    FilledPixelsWarning,
    FitResidualWarning,
    FrameOrderWarning,
    FrozenPixelsWarning,
    ModelEvidenceWarning,
    ParameterBoundWarning,
    PolarshapeWarning,
)
from polarshape.imaging.stokes import aolp, dolp
from polarshape.io.capture import Capture
from polarshape.recover.noise import NoiseModel, noise_or_constant
from polarshape.recover.observations import RecoveryInputs
from polarshape.recover.reflectometry import BOUNDS

logger = logging.getLogger(__name__)

__all__ = [
    "CHECK_WARNINGS", "CLIPPED_CORE_FRACTION", "FILLED_FRACTION_MAX", "LOBE_CORE_MIN_DEG", "LOBE_CORE_MIN_LIGHTS", "FROZEN_FRACTION_MAX", "RESIDUAL_RATIO_MAX", "RecoveryResult",
    "SelfChecks", "clipped_lobe", "convention_scores", "frame_order", "parameters_at_bounds", "residual_to_noise", "run_self_checks",
]

#: residual_to_noise above this: FitResidualWarning (clean ≤ 1.12 measured, failures ≥ 3.7; module docstring).
RESIDUAL_RATIO_MAX = 2.0
#: The same for a Lambertian fit, which leaves any gloss unexplained (glossy sphere 3.2, shuffled frames 40.7).
RESIDUAL_RATIO_MAX_LAMBERTIAN = 8.0
#: Mirrored AoLP score must beat the direct one by this much (and exceed it as a score) to warn.
CONVENTION_MARGIN = 0.3
#: Boundary normals pointing inward: a boundary score below minus this.
BOUNDARY_INWARD = 0.2
#: Frame order: the declared lights' projection residual above this and above this many times the best order's.
FRAME_ORDER_RESIDUAL_MIN = 0.05
FRAME_ORDER_RATIO = 3.0
#: More of the mask than this filled from neighbours: FilledPixelsWarning.
FILLED_FRACTION_MAX = 0.2
#: More of the FMBRDF normals than this still at their PS start (within 0.05°): FrozenPixelsWarning.
FROZEN_FRACTION_MAX = 0.5
#: Lambertian held-out s0 error below the FMBRDF's by more than this fraction: ModelEvidenceWarning.
MODEL_EVIDENCE_MARGIN = 0.05
#: The lobe's core: half vectors within max(atan α, this) degrees of the normal.
LOBE_CORE_MIN_DEG = 2.0
#: Fewer lights showing the lobe's core on the object than this: nothing to judge (no warning).
LOBE_CORE_MIN_LIGHTS = 2
#: The lobe's peak saturated under at least this fraction of the lights showing it: ClippedLobeWarning.
CLIPPED_CORE_FRACTION = 0.9
_BOUND_TOLERANCE = 0.01
_CHI2_1_MEDIAN = 0.454936  # median of a χ² variable with one degree of freedom

#: The warning classes the self-checks issue (and the ones issued earlier that they list).
CHECK_WARNINGS: tuple[type[PolarshapeWarning], ...] = (
    FitResidualWarning, ConventionWarning, FrameOrderWarning, BitDepthWarning, ParameterBoundWarning,
    ClippedLobeWarning, FilledPixelsWarning, FrozenPixelsWarning, ModelEvidenceWarning,
)


class RecoveryResult(Protocol):
    """What the checks read of :class:`polarshape.normals.NormalsResult` (a later stage: not imported)."""

    normals: Tensor  # (H, W, 3)
    params: dict[str, float]
    model: str
    mask: Tensor  # (H, W) bool
    rendered: Tensor  # (K, 3, H, W)
    observed: Tensor  # (K, 3, H, W)
    initial_normals: Tensor  # (H, W, 3)
    initial_valid: Tensor  # (H, W) bool
    filled: Tensor | None  # (H, W) bool


@dataclass
class SelfChecks:
    """The outcome of :func:`run_self_checks`.

    Attributes:
        warnings: (name, message) of every self-check warning, in the order issued.
        measured: what each check measured (see :meth:`as_dict`).
    """

    warnings: list[tuple[str, str]] = field(default_factory=list)
    measured: dict[str, Any] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.warnings]

    def as_dict(self) -> dict[str, Any]:
        """params.json's ``checks``: ``warnings`` [{name, message}], ``residual_to_noise`` (robust χ² ratio,
        1 = at the noise), ``residual_to_noise_rms``, ``noise`` (the model used), ``convention``,
        ``frame_order``, ``bounds``, ``clipped_lobe``, ``filled_fraction``, ``frozen_fraction``, ``model_evidence``, ``seconds``."""
        return {"warnings": [{"name": n, "message": m} for n, m in self.warnings], **self.measured}

    def _warn(self, kind: type[PolarshapeWarning], message: str) -> None:
        self.warnings.append((kind.__name__, message))
        logger.info("self-check %s: %s", kind.__name__, message)  # run.log
        warnings.warn(kind(message), stacklevel=3)


# --- fit residual ------------------------------------------------------------------------------


def _noise_of(inputs: RecoveryInputs) -> NoiseModel:
    return noise_or_constant(inputs.noise, inputs.noise_std)


def _interior(usable: Tensor) -> Tensor:
    """(K, H, W) usable observations whose 3×3 neighbours are usable too: the demosaic's stencil
    reaches one block further, so the neighbours of an edge block (texture step, silhouette, cast
    shadow; flagged mixed or dark) carry interpolation errors no noise model has (a 3-pixel checker
    at 32²: residual 9× the noise on all observations, 1.3× on these)."""
    rows = usable.clone()  # the 3×3 minimum, separably (a row's three, then a column's); the border has fewer
    rows[..., 1:] &= usable[..., :-1]
    rows[..., :-1] &= usable[..., 1:]
    out = rows.clone()
    out[..., 1:, :] &= rows[..., :-1, :]
    out[..., :-1, :] &= rows[..., 1:, :]
    return out


def _at(x: Tensor, where: Tensor) -> Tensor:
    """``x[..., where]`` (*, N) of x (*, H, W) at the pixels ``where`` (H, W) bool, on the CPU (through numpy:
    several times faster than torch's boolean indexing there), in x's dtype."""
    x = x.detach().cpu().contiguous()
    flat = x.numpy().reshape(*x.shape[:-2], -1)  # (*, H·W)
    return torch.from_numpy(flat.compress(where.cpu().numpy().ravel(), axis=-1))


def _lower_median(v: Tensor) -> float:
    """``float(v.median())`` of a 1-D CPU tensor (the lower middle value for an even count), by a numpy partition."""
    k = (v.numel() - 1) // 2
    return float(np.partition(v.numpy(), k)[k])


def residual_to_noise(inputs: RecoveryInputs, result: RecoveryResult) -> tuple[float, float, int]:
    """(robust ratio √(median χ² / 0.455), RMS ratio √(mean χ²), number of χ² terms) of the fit.

    s0 always; s1 and s2 too when the inputs are polarised and the FMBRDF was fitted (an
    intensity-only or Lambertian fit predicts no polarisation). NaN ratios without observations.
    """
    noise = _noise_of(inputs)
    use = _interior(inputs.valid & inputs.mask.unsqueeze(0)).cpu()  # (K, H, W)
    polarised = inputs.has_polarisation and result.model == "fmbrdf"
    chi: list[Tensor] = []
    for k in range(inputs.num_lights):  # one light at a time, its usable pixels only: (3, N) float64
        obs = _at(result.observed[k], use[k]).to(torch.float64)  # (3, N)
        pred = _at(result.rendered[k], use[k]).to(torch.float64)
        s0 = obs[0]
        chi.append(((pred[0] - s0) / noise.std(s0)).pow(2).to(torch.float32))
        if polarised:
            sigma = noise.linear_std(s0)
            chi += [((pred[c] - obs[c]) / sigma).pow(2).to(torch.float32) for c in (1, 2)]
    chi2 = torch.cat(chi).to(torch.float64)
    chi2 = chi2[torch.isfinite(chi2)]
    if chi2.numel() == 0:
        return math.nan, math.nan, 0
    return (math.sqrt(_lower_median(chi2) / _CHI2_1_MEDIAN), float(chi2.mean().sqrt()), int(chi2.numel()))


def _check_residual(checks: SelfChecks, inputs: RecoveryInputs, result: RecoveryResult) -> None:
    robust, rms, n = residual_to_noise(inputs, result)
    noise = _noise_of(inputs)
    checks.measured.update(residual_to_noise=robust, residual_to_noise_rms=rms, residual_terms=n,
                           noise={"read_var": noise.read_var, "shot_gain": noise.shot_gain, "source": noise.source})
    limit = RESIDUAL_RATIO_MAX if result.model == "fmbrdf" else RESIDUAL_RATIO_MAX_LAMBERTIAN
    checks.measured["residual_to_noise_max"] = limit
    if math.isfinite(robust) and robust > limit:
        what = "s0, s1, s2" if inputs.has_polarisation and result.model == "fmbrdf" else "s0"
        checks._warn(FitResidualWarning, (
            f"fit residual {robust:.1f}× the noise (typical χ² of {n} observations of {what} against the noise "
            f"model from {noise.source}; ≤ {limit:g} expected for model {result.model}): check light directions, "
            "frame order, bit depth"))


# --- convention ----------------------------------------------------------------------------------


def _boundary_scores(mask: Tensor, normals: Tensor, ok: Tensor) -> tuple[float, float, int]:
    """How well the normals (H, W, 3) near the silhouette of ``mask`` (H, W) point outward along x and
    along y: Σ n_x o_x / Σ |n_x||o_x| (o the outward direction, −∇ of the 5×5-blurred mask; the frame
    edge is no silhouette) over boundary pixels with ``ok``; (NaN, NaN, 0) without any."""
    m = mask.to(torch.float64)[None, None]
    blurred = F.avg_pool2d(F.pad(m, (2, 2, 2, 2), mode="replicate"), 5, stride=1)[0, 0]  # (H, W)
    gy, gx = torch.gradient(blurred)
    boundary = mask & ok & (blurred < 0.999) & ((gx.abs() + gy.abs()) > 0)
    if int(boundary.sum()) < 8:
        return math.nan, math.nan, int(boundary.sum())
    n = normals.to(torch.float64)[boundary]  # (B, 3)
    ox, oy = -gx[boundary], -gy[boundary]
    bx = float((n[:, 0] * ox).sum() / (n[:, 0].abs() * ox.abs()).sum().clamp_min(1e-12))
    by = float((n[:, 1] * oy).sum() / (n[:, 1].abs() * oy.abs()).sum().clamp_min(1e-12))
    return bx, by, int(boundary.sum())


def convention_scores(inputs: RecoveryInputs, normals: Tensor, ok: Tensor) -> dict[str, float]:
    """Agreement of the observed AoLP with the azimuth φ of ``normals`` (H, W, 3) at pixels ``ok`` (H, W).

    Returns:
        ``direct`` = weighted mean cos 4(AoLP − φ), ``mirrored`` = cos 4(AoLP + φ) (weights s0 · DoLP over
        usable observations whose normal is ≥ 0.3 off the view axis), ``boundary_x``, ``boundary_y``
        (:func:`_boundary_scores`: +1 all outward, −1 all inward), ``pixels`` used.
    """
    n = normals.detach().cpu().to(torch.float64)
    ok = ok.cpu() & torch.isfinite(n).all(-1) & inputs.mask.cpu()
    phi = torch.atan2(n[..., 1], n[..., 0])  # (H, W)
    ok = ok & (n[..., :2].norm(dim=-1) > 0.3)
    bx, by, nb = _boundary_scores(inputs.mask.cpu(), n, ok)
    out = {"direct": math.nan, "mirrored": math.nan, "boundary_x": bx, "boundary_y": by,
           "boundary_pixels": nb, "pixels": 0}
    total, direct, mirrored, seen = 0.0, 0.0, 0.0, torch.zeros_like(ok)
    for k in range(inputs.num_lights):  # one light at a time
        use = inputs.valid[k].cpu() & ok  # (H, W)
        s = _at(inputs.stokes[k], use).to(torch.float64)  # (3, P)
        angle, p = aolp(s, dim=0), _at(phi, use)
        weight = dolp(s, dim=0, eps=1e-6) * s[0].clamp_min(0.0)
        total += float(weight.sum())
        direct += float((torch.cos(4 * (angle - p)) * weight).sum())
        mirrored += float((torch.cos(4 * (angle + p)) * weight).sum())
        seen |= use
    out["pixels"] = int(seen.sum())
    if total > 0:
        out["direct"], out["mirrored"] = direct / total, mirrored / total
    return out


def _other_angles(capture: Capture) -> str:
    current = capture.spec.camera.mosaic.angles
    return "counterclockwise_on_screen" if current == "clockwise_on_screen" else "clockwise_on_screen"


def _check_convention(checks: SelfChecks, capture: Capture, inputs: RecoveryInputs, result: RecoveryResult) -> None:
    if not inputs.has_polarisation:
        checks.measured["convention"] = {"skipped": "no polarisation above the noise"}
        return
    scores = convention_scores(inputs, result.initial_normals, result.initial_valid)
    checks.measured["convention"] = scores
    direct, mirrored, bx, by = scores["direct"], scores["mirrored"], scores["boundary_x"], scores["boundary_y"]
    if not (math.isfinite(direct) and math.isfinite(mirrored)):
        return
    inward_x, inward_y = bx < -BOUNDARY_INWARD, by < -BOUNDARY_INWARD  # NaN compares False
    outward_x, outward_y = bx > BOUNDARY_INWARD, by > BOUNDARY_INWARD
    angles = f"camera.mosaic.angles: {_other_angles(capture)}"
    head = (f"the polarisation azimuth (AoLP) is mirrored against the azimuth of the photometric normals "
            f"(agreement {mirrored:.2f} mirrored vs {direct:.2f} as declared)")
    if mirrored > direct + CONVENTION_MARGIN and mirrored > CONVENTION_MARGIN:
        if inward_y and outward_x:
            fix = ("the light directions' y axis looks flipped (the normals point inward at the top and bottom of "
                   "the silhouette): negate y of every lights[*].direction in capture.yaml (y points down)")
        elif inward_x and outward_y:
            fix = ("the light directions' x axis looks flipped (the normals point inward at the left and right of "
                   "the silhouette): negate x of every lights[*].direction in capture.yaml (x points right)")
        elif outward_x and outward_y:
            fix = (f"the normals point outward, so the polariser angles look reversed: set {angles} (now "
                   f"{capture.spec.camera.mosaic.angles})")
        else:
            fix = (f"negate y (or x) of every lights[*].direction in capture.yaml, or set {angles}; the silhouette "
                   "does not tell which")
        checks._warn(ConventionWarning, f"{head}: {fix}")
    elif direct > CONVENTION_MARGIN and inward_x and inward_y:
        checks._warn(ConventionWarning, (
            "the photometric normals point inward all around the silhouette: x and y of the light directions look "
            "both flipped (negate x and y of every lights[*].direction in capture.yaml) — unless the object is "
            "concave"))


# --- frame order ---------------------------------------------------------------------------------


def _projection_residual(basis: np.ndarray, lights: np.ndarray) -> float:
    """‖(I − U Uᵀ) D‖ / ‖D‖ of lights D (K, 3) against an orthonormal basis U (K, 3)."""
    r = lights - basis @ (basis.T @ lights)
    return float(np.linalg.norm(r) / max(np.linalg.norm(lights), 1e-300))


def _best_order(basis: np.ndarray, lights: np.ndarray, restarts: int, rng: np.random.Generator) -> tuple[list[int], float]:
    """The order o (frame i ↔ lights[o[i]]) with the smallest projection residual: swap descent from the
    declared order and from ``restarts`` random ones."""
    k = len(lights)
    best_order, best = list(range(k)), _projection_residual(basis, lights)
    starts = [list(range(k))] + [list(rng.permutation(k)) for _ in range(restarts)]
    for order in starts:
        r = _projection_residual(basis, lights[order])
        improved = True
        while improved:
            improved = False
            for i in range(k):
                for j in range(i + 1, k):
                    trial = order.copy()
                    trial[i], trial[j] = trial[j], trial[i]
                    rt = _projection_residual(basis, lights[trial])
                    if rt < r - 1e-12:
                        order, r, improved = trial, rt, True
        if r < best - 1e-12:
            best_order, best = [int(o) for o in order], r
    return best_order, best


def frame_order(inputs: RecoveryInputs, *, restarts: int = 20, seed: int = 0) -> dict[str, Any]:
    """Whether the frames' s0 fits the declared lights in their order (module docstring).

    Returns:
        ``declared`` and ``best`` projection residuals, ``order`` (frame i looks lit by
        ``lights[order[i]]``), ``pixels`` (lit in every frame); ``skipped`` when too few pixels or lights.
    """
    k = inputs.num_lights
    use = (inputs.valid & inputs.mask.unsqueeze(0)).all(0).cpu()  # (H, W): lit and usable in every frame
    if k < 5 or int(use.sum()) < 16:
        return {"skipped": f"{int(use.sum())} pixels lit in all {k} frames (need ≥ 16, and ≥ 5 lights)"}
    s0 = _at(inputs.stokes[:, 0], use).to(torch.float64).numpy()  # (K, P)
    rows, cols = torch.nonzero(use, as_tuple=True)
    centre = len(rows) // 2  # the lights at one pixel of the region (point lights vary a little across it)
    r, c = int(rows[centre]), int(cols[centre])
    lights = (inputs.lights[:, r, c].detach().cpu().to(torch.float64)
              * inputs.irradiance[:, r, c].detach().cpu().to(torch.float64)[:, None]).numpy()  # (K, 3)
    # the 3 leading left singular vectors of s0, as the eigenvectors of its (K, K) Gram matrix (an SVD of the
    # (K, P) matrix costs ~10× more at a full frame); only their span enters the residuals
    basis = np.linalg.eigh(s0 @ s0.T)[1][:, ::-1][:, :3]  # (K, 3)
    declared = _projection_residual(basis, lights)
    order, best = _best_order(basis, lights, restarts, np.random.default_rng(seed))
    return {"declared": declared, "best": best, "order": order, "pixels": int(use.sum())}


def _check_frame_order(checks: SelfChecks, capture: Capture, inputs: RecoveryInputs) -> None:
    info = frame_order(inputs)
    checks.measured["frame_order"] = info
    if "skipped" in info:
        return
    declared, best, order = info["declared"], info["best"], info["order"]
    if declared > FRAME_ORDER_RESIDUAL_MIN and declared > FRAME_ORDER_RATIO * best:
        names = [light.frame for light in capture.spec.lights]
        moved = [f"frame {i} ({names[i]}) matches lights[{j}]" for i, j in enumerate(order) if i != j]
        listed = "; ".join(moved[:6]) + ("; ..." if len(moved) > 6 else "")
        checks._warn(FrameOrderWarning, (
            f"frames look shuffled: {listed} (the frames' shading fits the declared lights in that order with "
            f"residual {best:.3f}, in the declared order {declared:.3f}): check lights[*].frame in capture.yaml"))


# --- parameters, filled and frozen pixels, model evidence ------------------------------------------


def parameters_at_bounds(params: Mapping[str, float]) -> list[str]:
    """The material parameters of ``params`` (names as :class:`~polarshape.brdf.FMBRDFParams`) at
    the limits of the fit (:data:`polarshape.recover.reflectometry.BOUNDS`; κ = 0 is not one), each
    as "name value (bound b)"; k_s 0 as "k_s 0 (bound 0: no specular lobe)"."""
    out = []
    for name, (lo, hi) in BOUNDS.items():
        value = params.get(name)
        if value is None or not math.isfinite(value):
            continue
        log = name in ("alpha", "beta")
        a, b, v = (math.log(lo), math.log(hi), math.log(max(value, 1e-300))) if log else (lo, hi, value)
        t = (v - a) / (b - a)
        if t >= 1 - _BOUND_TOLERANCE:
            out.append(f"{name} {value:.3g} (bound {hi:g})")
        elif t <= _BOUND_TOLERANCE and name != "kappa":  # κ = 0: random microfacet placement, the default
            out.append(f"{name} {value:.3g} (bound {lo:g})")
    k_s = params.get("k_s")
    if k_s is not None and math.isfinite(k_s) and k_s <= 0:
        out.append("k_s 0 (bound 0: no specular lobe)")
    return out


def _check_bounds(checks: SelfChecks, result: RecoveryResult, fitted_material: bool) -> None:
    if result.model != "fmbrdf" or not fitted_material:
        checks.measured["bounds"] = []
        return
    several = getattr(result, "material_params", None) or []
    if len(several) > 1:  # an object of several materials: every material's bounds
        hits = [f"material {m}: {hit}" for m, p in enumerate(several) for hit in parameters_at_bounds(p)]
    else:
        hits = parameters_at_bounds(result.params)
    checks.measured["bounds"] = hits
    if hits:
        checks._warn(ParameterBoundWarning, (
            f"material parameters at the limits of the fit: {', '.join(hits)}: the FMBRDF cannot explain the data "
            "as given — check light directions, frame order and bit depth (FitResidualWarning), or the material is "
            "outside the model"))


def clipped_lobe(inputs: RecoveryInputs, normals: Tensor, params: Mapping[str, float]) -> dict[str, Any] | None:
    """Where the fitted specular lobe peaks, did the capture see it saturated? (module docstring)

    Per light, the lobe's core is the observations whose half vector is within θ_c = max(atan α,
    :data:`LOBE_CORE_MIN_DEG`) of the fitted normal (in the mask, facing light and camera); a light
    *shows* the core when it has one, and its peak (the observation nearest the mirror direction) is
    clipped when that observation is saturated.

    Args:
        inputs: the recovery's inputs (lights, view, saturated, mask on the full grid).
        normals: (H, W, 3) fitted unit normals.
        params: the fitted material (``alpha``).

    Returns:
        ``{"core_deg", "core_observations", "saturated", "clipped_fraction", "lights_with_core",
        "lights_peak_clipped"}`` (``saturated``, ``clipped_fraction``: of the core observations), or
        None without a finite α.
    """
    alpha = params.get("alpha")
    if alpha is None or not math.isfinite(alpha):
        return None
    n = normals.detach().to("cpu", torch.float64)  # (H, W, 3)
    view = inputs.view.to("cpu", torch.float64)  # (H, W, 3)
    core_deg = max(math.degrees(math.atan(max(alpha, 0.0))), LOBE_CORE_MIN_DEG)
    cos_core = math.cos(math.radians(core_deg))
    visible = inputs.mask.cpu() & torch.isfinite(n).all(-1) & ((view * n).sum(-1) > 0)  # (H, W)
    saturated = inputs.saturated.cpu()
    n_core = n_sat = with_core = peak_clipped = 0
    for k in range(inputs.lights.shape[0]):  # one light at a time: (H, W, 3) float64 temporaries only
        lights = inputs.lights[k].to("cpu", torch.float64)  # (H, W, 3)
        cos_h = (F.normalize(lights + view, dim=-1) * n).sum(-1)  # (H, W) cosine of the half-vector angle
        seen = visible & ((lights * n).sum(-1) > 0)  # (H, W)
        core = seen & (cos_h >= cos_core)
        n_core += int(core.sum())
        n_sat += int((core & saturated[k]).sum())
        if bool(core.any()):
            with_core += 1
            peak = torch.where(seen, cos_h, torch.full_like(cos_h, -2.0)).flatten().argmax()  # nearest the mirror
            peak_clipped += int(saturated[k].flatten()[peak])
    return {"core_deg": core_deg, "core_observations": n_core, "saturated": n_sat,
            "clipped_fraction": n_sat / n_core if n_core else None, "lights_with_core": with_core,
            "lights_peak_clipped": peak_clipped}


def _check_clipped_lobe(checks: SelfChecks, inputs: RecoveryInputs, result: RecoveryResult,
                        fitted_material: bool) -> None:
    if result.model != "fmbrdf" or not fitted_material:
        checks.measured["clipped_lobe"] = None
        return
    lobe = clipped_lobe(inputs, result.normals, result.params)
    checks.measured["clipped_lobe"] = lobe
    if lobe is None or lobe["lights_with_core"] < LOBE_CORE_MIN_LIGHTS:
        return
    if lobe["lights_peak_clipped"] >= CLIPPED_CORE_FRACTION * lobe["lights_with_core"]:
        p = result.params
        checks._warn(ClippedLobeWarning, (
            f"the specular lobe's core is clipped: where the fitted lobe peaks the observation is saturated (in every "
            f"exposure) under {lobe['lights_peak_clipped']} of the {lobe['lights_with_core']} lights that show it "
            f"({lobe['saturated']} of {lobe['core_observations']} observations within {lobe['core_deg']:.1f}° of the "
            f"mirror direction), so the fitted α {p.get('alpha', math.nan):.3g}, β {p.get('beta', math.nan):.3g} and "
            f"k_s {p.get('k_s', math.nan):.3g} are not identified (the fit sees only the lobe's flanks): capture "
            "exposure brackets (exposures_us in the session's capture section or the scene's camera; capture format "
            "2) or expose shorter"))


def _check_pixels(checks: SelfChecks, result: RecoveryResult) -> None:
    mask = result.mask.cpu()
    n_mask = max(int(mask.sum()), 1)
    filled = torch.zeros_like(mask) if result.filled is None else result.filled.cpu() & mask
    frac = int(filled.sum()) / n_mask
    checks.measured["filled_fraction"] = frac
    if frac > FILLED_FRACTION_MAX:
        checks._warn(FilledPixelsWarning, (
            f"{100 * frac:.0f} % of the mask ({int(filled.sum())} of {n_mask} pixels) has too few usable observations "
            "and took its neighbours' normal (filled.png): add lights, fix the exposure (dark or saturated frames) or "
            "tighten the mask"))
    if result.model != "fmbrdf":
        checks.measured["frozen_fraction"] = None
        return
    own = mask & ~filled & result.initial_valid.cpu()
    n, n0 = result.normals.detach().cpu().to(torch.float64), result.initial_normals.detach().cpu().to(torch.float64)
    cos = (n * n0).sum(-1).clamp(-1.0, 1.0)
    frozen = own & (cos > math.cos(math.radians(0.05)))
    frac_frozen = int(frozen.sum()) / max(int(own.sum()), 1)
    checks.measured["frozen_fraction"] = frac_frozen
    if frac_frozen > FROZEN_FRACTION_MAX:
        checks._warn(FrozenPixelsWarning, (
            f"{100 * frac_frozen:.0f} % of the FMBRDF normals did not move from their photometric-stereo start "
            "(within 0.05°): the joint fit did not refine them — check recovery.max_outer_iterations and a fixed "
            "recovery.material"))


def _check_model_evidence(checks: SelfChecks, result: RecoveryResult, validation: Mapping[str, Any] | None) -> None:
    models = (validation or {}).get("models") or {}
    fm = (models.get("fmbrdf") or {}).get("s0_rel_rmse")
    lam = (models.get("lambertian") or {}).get("s0_rel_rmse")
    if fm is None or lam is None or not (math.isfinite(fm) and math.isfinite(lam)):
        checks.measured["model_evidence"] = None
        return
    checks.measured["model_evidence"] = {"fmbrdf_s0_rel_rmse": fm, "lambertian_s0_rel_rmse": lam}
    if result.model == "fmbrdf" and lam < (1.0 - MODEL_EVIDENCE_MARGIN) * fm:
        checks._warn(ModelEvidenceWarning, (
            f"on the held-out lights the Lambertian model predicts s0 better than the FMBRDF this run used "
            f"({100 * lam:.1f} % vs {100 * fm:.1f} % relative RMSE): the FMBRDF fit is not trustworthy here — check "
            "the inputs (other warnings) or set recovery.model: lambertian"))


# --- all of them ---------------------------------------------------------------------------------


def run_self_checks(capture: Capture, inputs: RecoveryInputs, result: RecoveryResult,
                    validation: Mapping[str, Any] | None = None, *, earlier: Sequence[str] = (),
                    fitted_material: bool = True) -> SelfChecks:
    """Run every self-check on a finished recovery, issuing each one's named warning (module docstring).

    Args:
        capture: the capture (capture.yaml: frame names, mosaic angles).
        inputs: the recovery's inputs (the full super-pixel grid the result is on).
        result: the recovery (:class:`polarshape.normals.NormalsResult`).
        validation: params.json's ``validation`` (held-out errors per model), or None.
        earlier: warnings already issued in this run as ``"Name: message"`` (e.g. the pipeline's record);
            those of :data:`CHECK_WARNINGS` (the bit-depth warnings of loading) are listed, not re-issued.
        fitted_material: False when the material was fixed by ``recovery.material`` (no bound check).

    Returns:
        :class:`SelfChecks` (``as_dict()`` is params.json's ``checks``).
    """
    t0 = time.perf_counter()
    checks = SelfChecks()
    names = {kind.__name__ for kind in CHECK_WARNINGS}
    for text in earlier:
        name, _, message = text.partition(": ")
        if name in names:
            checks.warnings.append((name, message))
    _check_residual(checks, inputs, result)
    _check_convention(checks, capture, inputs, result)
    _check_frame_order(checks, capture, inputs)
    _check_bounds(checks, result, fitted_material)
    _check_clipped_lobe(checks, inputs, result, fitted_material)
    _check_pixels(checks, result)
    _check_model_evidence(checks, result, validation)
    checks.measured["seconds"] = time.perf_counter() - t0
    logger.info("self-checks: residual %.2f× the noise; %s (%.2f s)", checks.measured.get("residual_to_noise", math.nan),
                ", ".join(checks.names) or "no warnings", checks.measured["seconds"])
    return checks
