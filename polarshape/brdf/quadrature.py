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

import numpy as np

HALF_PI = 0.5 * math.pi


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
