"""Exposure brackets (capture format 2) → one radiance mosaic per light, before any Stokes vector.

A light of a format-2 capture holds B frames at exposures t_0 (``frame``, the light's reference
exposure) and t_1 … t_{B−1} (``brackets``). Each raw pixel (site) of frame j gives, in fractions of
full scale of its own frame, x_j = (count − black) / (full − black), an estimate of the radiance in
fractions of full scale **at the reference exposure**:

    y_j = x_j / r_j,   r_j = t_j / t_0.

:func:`merge_exposures` combines them per site with inverse-variance weights:

- a sample is **excluded** when it is clipped (count at the saturation level, less the margin), or
  above :data:`HEADROOM` of full scale while another exposure of the site is below it (near the
  clipping level only the samples whose noise drew them down escape clipping: biased dark), or
  dark (x_j below ``dark_threshold`` of its frame's full scale: mostly read noise and black-level
  error, which 1 / r_j would amplify) — unless it is the longest unclipped exposure of that site;
- the per-site noise is σ²(x) = ``read_var`` + ``gain`` · x in fractions of one frame's full scale
  (:class:`SiteNoise`, measured by :func:`bracket_site_noise` from the four-site redundancy of the
  reference frames), so var(y_j) = (read_var + gain · r_j ŷ) / r_j², evaluated at the estimate ŷ of
  the longest unclipped exposure (not at each sample's own value, which would favour samples that
  happen to read low): w_j = 1 / var(y_j);
- y = Σ w_j y_j / Σ w_j, its variance 1 / Σ w_j;
- a site clipped in **every** exposure keeps the shortest exposure's (clipped) value and is
  flagged ``clipped``: preprocessing marks its observations saturated exactly as for one exposure.

The merged radiance may exceed 1 (a highlight that clips the reference exposure but not a shorter
one). What the noise model downstream sees (:func:`polarshape.recover.noise.estimate_noise`):
preprocessing fits it on the blocks whose four sites were unclipped at the reference exposure, so
it is the reference exposure's noise (slightly lower where shorter exposures added weight);
blocks recovered from a shorter exposure t_j alone are noisier than it says, σ²(y) = read_var / r_j² +
gain · y / r_j (in highlights: a σ up to √(1 / r_j) times the model's at the same y). The test for
mixed blocks (edges) uses each block's own merged variance instead (a z-score), so those noisier
highlight blocks are not mistaken for edges.

:func:`check_bracket_exposures` refuses frames whose brightness ratio contradicts their declared
exposure times (frames of different exposures mixed up).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from polarshape.errors import CaptureError
from polarshape.imaging.mosaic import MosaicLayout, split_mosaic
from polarshape.imaging.pixels import counts_to_float, max_count, reduce_mask_to_superpixels, saturation_count
from polarshape.io.capture import CAPTURE_YAML, Capture
from polarshape.recover.noise import estimate_noise, site_redundancy

logger = logging.getLogger(__name__)

__all__ = [
    "BracketMerger",
    "EXPOSURE_RATIO_TOLERANCE",
    "HEADROOM",
    "MergedBracket",
    "SiteNoise",
    "bracket_site_noise",
    "check_bracket_exposures",
    "clipped_counts",
    "merge_exposures",
    "merge_light",
]

#: Measured / declared brightness ratio of two frames of a light beyond this factor (either way):
#: the frames' exposures are mixed up (a swap of ×8 brackets is off by ×64).
EXPOSURE_RATIO_TOLERANCE = 1.5
#: Samples above this fraction of full scale are used only when no exposure of the site is below it:
#: a value within a few noise σ of the clipping level is kept only when its noise drew it down (the
#: others are clipped), a bias toward dark (measured: β 1.5 instead of 2 on the benchmark sphere
#: without it).
HEADROOM = 0.9
#: Sites used to compare two exposures: above this fraction of full scale in both (no dark noise).
_RATIO_MIN_SIGNAL = 0.01
#: Fewer overlapping sites than this: the pair is not compared.
_RATIO_MIN_SITES = 64


@dataclass(frozen=True)
class SiteNoise:
    """σ² of one raw site's value x (fraction of its frame's full scale) = ``read_var + gain · x``."""

    read_var: float
    gain: float

    def variance(self, x: Tensor) -> Tensor:
        """σ² (same shape) at values ``x`` (negative values count as 0)."""
        return self.read_var + self.gain * x.clamp_min(0.0)


@dataclass(frozen=True)
class MergedBracket:
    """One light's merged mosaic (2H, 2W), fractions of full scale at the reference exposure.

    Attributes:
        radiance: (2H, 2W) float64 merged site values.
        variance: (2H, 2W) float64 their variance (1 / Σ w).
        clipped: (2H, 2W) bool sites clipped in every exposure.
        reference_used: (2H, 2W) bool sites whose reference-exposure sample was used (unclipped).
    """

    radiance: Tensor
    variance: Tensor
    clipped: Tensor
    reference_used: Tensor

    def redundancy_z(self, layout: MosaicLayout, redundancy: Tensor) -> Tensor:
        """(H, W) the four-site redundancy d (:func:`polarshape.recover.noise.site_redundancy` of the
        merged mosaic) over its σ, var(d) = Σ of the four sites' merged variances: the mixed-block
        test's statistic, valid whichever exposure each site came from."""
        var_d = split_mosaic(self.variance, layout).sum(-3)  # (H, W)
        return redundancy / var_d.clamp_min(1e-300).sqrt()


