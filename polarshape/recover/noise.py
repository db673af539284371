"""The capture's noise model: σ of an observed s0 as a function of the signal, from the data itself.

An ideal polariser mosaic over-determines the linear Stokes vector: in each 2×2 block
I0 + I90 = I45 + I135 (= s0, spec §1), so the four-site redundancy

    d = (I0 + I90) − (I45 + I135)

is pure noise (free of polarisation and of linear intensity gradients). With per-site noise
variance σ_site²(I) = r + g·I (read + quantisation noise r, shot noise g·I, fractions of full
scale), var(d) = Σ σ_site² = 4r + 2g·s0, while the block's own s0 = ½ Σ I has
var(s0) = r + ½g·s0 = var(d) / 4. So the binned robust variance of d / 2 against s0 measures
σ²(s0) of the super-pixel estimate directly; :func:`estimate_noise` fits it as
σ² = read_var + shot_gain·s0 (observations straddling an edge — mixed blocks — excluded: there d
holds signal).

The recovery does not see the super-pixel s0 but the run's demosaic of it. The s0 map is linear in
the mosaic, so on white per-site noise its variance is the sum of the squared weights of its
stencil: :func:`demosaic_variance_factor` measures that sum by pushing the four sites of one block
through the demosaic (exact away from the border; spatially varying signal changes the shot term
only to second order). Bilinear + block centre: the block averages four interpolated vectors, each
site's own sample weighted 9/16, its edge neighbours 3/16 and its corner neighbour 1/16 — factor
(81 + 2·9 + 1)/256 = 0.39 (σ × 0.625); the plain super-pixel estimate: 1; bilinear at a corner site:
0.5625. s1 and s2 are differences of two site images (not half sums of four), so their variance is
twice that of s0 for every demosaic (:meth:`NoiseModel.linear_std`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

__all__ = [
    "NOISE_MAX_SAMPLES",
    "NOISE_MIN_SAMPLES",
    "NoiseModel",
    "demosaic_variance_factor",
    "estimate_noise",
    "noise_or_constant",
    "quantisation_noise",
    "site_redundancy",
]

logger = logging.getLogger(__name__)

#: Fewer usable observations than this: :func:`estimate_noise` falls back to quantisation noise.
NOISE_MIN_SAMPLES = 400
#: About the most noise samples :func:`estimate_noise` uses: above it, every s-th row (column) of
#: blocks gives its samples, so that a full frame costs what a 512² capture does (≈ 40,000 samples a
#: bin: the bins' robust variances are then good to ≈ 1 %, far inside the ±15 % the estimate meets).
NOISE_MAX_SAMPLES = 1 << 19
_BINS = 12


@dataclass(frozen=True)
class NoiseModel:
    """σ² of an observed s0 (fraction of full scale) = ``read_var + shot_gain · s0``, as the recovery
    sees it (after the run's demosaic).

    Attributes:
        read_var: σ² of an observed s0 at zero signal (read and quantisation noise), (fraction of full scale)².
        shot_gain: σ² grows by ``shot_gain × s0`` (shot noise), fraction of full scale.
        source: how it was estimated: ``"four-site redundancy"`` or ``"quantisation only"``.

    Example:
        >>> NoiseModel(1e-6, 1e-4, "four-site redundancy").std(torch.tensor([0.0, 0.5]))
        tensor([0.0010, 0.0071])
    """

    read_var: float
    shot_gain: float
    source: str

    def variance(self, s0: Tensor) -> Tensor:
        """σ² (same shape) of observed s0 values (negative s0, noise around black, count as 0)."""
        return self.read_var + self.shot_gain * s0.clamp_min(0.0)

    def std(self, s0: Tensor) -> Tensor:
        """σ (same shape as ``s0``) of an observed s0, as the recovery sees it."""
        return self.variance(s0).sqrt()

    def linear_std(self, s0: Tensor) -> Tensor:
        """σ (same shape) of an observed s1 or s2 at intensity ``s0``: √2 × :meth:`std` (module docstring)."""
        return (2.0 * self.variance(s0)).sqrt()

    def scaled(self, variance_factor: float) -> NoiseModel:
        """The same model with both terms times ``variance_factor`` (e.g. ¼ for 2×2 means of independent pixels)."""
        return replace(self, read_var=self.read_var * variance_factor, shot_gain=self.shot_gain * variance_factor)


def site_redundancy(sites: Tensor) -> Tensor:
    """(*, H, W) d = (I0 + I90) − (I45 + I135) of site intensities (*, 4, H, W) at 0°, 45°, 90°, 135°:
    both sums are s0, so d is noise plus whatever differs between the four sites (an edge)."""
    i0, i45, i90, i135 = sites.unbind(-3)
    return (i0 + i90) - (i45 + i135)


def quantisation_noise(step: float, variance_factor: float = 1.0) -> NoiseModel:
    """The noise of rounding alone: σ² = step²/12 per site, so of the super-pixel s0 (½ Σ of four
    sites) too, times the demosaic's ``variance_factor``.

    Args:
        step: one count as a fraction of full scale, ``1 / (2^bits − 1 − black)``.
        variance_factor: :func:`demosaic_variance_factor` of the run's demosaic.
    """
    return NoiseModel(read_var=variance_factor * step * step / 12.0, shot_gain=0.0, source="quantisation only")


def noise_or_constant(noise: NoiseModel | None, std: float) -> NoiseModel:
    """``noise`` when estimated, else a constant σ = ``std`` (``RecoveryInputs.noise`` / ``noise_std``:
    the quantisation σ), labelled "quantisation only"."""
    if noise is not None:
        return noise
    return NoiseModel(read_var=float(std) ** 2, shot_gain=0.0, source="quantisation only")


def demosaic_variance_factor(to_s0: Callable[[Tensor], Tensor], size: int = 16) -> float:
    """var(observed s0) / var(super-pixel s0) on white per-site noise, for a demosaic ``to_s0``.

    Args:
        to_s0: maps a float64 mosaic (2h, 2w) to its s0 image (h, w) on the super-pixel grid
            (e.g. ``lambda m: superpixel_stokes(m, layout, demosaic="bilinear")[0]``); linear.
        size: super-pixels per side of the probe mosaic (large enough that a central block's stencil
            does not reach the border).

    Returns:
        Σ of the squared stencil weights of an interior s0 (the super-pixel estimate: 1).
    """
    total = 0.0
    c = 2 * (size // 2)
    for dy in range(2):
        for dx in range(2):
            probe = torch.zeros((2 * size, 2 * size), dtype=torch.float64)
            probe[c + dy, c + dx] = 1.0
            total += float(to_s0(probe).pow(2).sum())
    # a site's weight in the super-pixel s0 is ½, so its stencil's Σ w² over the four sites is 4·¼ = 1
    return total


def estimate_noise(redundancy: Tensor, s0: Tensor, usable: Tensor, *, step: float, variance_factor: float = 1.0,
                   min_samples: int = NOISE_MIN_SAMPLES, max_samples: int = NOISE_MAX_SAMPLES) -> NoiseModel:
    """Fit σ²(s0) = read_var + shot_gain·s0 from the four-site redundancy (module docstring).

    Args:
        redundancy: (K, H, W) d of every block (:func:`site_redundancy`), fraction of full scale.
        s0: (K, H, W) the block's own s0 = ½ Σ of its four sites.
        usable: (K, H, W) bool observations to use (lit, unsaturated, not mixed, in the mask).
        step: one count as a fraction of full scale (the quantisation fallback and floor).
        variance_factor: :func:`demosaic_variance_factor` of the run's demosaic.
        min_samples: fewer usable observations: :func:`quantisation_noise`.
        max_samples: about the most samples used (more usable observations: every s-th row and column).

    Returns:
        The :class:`NoiseModel` of the observed s0. The s0 range is cut in ``_BINS`` quantile bins;
        each gives a robust variance (1.4826·MAD)² of the detrended d (:func:`_detrended`), and a
        weighted least-squares line through them (weights ∝ count / variance², the variance of a
        variance estimate), refined once with the bins standardised by the first line, is clamped
        to read_var ≥ step²/12 (rounding alone) and shot_gain ≥ 0.
    """
    stride = max(1, math.ceil(2 * int(torch.count_nonzero(usable)) / max(max_samples, 1)))  # two samples per observation
    d, x = _detrended(redundancy, s0, usable, stride)
    floor = quantisation_noise(step, variance_factor)
    if d.numel() < min_samples:
        logger.info("noise: %d usable observations < %d: quantisation noise only", d.numel(), min_samples)
        return floor
    order = torch.argsort(x)
    xs, ds = x[order], d[order]
    r, g = _binned_fit(xs, ds, None)
    # second pass: standardise by the first fit inside each bin (a bin spanning a range of variances
    # is a scale mixture, whose MAD underestimates its mean variance: read_var 0.5× on a ramp)
    r, g = _binned_fit(xs, ds, (max(r, step * step / 12.0), max(g, 0.0)))
    read_var = max(r, step * step / 12.0) * variance_factor
    shot_gain = max(g, 0.0) * variance_factor
    if not (math.isfinite(read_var) and math.isfinite(shot_gain)):
        return floor
    logger.debug("noise: read σ %.3g, shot gain %.3g (factor %.3g, %d observations)", math.sqrt(read_var), shot_gain,
                 variance_factor, d.numel())
    return NoiseModel(read_var=read_var, shot_gain=shot_gain, source="four-site redundancy")


def _binned_fit(xs: Tensor, ds: Tensor, first: tuple[float, float] | None) -> tuple[float, float]:
    """(read, gain) of var(d) ≈ read + gain·s0 from samples sorted by s0 (xs, ds (N,)), via ``_BINS``
    quantile bins' robust variances; with ``first`` = (read, gain) each bin's d is divided by that
    model's σ before its MAD is taken, and the result times the bin's mean model variance."""
    centres, variances, counts = [], [], []
    for part_x, part_d in zip(torch.tensor_split(xs, _BINS), torch.tensor_split(ds, _BINS)):
        if part_d.numel() < 8:
            continue
        scale = None if first is None else first[0] + first[1] * part_x.clamp_min(0.0)
        z = part_d if scale is None else part_d / scale.sqrt()
        var = (1.4826 * float((z - z.median()).abs().median())) ** 2
        centres.append(float(part_x.mean()))
        variances.append(var if scale is None else var * float(scale.mean()))
        counts.append(part_d.numel())
    xc, vc, nc = (torch.tensor(v, dtype=torch.float64) for v in (centres, variances, counts))
    return _weighted_line(xc, vc, nc)


def _detrended(d: Tensor, s0: Tensor, usable: Tensor, stride: int = 1) -> tuple[Tensor, Tensor]:
    """Samples (N,) of noise with the variance of the super-pixel s0, and their s0 (N,), from every
    ``stride``-th row (differences along rows) and column (along columns) of blocks.

    d is free of linear gradients but not of curvature (on a 30-pixel sphere its deterministic part
    doubles the measured σ at low signal). That part is smooth, while the noise of neighbouring
    blocks is independent (each d uses only its block's four raw pixels), so the second difference
    e = d_p − ½ (d_{p−1} + d_{p+1}) along rows and along columns removes it and keeps
    var(e) = 1.5 var(d) = 6 var(s0): e / √6 (three usable blocks in a row).
    """
    parts_d, parts_x = [], []
    for dim in (-1, -2):
        across = -2 if dim == -1 else -1  # the rows (columns) taken when differencing along columns (rows)
        d_dim, s0_dim, usable_dim = (t.index_select(across, torch.arange(0, t.shape[across], stride, device=t.device))
                                     if stride > 1 else t for t in (d, s0, usable))
        d_dim, s0_dim = d_dim.to(torch.float64), s0_dim.to(torch.float64)  # the rows taken only
        n = d.shape[dim]
        if n < 3:
            continue
        mid, lo, hi = (d_dim.narrow(dim, a, n - 2) for a in (1, 0, 2))
        ok = usable_dim.narrow(dim, 1, n - 2) & usable_dim.narrow(dim, 0, n - 2) & usable_dim.narrow(dim, 2, n - 2)
        parts_d.append(((mid - 0.5 * (lo + hi)) / math.sqrt(6.0))[ok])
        parts_x.append(s0_dim.narrow(dim, 1, n - 2)[ok])
    if not parts_d:
        return d.new_zeros(0), d.new_zeros(0)
    return torch.cat(parts_d), torch.cat(parts_x)


def _weighted_line(x: Tensor, v: Tensor, n: Tensor) -> tuple[float, float]:
    """Intercept and slope of v ≈ r + g·x, weights n / v² (two passes: the second weights by the
    first fit's variance, so one noisy low bin does not dominate)."""
    pred = v.clamp_min(v.max() * 1e-6 + 1e-30)
    r, g = 0.0, 0.0
    for _ in range(2):
        w = n / pred.pow(2)
        a = torch.stack([torch.ones_like(x), x], dim=1)  # (B, 2)
        ata = (a * w[:, None]).T @ a
        atb = (a * w[:, None]).T @ v
        if float(torch.linalg.det(ata)) <= 0:
            return float((w * v).sum() / w.sum()), 0.0
        r, g = (float(t) for t in torch.linalg.solve(ata, atb))
        if g < 0:  # no shot term visible: a constant
            r, g = float((w * v).sum() / w.sum()), 0.0
        pred = (r + g * x).clamp_min(v.max() * 1e-6 + 1e-30)
    return r, g
