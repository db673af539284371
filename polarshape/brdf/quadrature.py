"""Quadrature rules over the microfacet polar angle θ ∈ [0, π/2], graded to the width of D.

The microfacet distribution of spec §3, D ∝ exp(−(θ/α)^β), is concentrated within a few α of the
macro normal for small α and has heavy tails for β < 1. A composite Gauss–Legendre rule on panels
whose breakpoints grow geometrically from α/32 resolves both; panels are capped in width so that
smooth factors varying on an O(1) or 1/√κ scale are resolved too. Node positions are plain numpy
(they depend on α, β only through the choice of panels, never differentiated); integrands are
evaluated in torch so that gradients with respect to the parameters flow through the values.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

HALF_PI = 0.5 * math.pi

#: Elements per temporary of the blocked parts of a table build (2¹⁴ float64 = 128 KB): a block's dozen
#: temporaries then stay in a core's cache, and the allocator reuses their memory instead of handing it
#: back to the system and faulting it in again on the next operation (measured: Fresnel on 2¹⁵
#: elements costs 3–4× per element what it costs on 2¹⁴, ~600 page faults a call; issue 13).
BLOCK_ELEMENTS = 1 << 14


@functools.lru_cache(maxsize=64)
def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [−1, 1] (read-only arrays, shape (n,))."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def theta_cutoff(alpha: float, beta: float, tail: float = 45.0) -> float:
    """Polar angle beyond which exp(−(θ/α)^β) < e^−tail (clipped to π/2)."""
    return min(HALF_PI, alpha * tail ** (1.0 / beta))


def theta_breaks(
    alpha: float,
    beta: float,
    *,
    max_width: float = 0.1,
    extra: tuple[float, ...] | np.ndarray = (),
    ratio: float = math.sqrt(2.0),
    tail: float = 45.0,
) -> np.ndarray:
    """Panel breakpoints on [0, θ_cut] for integrals weighted by the microfacet distribution.

    Args:
        alpha, beta: D's width (rad) and shape.
        max_width: the widest panel allowed (rad).
        extra: additional breakpoints (e.g. the θ where a clipped integrand has a kink).
        ratio: geometric growth of the breakpoints α/32·ratio^k.
        tail: see :func:`theta_cutoff`.

    Returns:
        (B,) increasing breakpoints, first 0, last θ_cut.
    """
    cut = theta_cutoff(alpha, beta, tail)
    start = alpha / 32.0
    n_geo = max(1, int(math.ceil(math.log(max(cut / start, 1.0 + 1e-12)) / math.log(ratio))) + 1)
    geo = start * ratio ** np.arange(n_geo)
    pts = np.concatenate([[0.0, cut], geo[geo < cut], np.asarray(extra, dtype=np.float64)])
    pts = np.unique(np.clip(pts, 0.0, cut))
    # split panels wider than max_width
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        k = max(1, int(math.ceil((b - a) / max_width - 1e-12)))
        out.extend(a + (b - a) * np.arange(1, k + 1) / k)
    br = np.unique(np.asarray(out))
    keep = np.concatenate([[True], np.diff(br) > 1e-14])
    return br[keep]


def composite_rule(breaks: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Composite n-point Gauss–Legendre rule on the panels ``breaks``: nodes, weights (P·n,)."""
    x, w = gauss_legendre(n)
    a = breaks[:-1, None]
    h = (breaks[1:] - breaks[:-1])[:, None]
    nodes = a + 0.5 * h * (x[None, :] + 1.0)
    weights = 0.5 * h * w[None, :]
    return nodes.ravel(), weights.ravel()


def theta_rule(
    alpha: float, beta: float, n: int = 6, *, max_width: float = 0.1, extra: tuple[float, ...] | np.ndarray = ()
) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights in θ for ∫₀^{π/2} f(θ) D(θ) … dθ (see :func:`theta_breaks`)."""
    return composite_rule(theta_breaks(alpha, beta, max_width=max_width, extra=extra), n)


def asinh_nonneg(x: "torch.Tensor") -> "torch.Tensor":
    """asinh(x) for x ≥ 0 as log1p(x + x²/(1 + √(1 + x²))) (the identity asinh x = log(x + √(1 + x²))
    written without cancellation): the same value to a few ulps, ~15× cheaper than ``torch.asinh``
    on CPU (not vectorised there). Differentiable (derivative 1/√(1 + x²))."""
    x2 = x * x
    return torch.log1p(x + x2 / (1.0 + torch.sqrt(1.0 + x2)))


@dataclass(frozen=True)
class ThetaWarp:
    """Monotone map θ ∈ [0, π/2] ↦ t ∈ [−1, 1] whose uniform grid is dense near grazing.

    u(θ) = θ − c·ε·asinh((π/2 − θ)/ε): spacing ≈ uniform away from grazing and ≈ 1/(1 + c) of it
    within ε of π/2, where the body term varies on the scale of α (Fresnel transmission and the
    horizon of the facet distribution). ε = clip(α/2, 0.005, 0.2); c puts about a third of the
    grid in that layer (by default).
    """

    eps: float
    c: float

    @staticmethod
    def for_alpha(alpha: float, *, eps_factor: float = 0.5, layer: float = 0.25 * math.pi) -> "ThetaWarp":
        """ε = clip(eps_factor·α, 0.0025, 0.2); ``layer`` = extra grid range given to the layer
        (0.25π: about a third of the grid)."""
        eps = min(max(eps_factor * alpha, 0.0025), 0.2)
        return ThetaWarp(eps=eps, c=layer / (eps * math.asinh(HALF_PI / eps)))

    def _u(self, theta: "torch.Tensor | np.ndarray") -> "torch.Tensor | np.ndarray":
        if isinstance(theta, torch.Tensor):
            return theta - self.c * self.eps * asinh_nonneg((HALF_PI - theta) / self.eps)
        return theta - self.c * self.eps * np.arcsinh((HALF_PI - theta) / self.eps)

    def to_grid(self, theta: "torch.Tensor") -> "torch.Tensor":
        """(...) θ -> (...) normalised grid coordinate in [−1, 1] (differentiable)."""
        u0, u1 = float(self._u(np.float64(0.0))), float(self._u(np.float64(HALF_PI)))
        return (self._u(theta) - u0) * (2.0 / (u1 - u0)) - 1.0

    def nodes(self, n: int) -> np.ndarray:
        """(n,) θ at the n uniformly spaced grid coordinates (θ_0 = 0, θ_{n−1} = π/2).

        Inverts the increasing map u(θ) = θ − cε·asinh((π/2 − θ)/ε): interpolation on a 2001-point
        grid, then Newton steps with u'(θ) = 1 + c/√(1 + ((π/2 − θ)/ε)²) to machine precision.
        """
        fine = np.linspace(0.0, HALF_PI, 2001)
        uf = self._u(fine)
        target = np.linspace(uf[0], uf[-1], n)
        out = np.interp(target, uf, fine)
        for _ in range(6):
            slope = 1.0 + self.c / np.sqrt(1.0 + ((HALF_PI - out) / self.eps) ** 2)
            out = np.clip(out - (self._u(out) - target) / slope, 0.0, HALF_PI)
        out[0], out[-1] = 0.0, HALF_PI
        return out
