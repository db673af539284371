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
polarisation) under all K lights: the pair (b, b') has a step when log(s0_b' / s0_b) has one sign,
at least ``log(min_ratio)`` in size, under every light where both are usable, and varies between the
lights by at most ``max_spread`` of its size (at least two such lights). A block with a step to a
neighbour is ``adjacent``; one whose s0 lies strictly between two opposite neighbours', with a step
to each (along a row, a column or a diagonal), is ``on_edge``. Preprocessing then takes the plain
super-pixel estimate (the block's own four sites) where a block is adjacent and not on the edge, and
leaves the observations of blocks on the edge out (their normals and albedo filled from the
neighbours, as for other pixels without data; the run writes them into ``mixed.png``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from polarshape.checks import check_shape

__all__ = ["AlbedoEdges", "find_albedo_edges"]

#: neighbour offsets (row, column) of one direction per axis: a row, a column and the two diagonals.
_AXES: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))


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


def _shifted(x: Tensor, dy: int, dx: int, fill: float | bool) -> Tensor:
    """x (…, H, W) moved so that out[…, y, x] = x[…, y + dy, x + dx] (``fill`` beyond the border)."""
    h, w = x.shape[-2:]
    out = torch.full_like(x, fill)
    ys, yd = slice(max(dy, 0), h + min(dy, 0)), slice(max(-dy, 0), h + min(-dy, 0))
    xs, xd = slice(max(dx, 0), w + min(dx, 0)), slice(max(-dx, 0), w + min(-dx, 0))
    out[..., yd, xd] = x[..., ys, xs]
    return out


def _consistent_step(q: Tensor, usable: Tensor, threshold: float, max_spread: float, min_lights: int
                     ) -> tuple[Tensor, Tensor]:
    """Whether log-ratios q (K, H, W) show one albedo step, and which lights see it clearly.

    A surface reflection (untextured) shrinks the step in s0 toward 1 under a light where it is strong,
    so the step is measured on the lights where it is largest: at least ``min_lights`` of them within
    ``max_spread`` of the largest, that one at least ``threshold``; no usable light may see the
    opposite sign (beyond a tenth of the step).

    Returns:
        step (H, W) int8: +1 brighter, −1 darker, 0 none; clear (K, H, W) bool lights that see it.
    """
    out = torch.zeros(q.shape[1:], dtype=torch.int8, device=q.device)
    clear = torch.zeros_like(usable)
    for sign in (1, -1):
        qs = torch.where(usable, sign * q, torch.zeros_like(q))  # (K, H, W)
        top = qs.amax(0)  # (H, W)
        near_top = usable & (qs >= (1 - max_spread) * top)
        ok = (top >= threshold) & (near_top.sum(0) >= min_lights)
        ok &= (torch.where(usable, qs, torch.zeros_like(qs)) >= -0.1 * top).all(0)
        out = torch.where(ok, torch.full_like(out, sign), out)
        clear |= near_top & ok
    return out, clear


def _isolated_step(log_s0: Tensor, usable: Tensor, dy: int, dx: int, lo: int, hi: int, threshold: float,
                   max_spread: float, min_lights: int, flat: float = 0.25) -> tuple[Tensor, Tensor, Tensor]:
    """The step from block b + lo·o to b + hi·o (o = (dy, dx)), at b, where the radiance is flat on both
    sides of it (a step, not a shading ramp): under the lights that see the step clearly, the change from
    b + (lo − 1)·o to b + lo·o and from b + hi·o to b + (hi + 1)·o is at most ``flat`` of it, seen under
    at least ``min_lights`` of them (a step at the border of the usable observations is not taken).

    Args:
        log_s0: (K, H, W) log of the blocks' s0 (any value where not usable).
        usable: (K, H, W) bool.

    Returns:
        step (H, W) int8 (:func:`_consistent_step`), clear (K, H, W) bool, the log-step (K, H, W).
    """
    def at(x: Tensor, i: int, fill: float | bool) -> Tensor:
        return _shifted(x, i * dy, i * dx, fill)

    total = at(log_s0, hi, 0.0) - at(log_s0, lo, 0.0)  # (K, H, W)
    both = at(usable, lo, False) & at(usable, hi, False)
    step, clear = _consistent_step(total, both, threshold, max_spread, min_lights)
    for a, b in ((lo - 1, lo), (hi, hi + 1)):
        side = at(log_s0, b, 0.0) - at(log_s0, a, 0.0)
        seen = at(usable, a, False) & at(usable, b, False)
        steep = (clear & seen & (side.abs() > flat * total.abs())).any(0)
        unseen = (clear & seen).sum(0) < min_lights
        step = torch.where(steep | unseen, torch.zeros_like(step), step)
    return step, clear, total