def merge_exposures(values: Tensor, clipped: Tensor, ratios: Tensor, noise: SiteNoise, *,
                    dark_threshold: float) -> MergedBracket:
    """Merge B exposures of one mosaic (module docstring).

    Args:
        values: (B, *) float64 x_j, fractions of full scale of each frame (e.g. (B, 2H, 2W) mosaics).
        clipped: (B, *) bool samples at the saturation level.
        ratios: (B,) float64 r_j = t_j / t_0 (r_0 = 1), all > 0.
        noise: per-site noise of one frame.
        dark_threshold: samples below this fraction of full scale are excluded (except the longest
            unclipped one of a site).

    Returns:
        :class:`MergedBracket` (its maps of shape (*)).
    """
    ones = (1,) * (values.ndim - 1)
    r = ratios.to(values).reshape(-1, *ones)  # (B, 1, …)
    # near the top, the samples that escaped clipping read low (the others clipped): not used when a
    # sample below the headroom is there
    below = ~clipped & (values <= HEADROOM)
    usable = torch.where(below.any(0, keepdim=True), below, ~clipped)
    # the best sample: the longest unclipped exposure; none unclipped: the shortest exposure
    score = torch.where(usable, r.expand_as(values), torch.full_like(values, -math.inf))
    best = score.argmax(0, keepdim=True)  # (1, 2H, 2W)
    none = ~usable.any(0)  # (2H, 2W)
    best = torch.where(none.unsqueeze(0), torch.argmin(ratios).reshape(1, *ones).to(best), best)
    estimates = values / r  # (B, 2H, 2W) y_j
    y_best = estimates.gather(0, best)[0]  # (2H, 2W)
    index = torch.arange(values.shape[0], device=values.device).reshape(-1, *ones)
    keep = usable & ((values >= dark_threshold) | (index == best))
    var = noise.variance(r * y_best.unsqueeze(0)) / (r * r)  # (B, 2H, 2W) var(y_j) at the estimate
    weight = torch.where(keep, 1.0 / var, torch.zeros_like(var))
    total = weight.sum(0)
    merged = (weight * estimates).sum(0) / total.clamp_min(1e-300)
    merged = torch.where(none, y_best, merged)
    variance = torch.where(none, var.gather(0, best)[0], 1.0 / total.clamp_min(1e-300))
    return MergedBracket(radiance=merged, variance=variance, clipped=none, reference_used=keep[0])


def clipped_counts(frames: np.ndarray, bit_depth: int, margin: int = 0) -> Tensor:
    """(*) bool: ``frames`` (*) counts at the saturation level less ``margin`` (clipped sites)."""
    return torch.from_numpy(frames.astype(np.int64) >= saturation_count(bit_depth) - int(margin))


