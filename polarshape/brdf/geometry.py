"""NaN-free vector geometry for the forward model (spec §1 frames, §7 numerics).

All functions take batch-first tensors whose last dimension is 3 (camera frame, OpenCV: x right,
y down, z forward) and never produce NaN/Inf values or gradients, including for zero vectors and
parallel or anti-parallel pairs: norms are clamped before the square root, angles are taken as
``atan2(|a × b|, a · b)`` (spec §7, "Numerics") rather than ``arccos`` of a clamped dot product.

The pixel Stokes frame (:func:`stokes_frame`) and its projection onto the sensor plane
(:func:`sensor_plane_basis`, :func:`sensor_plane_stokes`, Stokes (..., 3, H, W)) live here too: the
simulator maps per-pixel Stokes to the angles a perspective sensor reports, recovery maps them back.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


def tiny(dtype: torch.dtype) -> float:
    """A positive floor far below any physical value but safe to square in ``dtype``."""
    return 1e-30 if dtype == torch.float64 else 1e-18


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last dimension: (..., 3), (..., 3) -> (...).

    Written per component: a reduction over a trailing dimension of size 3 is several times slower
    in torch than three fused multiply-adds."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def safe_norm(x: Tensor) -> Tensor:
    """Euclidean norm over the last dimension with a finite gradient at 0: (..., 3) -> (...)."""
    eps = tiny(x.dtype)
    return torch.sqrt(dot(x, x).clamp_min(eps * eps))


def safe_normalize(x: Tensor) -> Tensor:
    """``x / |x|`` over the last dimension; a zero vector stays (numerically) zero: (..., 3)."""
    return x / safe_norm(x).unsqueeze(-1)


def angle_between(a: Tensor, b: Tensor) -> Tensor:
    """Angle in [0, π] between ``a`` and ``b`` (any lengths) as atan2(|a×b|, a·b): (...)."""
    a, b = torch.broadcast_tensors(a, b)
    return torch.atan2(safe_norm(torch.linalg.cross(a, b, dim=-1)), dot(a, b))


def safe_atan2(y: Tensor, x: Tensor) -> Tensor:
    """``atan2(y, x)`` whose gradient is finite (zero) at the origin."""
    eps = tiny(y.dtype)
    at_origin = (x * x + y * y) <= eps * eps
    return torch.atan2(torch.where(at_origin, torch.zeros_like(y), y), torch.where(at_origin, torch.ones_like(x), x))


def tangent_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors (..., 3) orthogonal to the unit vectors n (..., 3) and to each other
    (t1 = n × x̂ normalised, or n × ŷ where n is within 26° of x̂; t2 = n × t1)."""
    use_x = (n[..., 0].abs() < 0.9).unsqueeze(-1)  # (..., 1)
    ref = torch.where(use_x, n.new_tensor([1.0, 0.0, 0.0]), n.new_tensor([0.0, 1.0, 0.0]))
    t1 = torch.linalg.cross(n, ref.expand_as(n))
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(n, t1)
    return t1, t2


def stokes_frame(view: Tensor) -> tuple[Tensor, Tensor]:
    """The pixel's Stokes frame of spec §1.

    Args:
        view: (..., 3) unit vectors from the surface point to the camera (V).

    Returns:
        ``(e_x, e_y)``, each (..., 3): with the ray d = −V, e_x = normalise(x̂ − (x̂·d) d) and
        e_y = d × e_x. Orthographic (V = (0, 0, −1)): e_x = x̂, e_y = ŷ (image down).
    """
    d = -view
    x_hat = torch.zeros_like(d)
    x_hat[..., 0] = 1.0
    e_x = safe_normalize(x_hat - dot(x_hat, d).unsqueeze(-1) * d)
    e_y = torch.linalg.cross(d, e_x, dim=-1)
    return e_x, e_y


def double_angle(vec: Tensor, e_x: Tensor, e_y: Tensor) -> tuple[Tensor, Tensor]:
    """cos 2ψ and sin 2ψ of ψ = atan2(vec·e_y, vec·e_x), the angle of ``vec`` projected into a frame.

    Computed algebraically ((a²−b²)/(a²+b²), 2ab/(a²+b²)); both are 0 when the projection
    vanishes (then the Fresnel factor they multiply vanishes too). Shapes (..., 3) -> (...), (...).
    """
    a = dot(vec, e_x)
    b = dot(vec, e_y)
    r2 = (a * a + b * b).clamp_min(tiny(a.dtype))
    return (a * a - b * b) / r2, 2.0 * a * b / r2


def rotate_linear_stokes(q: Tensor, u: Tensor, cos2chi: Tensor, sin2chi: Tensor) -> tuple[Tensor, Tensor]:
    """Express (s1, s2) given in a frame rotated by χ (from the target frame's e_x toward e_y)
    in the target frame: a polarisation angle ψ' in the source frame is ψ' + χ in the target."""
    return q * cos2chi - u * sin2chi, q * sin2chi + u * cos2chi


