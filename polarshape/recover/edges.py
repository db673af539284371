"""Albedo edges (texture, print, paint) in a polarisation mosaic: found from every light at once.

A step in body albedo between two neighbouring 2×2 blocks multiplies the radiance on one side by the
same ratio under every light, whereas shading, highlights and shadows change it differently from
light to light. Two harms follow, both a false linear polarisation (measured on
``configs/scenes/textured.yaml``: DoLP ≈ 0.3 where the surface has ≈ 0.03):

- a block **next to** a step, uniform itself: the bilinear demosaic (``preprocess.demosaic:
  bilinear``) interpolates each channel toward the block's other sites from the neighbouring block,
  a quarter of the other side's radiance in two of the four channels;
- a block **on** the step: its four sites see two albedos, so no estimate made of them is one Stokes
  vector (the four-site redundancy test of
  :func:`polarshape.recover.preprocess.mixed_superpixels` misses a step along a row or column: it
  leaves I0 + I90 = I45 + I135).

:func:`find_albedo_edges` finds both from the blocks' own s0 (½ Σ of their four sites, free of
polarisation) under all K lights: the pair (b, b') has a step when log(s0_b' / s0_b) is at least
``log(min_ratio)`` under the light that sees it most, at least ``min_lights`` lights see it within
``max_spread`` of that (a strong untextured surface reflection shrinks the ratio under some lights), no
light sees the opposite sign, the lights that see it (at least 0.3 of the log-step) carry at least ``min_weight``
of the pair's s0 summed over the lights, and s0 is flat on both sides of it (a step, not a shading ramp). The
weight test keeps a plain object's rim off: near a light's terminator its s0 is small and its log steep, and
with noise a ramp there passes the flatness test under the two or three lights nearest their terminator while
the others see nothing (measured: 1,365 blocks flagged on an untextured sphere at full frame, 12 lights; those
lights carry ≤ 0.23 of the radiance there, against ≥ 0.84 at the textured scene's true steps).

A block with a step to a neighbour (or next to a block on the edge) is ``adjacent``; a block b between two
opposite neighbours (along a row, a column or a diagonal) with such a step from one to the other, its own s0 at
least ``share`` of the log-step from each, is ``on_edge`` (its sites see both albedos). Preprocessing then takes
the plain super-pixel estimate (the block's own four sites) where a block is adjacent and not on the edge, and
leaves the observations of blocks on the edge out (their normals and albedo filled from the neighbours, as for
other pixels without data; the run writes them into ``mixed.png``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from polarshape.checks import check_shape

__all__ = ["AlbedoEdges", "find_albedo_edges"]

#: neighbour offsets (row, column) of one direction per axis: a row, a column and the two diagonals.
_AXES: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))
#: the share of a step's log-ratio under which a light counts as seeing it (:func:`_consistent_step`): a strong
#: surface reflection leaves ≥ ~0.4 of it on the textured scene's glossy sphere.
_SEEN = 0.3


@dataclass(frozen=True)
class AlbedoEdges:
    """Where the body albedo steps, on the super-pixel grid (H, W).

    Attributes:
        adjacent: (H, W) bool blocks with an albedo step to one of their 8 neighbours (bilinear
            interpolation would mix the other side in).
        on_edge: (H, W) bool blocks whose own four sites straddle the step (mixed albedo).
    """

    adjacent: Tensor
    on_edge: Tensor


def _gather(x: Tensor, ys: Tensor, xs: Tensor) -> tuple[Tensor, Tensor]:
    """x (H, W, K) (pixel-major: a block's K values side by side, ~4× faster to gather than (K, H, W)) at the
    blocks (ys, xs) (N,) each: (K, N) values (clamped at the border) and (N,) in-bounds."""
    h, w, k = x.shape
    inside = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
    flat = ys.clamp(0, h - 1) * w + xs.clamp(0, w - 1)  # (N,)
    return x.reshape(h * w, k).index_select(0, flat).T, inside


def _step_sign(q: Tensor, usable: Tensor, threshold: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Log-ratios q (K, *) over the ``usable`` lights: (*) bool a rising step (the largest at least
    ``threshold``, none falling beyond a tenth of it), a falling one, and the largest and smallest q."""
    inf = torch.tensor(math.inf, dtype=q.dtype, device=q.device)
    q_max = torch.where(usable, q, -inf).amax(0)
    q_min = torch.where(usable, q, inf).amin(0)
    up = (q_max >= threshold) & (q_min >= -0.1 * q_max)
    down = (q_min <= -threshold) & (q_max <= -0.1 * q_min)
    return up, down, q_max, q_min


def _candidates(scan: Tensor, oy: int, ox: int, threshold: float) -> tuple[Tensor, Tensor]:
    """Blocks a whose log-ratio to a + (oy, ox) may be one albedo step (the cheap necessary part of
    :func:`_consistent_step`, over the whole grid): their rows and columns (N,) each.

    ``scan`` (K, H, W) is log s0 with NaN at the observations that are not usable: a ratio with one is NaN,
    which ``fmax``/``fmin`` pass over — the largest and smallest usable q of :func:`_step_sign` (−inf, +inf
    without one), one light at a time into (H, W) buffers (no (K, H, W) temporaries).
    """
    h, w = scan.shape[-2:]
    c0, c1 = max(0, -ox), w - max(0, ox)
    a = (slice(0, h - oy), slice(c0, c1))
    b = (slice(oy, h), slice(c0 + ox, c1 + ox))
    q_max = torch.full((h - oy, c1 - c0), -math.inf, dtype=scan.dtype, device=scan.device)
    q_min = torch.full_like(q_max, math.inf)
    q = torch.empty_like(q_max)
    # numpy's fmax/fmin on the CPU (~3× torch's there), torch's elsewhere
    lib, bufs = (np, [t.numpy() for t in (scan, q_max, q_min, q)]) if scan.device.type == "cpu" else (
        torch, [scan, q_max, q_min, q])
    lights, hi, lo, diff = bufs
    for light in lights:  # (H, W)
        lib.subtract(light[b], light[a], out=diff)
        lib.fmax(hi, diff, out=hi)
        lib.fmin(lo, diff, out=lo)
    up = (q_max >= threshold) & (q_min >= -0.1 * q_max)
    down = (q_min <= -threshold) & (q_max <= -0.1 * q_min)
    ys, xs = torch.nonzero(up | down, as_tuple=True)
    return ys, xs + c0


def _consistent_step(q: Tensor, usable: Tensor, weight: Tensor, threshold: float, max_spread: float, min_lights: int,
                     min_weight: float) -> tuple[Tensor, Tensor]:
    """Whether log-ratios q (K, N) show one albedo step, and which lights see it clearly.

    A surface reflection (untextured) shrinks the step in s0 toward 1 under a light where it is strong,
    so the step is measured on the lights where it is largest: at least ``min_lights`` of them within
    ``max_spread`` of the largest, that one at least ``threshold``; no usable light may see the
    opposite sign (beyond a tenth of the step). And it is seen across the lights: those that see at least
    :data:`_SEEN` of it carry at least ``min_weight`` of the pair's radiance ``weight`` (K, N) over the usable
    lights — an albedo step scales the body reflection under every light, whereas a shading change near a
    light's terminator or shadow (where log s0 is steep and noisy, s0 small) is seen by the dim lights alone.

    Returns:
        ok (N,) bool; clear (K, N) bool lights that see it.
    """
    up, down, q_max, q_min = _step_sign(q, usable, threshold)
    sign = up.to(q.dtype) - down.to(q.dtype)  # (N,)
    top = torch.where(up, q_max, -q_min)
    clear = usable & (sign * q >= (1 - max_spread) * top) & (up | down)
    w = torch.where(usable, weight, torch.zeros_like(weight))  # (K, N)
    seen = (w * (sign * q >= _SEEN * top)).sum(0) >= min_weight * w.sum(0)
    return (up | down) & (clear.sum(0) >= min_lights) & seen, clear


def _isolated_steps(log_s0: Tensor, usable: Tensor, scan: Tensor, dy: int, dx: int, span: int, threshold: float,
                    max_spread: float, min_lights: int, min_weight: float, flat: float = 0.25
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The blocks a with a step from a to a + span·o (o = (dy, dx)) where the radiance is flat on both sides
    of it (a step, not a shading ramp): under the lights that see the step clearly, the change from a − o to
    a and from a + span·o to a + (span + 1)·o is at most ``flat`` of it, seen under at least ``min_lights``
    of them (a step at the border of the usable observations is not taken). ``log_s0`` and ``usable`` (H, W, K)
    pixel-major (:func:`_gather`); ``scan`` (K, H, W): :func:`_candidates`'.

    Returns:
        rows, columns (N,) of those blocks a, clear (K, N) lights, log-steps (K, N).
    """
    ys, xs = _candidates(scan, span * dy, span * dx, threshold)
    start, ok_a = _gather(log_s0, ys, xs)[0], _gather(usable, ys, xs)[0]
    end, ok_b = _gather(log_s0, ys + span * dy, xs + span * dx)[0], _gather(usable, ys + span * dy, xs + span * dx)[0]
    total = end - start  # (K, N)
    weight = torch.minimum(start, end).exp()  # (K, N) the darker side's s0
    keep, clear = _consistent_step(total, ok_a & ok_b, weight, threshold, max_spread, min_lights, min_weight)
    for i, j in ((-1, 0), (span, span + 1)):
        v1, in1 = _gather(log_s0, ys + i * dy, xs + i * dx)
        v2, in2 = _gather(log_s0, ys + j * dy, xs + j * dx)
        seen = clear & _gather(usable, ys + i * dy, xs + i * dx)[0] & _gather(usable, ys + j * dy, xs + j * dx)[0]
        seen &= (in1 & in2).unsqueeze(0)
        steep = (seen & ((v2 - v1).abs() > flat * total.abs())).any(0)
        keep &= ~steep & (seen.sum(0) >= min_lights)
    return ys[keep], xs[keep], clear[:, keep], total[:, keep]


def find_albedo_edges(
    block_s0: Tensor,
    usable: Tensor,
    *,
    min_ratio: float = 1.25,
    max_spread: float = 0.35,
    min_lights: int = 2,
    share: float = 0.1,
    min_weight: float = 0.5,
) -> AlbedoEdges:
    """Blocks next to and on an albedo step, from the blocks' own s0 under every light (module docstring).

    The whole grid is scanned once per direction for the cheap part of the test; the rest runs on the few
    candidate blocks only.

    Args:
        block_s0: (K, H, W) s0 of each 2×2 block from its own four sites (½ Σ), fraction of full scale.
        usable: (K, H, W) bool observations to compare (lit, unsaturated, in the mask).
        min_ratio: the smallest albedo ratio between neighbours taken for a step (> 1).
        max_spread: the lights that see the step clearly are within this fraction of the largest log-ratio.
        min_lights: the fewest lights a step must be seen under (≥ 2: one light cannot tell albedo
            from shading).
        share: a block on a step lies at least this fraction of the log-step from either side.
        min_weight: the lights that see a step (at least 0.3 of its log-ratio) carry at least this fraction of
            the pair's s0 summed over the usable lights (its darker side's).

    Returns:
        :class:`AlbedoEdges` on the (H, W) grid.

    Raises:
        ValueError: shapes that differ; min_ratio ≤ 1; max_spread outside [0, 1); min_lights < 2; min_weight
            outside (0, 1].
    """
    check_shape(block_s0, ["K", "H", "W"], "block_s0")
    if usable.shape != block_s0.shape:
        raise ValueError(f"usable: shape {tuple(usable.shape)} must be block_s0's {tuple(block_s0.shape)}")
    if not min_ratio > 1:
        raise ValueError(f"min_ratio must be > 1 (an albedo ratio between neighbours); got {min_ratio!r}")
    if not 0 <= max_spread < 1:
        raise ValueError(f"max_spread must be in [0, 1); got {max_spread!r}")
    if min_lights < 2:
        raise ValueError(f"min_lights must be ≥ 2 (one light cannot tell albedo from shading); got {min_lights!r}")
    if not 0 < min_weight <= 1:
        raise ValueError(f"min_weight must be in (0, 1] (a share of the radiance over the lights); got {min_weight!r}")
    tiny = 1e-6
    ok = usable & (block_s0 > tiny)
    log_s0 = torch.log(block_s0.to(torch.float32).clamp_min(tiny))
    scan = log_s0.masked_fill(~ok, math.nan)  # (K, H, W) the candidates' scan (_candidates)
    log_s0, ok = log_s0.permute(1, 2, 0).contiguous(), ok.permute(1, 2, 0).contiguous()  # (H, W, K) for _gather
    threshold = math.log(min_ratio)
    h, w = block_s0.shape[-2:]
    adjacent = torch.zeros((h, w), dtype=torch.bool, device=block_s0.device)
    on_edge = torch.zeros_like(adjacent)
    for dy, dx in _AXES:
        ys, xs, _, _ = _isolated_steps(log_s0, ok, scan, dy, dx, 1, threshold, max_spread, min_lights, min_weight)
        adjacent[ys, xs] = True
        adjacent[ys + dy, xs + dx] = True
        # a block b = a + o between a and a + 2o: its s0 at least ``share`` of the log-step from each side
        ys, xs, clear, total = _isolated_steps(log_s0, ok, scan, dy, dx, 2, threshold, max_spread, min_lights,
                                               min_weight)
        mid, ok_mid = _gather(log_s0, ys + dy, xs + dx)[0], _gather(ok, ys + dy, xs + dx)[0]
        part = (mid - _gather(log_s0, ys, xs)[0]) / torch.where(total.abs() > 0, total, torch.ones_like(total))
        seen = clear & ok_mid
        inside = (part >= share) & (part <= 1 - share)
        between = (inside | ~seen).all(0) & (seen.sum(0) >= min_lights)
        on_edge[ys[between] + dy, xs[between] + dx] = True
    # the neighbours of a mixed block interpolate from it
    adjacent |= torch.nn.functional.max_pool2d(on_edge[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    return AlbedoEdges(adjacent=adjacent, on_edge=on_edge)
