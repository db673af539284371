"""Stokes images from a raw polarisation mosaic (demosaicing).

Three methods, all exact on noise-free mosaics of spatially constant Stokes vectors for every
layout and ROI offset (pass the layout as seen by the stored mosaic, see
:meth:`MosaicLayout.shifted`):

- ``"superpixel"``: each 2×2 super-pixel gives one Stokes vector (half resolution). No
  interpolation, but the four sites are half a pixel apart, so edges produce false polarisation.
- ``"bilinear"``: each polariser channel is interpolated from its own quarter-density lattice
  with the tent kernel (full resolution).
- ``"edge_aware"`` (written for polarshape): every 2×2 window of the mosaic, aligned with the
  super-pixel grid or not, holds one site of each angle, so the (H−1)×(W−1) overlapping windows
  each give a Stokes vector; a pixel lies in four of them. Averaging the four equally is close to
  ``"bilinear"``. Instead each window is weighted by how little it straddles an intensity edge:
  a window whose s0 differs from both its left and right (or upper and lower) neighbours covers
  a step, and its four samples would mix two sides and invent polarisation; the windows that
  lie on one side of the step dominate. In flat regions the weights are equal, so noise is as
  with ``"bilinear"``; at intensity edges the false polarisation mostly disappears (see
  benchmarks/demosaic.py).

Pixel (row y, column x) of a full-resolution output is the mosaic pixel (y, x); pixel (y, x) of a
super-pixel output covers mosaic pixels (2y..2y+1, 2x..2x+1).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.checks import check_dtype_floating
from polarshape.imaging.mosaic import MosaicLayout, channel_angles_rad, check_layout, check_mosaic_shape, split_mosaic
from polarshape.imaging.stokes import intensities_from_stokes, stokes_from_intensities

__all__ = ["DEMOSAIC_METHODS", "DemosaicMethod", "block_mean_bilinear_sites", "block_mean_bilinear_stokes", "intensities_from_mosaic", "stokes_from_mosaic"]

DemosaicMethod = Literal["superpixel", "bilinear", "edge_aware"]
DEMOSAIC_METHODS: tuple[str, ...] = ("superpixel", "bilinear", "edge_aware")

_IMX250MZR = MosaicLayout.imx250mzr()


# (cos 2θ, sin 2θ) of the channels 0°, 45°, 90°, 135°, exact.
_COS_SIN_2THETA = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))


def _modulation_maps(layout: MosaicLayout, h: int, w: int, like: Tensor) -> Tensor:
    """(2, H, W) cos 2θ and sin 2θ of the polariser in front of each pixel."""
    tile = like.new_tensor(
        [[_COS_SIN_2THETA[layout.channel_of_site(i, j)] for j in range(2)] for i in range(2)]
    )  # (2, 2, 2): row parity, column parity, (cos, sin)
    return tile.permute(2, 0, 1).repeat(1, h // 2, w // 2)


def _box2x2(x: Tensor) -> Tensor:
    """Sum over every 2×2 window ('valid'): (..., H, W) -> (..., H-1, W-1)."""
    rows = x[..., :-1, :] + x[..., 1:, :]
    return rows[..., :-1] + rows[..., 1:]


def _midpoints(g: Tensor, dim: int, after: bool) -> Tensor:
    """Means of neighbouring lattice samples along ``dim`` (-1 or -2), edge sample repeated.

    ``after``: the midpoints lie after each sample (between g[k] and g[k+1]); else before it.
    """
    n = g.shape[dim]
    last, first = g.narrow(dim, n - 1, 1), g.narrow(dim, 0, 1)
    padded = torch.cat([g, last], dim=dim) if after else torch.cat([first, g], dim=dim)
    return 0.5 * (padded.narrow(dim, 0, n) + padded.narrow(dim, 1, n))


def _bilinear(m: Tensor, layout: MosaicLayout) -> Tensor:
    """Each channel interpolated bilinearly from its own quarter-density lattice.

    m (N, H, W) -> (N, 4, H, W). At the borders the missing neighbour is replaced by the nearest
    sample of the same channel (equivalent to normalised tent interpolation).
    """
    out = m.new_empty((m.shape[0], 4, *m.shape[-2:]))
    for c in range(4):
        i, j = layout.site_of_channel(c)
        g = m[:, i::2, j::2]  # (N, H/2, W/2) samples of channel c
        across = _midpoints(g, -1, after=j == 0)  # at the other columns of the same rows
        out[:, c, i::2, j::2] = g
        out[:, c, i::2, 1 - j :: 2] = across
        out[:, c, 1 - i :: 2, j::2] = _midpoints(g, -2, after=i == 0)
        out[:, c, 1 - i :: 2, 1 - j :: 2] = _midpoints(across, -2, after=i == 0)
    return out


def _one_sided_min_abs_diff(x: Tensor, dim: int) -> Tensor:
    """Per element, the smaller of |forward difference| and |backward difference| along ``dim``.

    At a step between samples k and k+1 only the sample straddling it (a window that covers both
    sides) has both differences large; its neighbours each have one zero difference.
    """
    if x.shape[dim] < 2:
        return torch.zeros_like(x)
    d = x.diff(dim=dim).abs()
    edge = torch.full_like(d.narrow(dim, 0, 1), float("inf"))
    return torch.minimum(torch.cat([d, edge], dim=dim), torch.cat([edge, d], dim=dim))


def _edge_aware(m: Tensor, modulation: Tensor, tau_rel: float) -> Tensor:
    """Edge-aware blend of the four overlapping 2×2 super-pixels that contain each pixel.

    m (N, 1, H, W), modulation (2, H, W) cos 2θ and sin 2θ per pixel -> Stokes (N, 3, H, W).
    """
    # Every 2×2 window, aligned or not, holds one site of each angle, so its samples give the
    # exact quad inverse (spec §1) wherever the field is constant over the window:
    # s0 = ½ Σ I, s1 = Σ I cos 2θ = I0 − I90, s2 = Σ I sin 2θ = I45 − I135.
    windows = torch.cat([0.5 * _box2x2(m), _box2x2(m * modulation)], dim=1)  # (N, 3, H-1, W-1)
    s0 = windows[:, :1]  # (N, 1, H-1, W-1), free of the polariser modulation
    # Windows that straddle an intensity edge are the ones whose s0 differs from BOTH neighbours;
    # they would mix two sides and invent polarisation, so they get little weight.
    e2 = _one_sided_min_abs_diff(s0, -1) ** 2 + _one_sided_min_abs_diff(s0, -2) ** 2
    scale = s0.abs() + 0.1 * s0.abs().mean(dim=(-2, -1), keepdim=True)  # relative: unit-free
    tau2 = (tau_rel * scale) ** 2 + torch.finfo(m.dtype).tiny
    weight = 1.0 / (1.0 + e2 / tau2) + 1e-12  # (N, 1, H-1, W-1) in (0, 1]; floor keeps 0/0 away
    # Pixel (y, x) lies in windows (y-1..y, x-1..x); zero padding drops the ones off the image.
    num = _box2x2(F.pad(weight * windows, (1, 1, 1, 1)))  # (N, 3, H, W)
    den = _box2x2(F.pad(weight, (1, 1, 1, 1)))  # (N, 1, H, W)
    return num / den


def _prepare(mosaic: Tensor, layout: MosaicLayout, method: str, tau_rel: float) -> None:
    check_dtype_floating(mosaic, "mosaic", "convert sensor counts with polarshape.imaging.pixels.counts_to_float")
    check_layout(layout)
    if method not in DEMOSAIC_METHODS:
        raise ValueError(f"method must be one of {DEMOSAIC_METHODS}; got {method!r}")
    check_mosaic_shape(mosaic)
    if not tau_rel > 0:
        raise ValueError(f"tau_rel must be > 0 (edge contrast, fraction of the local intensity); got {tau_rel!r}")


def _full_resolution(mosaic: Tensor, layout: MosaicLayout, method: str, tau_rel: float) -> Tensor:
    """(*, H, W) -> (*, 4, H, W) intensities for "bilinear", (*, 3, H, W) Stokes for "edge_aware"."""
    *batch, h, w = mosaic.shape
    work_dtype = mosaic.dtype if mosaic.dtype in (torch.float32, torch.float64) else torch.float32
    m = mosaic.reshape(-1, h, w).to(work_dtype)  # (N, H, W)
    if method == "bilinear":
        out = _bilinear(m, layout)  # (N, 4, H, W)
    else:
        out = _edge_aware(m[:, None], _modulation_maps(layout, h, w, m), tau_rel)  # (N, 3, H, W)
    return out.to(mosaic.dtype).reshape(*batch, out.shape[1], h, w)


def stokes_from_mosaic(
    mosaic: Tensor,
    layout: MosaicLayout = _IMX250MZR,
    method: DemosaicMethod = "superpixel",
    *,
    tau_rel: float = 0.03,
) -> Tensor:
    """Linear Stokes images from a raw polarisation mosaic.

    Args:
        mosaic: (*, H, W) raw mosaic, floating point (e.g. fraction of full scale from
            :func:`polarshape.imaging.pixels.counts_to_float`); H and W even.
        layout: mosaic layout of ``mosaic`` as stored, our convention (default IMX250MZR; for an
            ROI use ``layout.shifted(offset_x, offset_y)``).
        method: ``"superpixel"`` -> (*, 3, H/2, W/2); ``"bilinear"`` or ``"edge_aware"`` -> (*, 3, H, W).
        tau_rel: ``"edge_aware"`` only: intensity step, as a fraction of the local intensity, at
            which a straddling window's weight halves (smaller = more edge-sensitive, noisier).

    Returns:
        (*, 3, H', W') Stokes vectors (s0, s1, s2), same dtype and device as ``mosaic``; angles
        from image x toward image y (down).

    Example:
        >>> m = torch.rand(2, 8, 8)
        >>> stokes_from_mosaic(m).shape, stokes_from_mosaic(m, method="edge_aware").shape
        (torch.Size([2, 3, 4, 4]), torch.Size([2, 3, 8, 8]))
    """
    _prepare(mosaic, layout, method, tau_rel)
    if method == "edge_aware":
        return _full_resolution(mosaic, layout, method, tau_rel)
    intensities = (
        split_mosaic(mosaic, layout) if method == "superpixel" else _full_resolution(mosaic, layout, method, tau_rel)
    )
    return stokes_from_intensities(intensities, channel_angles_rad(device=mosaic.device, dtype=mosaic.dtype))


def block_mean_bilinear_stokes(mosaic: Tensor, layout: MosaicLayout = _IMX250MZR) -> Tensor:
    """The bilinear Stokes estimate averaged over each 2×2 block, computed at block resolution.

    Equal (to rounding) to ``avg_pool2d(stokes_from_mosaic(mosaic, layout, "bilinear"), 2)``: over
    its block, the bilinear image of a channel at site (i, j) holds the sample g, its midpoints
    across (A g) and down (D g) and their midpoint (D A g); their mean ¼ (1 + A)(1 + D) g is the
    separable [¾, ¼] filter of the channel's own lattice toward the block's other sites — a quarter
    of the full-resolution work and memory (:func:`block_mean_bilinear_sites`).

    Args:
        mosaic: (*, H, W) raw mosaic, floating point, H and W even.
        layout: the mosaic's layout as stored.

    Returns:
        (*, 3, H/2, W/2) Stokes vectors, same dtype and device as ``mosaic``.
    """
    _prepare(mosaic, layout, "bilinear", 0.03)
    intensities = block_mean_bilinear_sites(split_mosaic(mosaic, layout), layout, inplace=True)
    return stokes_from_intensities(intensities, channel_angles_rad(device=mosaic.device, dtype=mosaic.dtype))


def block_mean_bilinear_sites(sites: Tensor, layout: MosaicLayout = _IMX250MZR, *, inplace: bool = False) -> Tensor:
    """The four bilinear polariser images averaged over each 2×2 block, from the block's sites.

    Each channel's lattice (H, W) takes the separable filter ¾ g + ¼ (its neighbour toward the
    block's other sites), across then down, the last sample repeated at the border
    (:func:`block_mean_bilinear_stokes`). The weights are multiples of 1/16, so on integer counts
    (up to 2²⁰) the result is exact in float32.

    Args:
        sites: (*, 4, H, W) images at 0°, 45°, 90°, 135° (:func:`polarshape.imaging.mosaic.split_mosaic`
            of a mosaic of this ``layout``), floating point; H, W ≥ 1.
        layout: the layout of the mosaic the sites come from (where each channel sits in its block).
        inplace: overwrite ``sites`` (no new (*, 4, H, W) tensor; one (*, H, W) scratch).

    Returns:
        (*, 4, H, W) intensities, same dtype and device (``sites`` itself when ``inplace``).
    """
    check_dtype_floating(sites, "sites")
    check_layout(layout)
    out = sites if inplace else sites.clone()
    scratch = torch.empty_like(out[..., 0, :, :])  # (*, H, W)
    for c in range(4):
        i, j = layout.site_of_channel(c)
        g = out[..., c, :, :]
        _toward_into(g, scratch, -1, after=j == 0)  # across: scratch ← filtered g
        _toward_into(scratch, g, -2, after=i == 0)  # down: g ← filtered scratch
    return out


def _toward_into(g: Tensor, out: Tensor, dim: int, after: bool) -> None:
    """``out`` ← ¾ g + ¼ (the neighbouring sample after (or before) each one along ``dim``), edge
    repeated; ``out`` and ``g`` of the same shape, not overlapping (no temporaries)."""
    n = g.shape[dim]
    torch.mul(g, 0.75, out=out)
    if n == 1:
        out.add_(g, alpha=0.25)
        return
    if after:  # out[k] += ¼ g[k + 1]
        out.narrow(dim, 0, n - 1).add_(g.narrow(dim, 1, n - 1), alpha=0.25)
    else:  # out[k] += ¼ g[k − 1]
        out.narrow(dim, 1, n - 1).add_(g.narrow(dim, 0, n - 1), alpha=0.25)
    edge = n - 1 if after else 0  # the border sample's neighbour is itself
    out.narrow(dim, edge, 1).add_(g.narrow(dim, edge, 1), alpha=0.25)


def intensities_from_mosaic(
    mosaic: Tensor,
    layout: MosaicLayout = _IMX250MZR,
    method: DemosaicMethod = "superpixel",
    *,
    tau_rel: float = 0.03,
) -> Tensor:
    """The four polariser images 0°, 45°, 90°, 135° (our convention) from a raw mosaic.

    Same arguments as :func:`stokes_from_mosaic`.

    Returns:
        (*, 4, H', W') intensities (H' = H/2 for ``"superpixel"``, else H), same dtype and device
        as ``mosaic``. ``"superpixel"`` returns the raw samples; ``"edge_aware"`` returns the
        intensities of its Stokes estimate.
    """
    _prepare(mosaic, layout, method, tau_rel)
    if method == "superpixel":
        return split_mosaic(mosaic, layout)
    out = _full_resolution(mosaic, layout, method, tau_rel)
    if method == "edge_aware":
        out = intensities_from_stokes(out, channel_angles_rad(device=out.device, dtype=out.dtype))
    return out