def find_albedo_edges(
    block_s0: Tensor,
    usable: Tensor,
    *,
    min_ratio: float = 1.25,
    max_spread: float = 0.35,
    min_lights: int = 2,
) -> AlbedoEdges:
    """Blocks next to and on an albedo step, from the blocks' own s0 under every light (module docstring).

    Args:
        block_s0: (K, H, W) s0 of each 2×2 block from its own four sites (½ Σ), fraction of full scale.
        usable: (K, H, W) bool observations to compare (lit, unsaturated, in the mask).
        min_ratio: the smallest albedo ratio between neighbours taken for a step (> 1).
        max_spread: the most the log-ratio may vary between lights, as a fraction of its size.
        min_lights: the fewest lights a step must be seen under (≥ 2: one light cannot tell albedo
            from shading).

    Returns:
        :class:`AlbedoEdges` on the (H, W) grid.

    Raises:
        ValueError: shapes that differ; min_ratio ≤ 1; max_spread < 0; min_lights < 2.
    """
    check_shape(block_s0, ["K", "H", "W"], "block_s0")
    if usable.shape != block_s0.shape:
        raise ValueError(f"usable: shape {tuple(usable.shape)} must be block_s0's {tuple(block_s0.shape)}")
    if not min_ratio > 1:
        raise ValueError(f"min_ratio must be > 1 (an albedo ratio between neighbours); got {min_ratio!r}")
    if not max_spread >= 0:
        raise ValueError(f"max_spread must be ≥ 0; got {max_spread!r}")
    if min_lights < 2:
        raise ValueError(f"min_lights must be ≥ 2 (one light cannot tell albedo from shading); got {min_lights!r}")
    tiny = 1e-6
    ok = usable & (block_s0 > tiny)
    log_s0 = torch.log(block_s0.clamp_min(tiny))
    threshold = math.log(min_ratio)
    h, w = block_s0.shape[-2:]
    adjacent = torch.zeros((h, w), dtype=torch.bool, device=block_s0.device)
    on_edge = torch.zeros_like(adjacent)
    for dy, dx in _AXES:
        forward, _, _ = _isolated_step(log_s0, ok, dy, dx, 0, 1, threshold, max_spread, min_lights)  # b → b + o
        adjacent |= (forward != 0) | (_shifted(forward, -dy, -dx, 0) != 0)  # a step to b + o or from b − o
        on_edge |= _between(log_s0, ok, dy, dx, threshold, max_spread, min_lights)
    for dy in (-1, 0, 1):  # the neighbours of a mixed block interpolate from it
        for dx in (-1, 0, 1):
            adjacent |= _shifted(on_edge, dy, dx, False)
    return AlbedoEdges(adjacent=adjacent, on_edge=on_edge)


def _between(log_s0: Tensor, usable: Tensor, dy: int, dx: int, threshold: float, max_spread: float,
             min_lights: int, share: float = 0.1) -> Tensor:
    """(H, W) bool blocks b on an isolated step from b − o to b + o whose s0 lies between theirs under every
    light that sees the step clearly: at least ``share`` of the log-step from each side (a mixed block)."""
    step, clear, total = _isolated_step(log_s0, usable, dy, dx, -1, 1, threshold, max_spread, min_lights)
    part = (log_s0 - _shifted(log_s0, -dy, -dx, 0.0)) / torch.where(total.abs() > 0, total, torch.ones_like(total))
    inside = (part >= share) & (part <= 1 - share)
    return (step != 0) & (inside | ~clear).all(0)