class ShadingGeometry(NamedTuple):
    """What the surface and body terms both need of a (N, L, V) configuration, computed once.

    Attributes (each (...)): n_dot_l, n_dot_v (cosines), theta_l, theta_v (polar angles from N in
    [0, π/2], via atan2), front (N·L > 0 and N·V > 0); e_x, e_y (..., 3): the pixel Stokes frame.
    """

    n_dot_l: Tensor
    n_dot_v: Tensor
    theta_l: Tensor
    theta_v: Tensor
    front: Tensor
    e_x: Tensor
    e_y: Tensor


def shading_geometry(normal: Tensor, light: Tensor, view: Tensor) -> ShadingGeometry:
    """:class:`ShadingGeometry` of broadcast (..., 3) unit vectors N, L, V."""
    n_dot_l = dot(normal, light)
    n_dot_v = dot(normal, view)
    e_x, e_y = stokes_frame(view)
    return ShadingGeometry(
        n_dot_l=n_dot_l,
        n_dot_v=n_dot_v,
        theta_l=angle_between(normal, light).clamp(max=torch.pi / 2),
        theta_v=angle_between(normal, view).clamp(max=torch.pi / 2),
        front=(n_dot_l > 0) & (n_dot_v > 0),
        e_x=e_x,
        e_y=e_y,
    )


def sensor_plane_basis(view: Tensor) -> Tensor:
    """Per pixel, how the Stokes frame projects onto the sensor plane (spec §1).

    Args:
        view: (..., 3) V of each pixel.

    Returns:
        (..., 2, 2) M = [[e_x·x̂, e_y·x̂], [e_x·ŷ, e_y·ŷ]]: a polarisation direction
        e = cos φ e_x + sin φ e_y is seen in the sensor plane along M (cos φ, sin φ).
        Identity for orthographic cameras.
    """
    e_x, e_y = stokes_frame(view)  # (..., 3) each
    return torch.stack([torch.stack([e_x[..., 0], e_y[..., 0]], -1), torch.stack([e_x[..., 1], e_y[..., 1]], -1)], -2)


def sensor_plane_stokes(stokes: Tensor, view: Tensor | None = None, *, basis: Tensor | None = None) -> Tensor:
    """Re-express Stokes vectors with the angle the sensor reports (spec §1, perspective cameras).

    A polarisation direction e = cos φ e_x + sin φ e_y (φ = AoLP in the pixel's Stokes frame) is
    observed at atan2(e·ŷ, e·x̂). s0 and the DoLP are kept. Computed without angles: with
    p = M (cos φ, sin φ) (see :func:`sensor_plane_basis`), the quadratic forms p_x², p_y², p_x p_y
    are linear in lin·cos²φ = (lin + s1)/2, lin·sin²φ = (lin − s1)/2, lin·sin φ cos φ = s2/2
    (lin = √(s1² + s2²)). Identity for orthographic cameras (e_x = x̂, e_y = ŷ).

    Args:
        stokes: (..., 3, H, W) Stokes in the per-pixel frames.
        view: (H, W, 3) V of each pixel (or give ``basis``).
        basis: (H, W, 2, 2) precomputed :func:`sensor_plane_basis` (cheaper for many lights).

    Returns:
        Same shape as ``stokes``.
    """
    if basis is None:
        if view is None:
            raise ValueError("sensor_plane_stokes needs view (H, W, 3) or basis (H, W, 2, 2)")
        basis = sensor_plane_basis(view.to(stokes.dtype))
    basis = basis.to(stokes.dtype)
    a, b = basis[..., 0, 0], basis[..., 0, 1]  # (H, W)
    c, d = basis[..., 1, 0], basis[..., 1, 1]
    s0, s1, s2 = stokes.unbind(-3)
    lin = torch.sqrt(s1 * s1 + s2 * s2)
    cc, ss, cs = 0.5 * (lin + s1), 0.5 * (lin - s1), 0.5 * s2  # lin·cos²φ, lin·sin²φ, lin·sinφ cosφ
    pxx = a * a * cc + 2 * a * b * cs + b * b * ss  # lin · p_x²
    pyy = c * c * cc + 2 * c * d * cs + d * d * ss  # lin · p_y²
    pxy = a * c * cc + (a * d + b * c) * cs + b * d * ss  # lin · p_x p_y
    norm = pxx + pyy
    ok = norm > 0
    safe = torch.where(ok, norm, torch.ones_like(norm))
    s1_out = torch.where(ok, lin * (pxx - pyy) / safe, 0.0)
    s2_out = torch.where(ok, lin * 2 * pxy / safe, 0.0)
    return torch.stack([s0, s1_out, s2_out], dim=-3)