def bracket_site_noise(capture: Capture, *, dark_threshold: float, saturation_margin: int = 0) -> SiteNoise:
    """Per-site noise of the capture's frames, from the four-site redundancy of the reference frames.

    :func:`polarshape.recover.noise.estimate_noise` on the plain 2×2 blocks (variance factor 1) gives
    var(s0) = R + G · s0 of a block's own s0 = ½ Σ of its four sites; with per-site σ²(I) = r + g · I,
    var(s0) = r + ½ g · s0 (:mod:`polarshape.recover.noise`), so r = R and g = 2G.
    """
    k = capture.num_lights
    h, w = capture.frames.shape[1] // 2, capture.frames.shape[2] // 2
    black = capture.spec.camera.black_level
    redundancy = torch.empty((k, h, w), dtype=torch.float64)
    block_s0 = torch.empty((k, h, w), dtype=torch.float64)
    usable = torch.empty((k, h, w), dtype=torch.bool)
    for i in range(k):
        sites = split_mosaic(counts_to_float(capture.frames[i], capture.bit_depth, black, dtype=torch.float64),
                             capture.layout)  # (4, H, W)
        redundancy[i] = site_redundancy(sites)
        block_s0[i] = 0.5 * sites.sum(0)
        clipped = reduce_mask_to_superpixels(clipped_counts(capture.frames[i], capture.bit_depth, saturation_margin),
                                             "any")
        usable[i] = ~clipped & (block_s0[i] >= dark_threshold)
    step = 1.0 / (max_count(capture.bit_depth) - black)
    model = estimate_noise(redundancy, block_s0, usable, step=step)
    logger.debug("brackets: per-site noise read σ %.3g, gain %.3g (%s)", math.sqrt(model.read_var), 2 * model.shot_gain,
                 model.source)
    return SiteNoise(read_var=model.read_var, gain=2.0 * model.shot_gain)


def _frame_names(capture: Capture, k: int) -> list[str]:
    light = capture.spec.lights[k]
    keys = [f"lights[{k}].frame"] + [f"lights[{k}].brackets[{j}]" for j in range(len(light.brackets))]
    root = capture.root
    return [f"{root / path if root is not None else path} ({key})" for path, key in zip(light.frame_paths(), keys)]


def check_bracket_exposures(capture: Capture, k: int, values: Tensor, clipped: Tensor, exposures: np.ndarray) -> None:
    """Refuse light ``k``'s frames when their brightness ratios contradict their exposure times.

    Every two frames are compared over the sites above ``_RATIO_MIN_SIGNAL`` of full scale and
    unclipped in both (pairs sharing fewer than ``_RATIO_MIN_SITES`` such sites are not): the median
    ratio of their values must be within :data:`EXPOSURE_RATIO_TOLERANCE` of the ratio of their
    ``exposure_us``.

    Args:
        capture: the capture (frame names for the message).
        k: the light.
        values: (B, 2H, 2W) float64 x_j, fractions of full scale of each frame.
        clipped: (B, 2H, 2W) bool clipped samples.
        exposures: (B,) exposure times, µs, in the order of ``values``.

    Raises:
        CaptureError: a pair of frames whose brightness ratio is off, naming both files and the fix.
    """
    names = _frame_names(capture, k)
    pairs = [(a, b) if exposures[a] < exposures[b] else (b, a) for a in range(len(exposures))
             for b in range(a + 1, len(exposures))]
    for short, long in pairs:
        both = ~clipped[short] & ~clipped[long] & (values[short] >= _RATIO_MIN_SIGNAL) & (values[long] >= _RATIO_MIN_SIGNAL)
        n = int(both.sum())
        if n < _RATIO_MIN_SITES:
            logger.debug("brackets: light %d, exposures %g and %g µs share %d sites: not compared", k,
                         exposures[short], exposures[long], n)
            continue
        measured = float((values[long][both] / values[short][both]).median())
        declared = float(exposures[long] / exposures[short])
        if abs(math.log(max(measured, 1e-12) / declared)) > math.log(EXPOSURE_RATIO_TOLERANCE):
            raise CaptureError(
                f"{names[long]} is {measured:.3g}× as bright as {names[short]} where both are exposed, but their "
                f"exposure_us ({exposures[long]:g} and {exposures[short]:g} µs) say {declared:.3g}×: frames of different "
                f"exposures are mixed up — fix the frame paths or exposure_us of lights[{k}] in {CAPTURE_YAML} so that "
                "each frame is listed with its own exposure time (or the light changed between the frames)")


def merge_light(capture: Capture, k: int, noise: SiteNoise, *, dark_threshold: float, saturation_margin: int = 0,
                black_shift: Tensor | None = None) -> MergedBracket:
    """Light ``k``'s exposures merged into one mosaic (2H, 2W) at its reference exposure (module docstring).

    Args:
        capture: a capture whose lights hold exposure brackets (format 2).
        k: the light.
        noise: :func:`bracket_site_noise` of the capture.
        dark_threshold, saturation_margin: as :func:`polarshape.recover.preprocess.preprocess_capture`'s.
        black_shift: (2H, 2W) per-pixel black level minus the nominal one, fraction of full scale (a
            polarimetric calibration), subtracted from every frame before merging; None = none.

    Raises:
        CaptureError: the frames contradict their exposure times (:func:`check_bracket_exposures`).
    """
    frames = capture.bracket(k)  # (B, 2H, 2W)
    exposures = capture.spec.exposures_us
    if exposures is None:
        raise ValueError("merge_light needs a capture with exposure_us (format 2)")
    black = capture.spec.camera.black_level
    values = counts_to_float(frames, capture.bit_depth, black, dtype=torch.float64)  # (B, 2H, 2W)
    if black_shift is not None:
        values = values - black_shift.to(values)
    clipped = clipped_counts(frames, capture.bit_depth, saturation_margin)
    check_bracket_exposures(capture, k, values, clipped, exposures[k])
    ratios = torch.as_tensor(exposures[k] / exposures[k][0], dtype=torch.float64)
    return merge_exposures(values, clipped, ratios, noise, dark_threshold=dark_threshold)


@dataclass(frozen=True)
class BracketMerger:
    """What merging a format-2 capture's lights needs once (:func:`bracket_site_noise`), then
    :meth:`merge` one light at a time (preprocessing's per-light loop).

    Attributes:
        capture: a capture whose lights hold several exposures.
        noise: its per-site noise.
        dark_threshold, saturation_margin: as preprocessing's.
        black_shift: (2H, 2W) a polarimetric calibration's per-pixel black level minus the nominal one
            (fraction of full scale), or None.
    """

    capture: Capture
    noise: SiteNoise
    dark_threshold: float
    saturation_margin: int
    black_shift: Tensor | None = None

    @classmethod
    def of(cls, capture: Capture, *, dark_threshold: float, saturation_margin: int = 0,
           black_shift: Tensor | None = None) -> BracketMerger | None:
        """The merger of ``capture``, or None when its lights hold one frame each."""
        if not capture.has_brackets:
            return None
        noise = bracket_site_noise(capture, dark_threshold=dark_threshold, saturation_margin=saturation_margin)
        logger.info("preprocess: merging %d exposures per light (exposure brackets)", capture.spec.bracket_size)
        return cls(capture, noise, dark_threshold, int(saturation_margin), black_shift)

    def merge(self, k: int) -> MergedBracket:
        """Light ``k`` merged (:func:`merge_light`). A calibration's black shift is taken off every frame
        before merging and put back after, since preprocessing takes it off the mosaic it is given."""
        merged = merge_light(self.capture, k, self.noise, dark_threshold=self.dark_threshold,
                             saturation_margin=self.saturation_margin, black_shift=self.black_shift)
        if self.black_shift is None:
            return merged
        return replace(merged, radiance=merged.radiance + self.black_shift.to(merged.radiance))
