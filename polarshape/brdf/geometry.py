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


#: A vector as its three components (x, y, z), each a tensor; the components broadcast together.
#: The evaluators work on components: contiguous per-component tensors vectorise where (..., 3)
#: slices are strided, and quantities of one pixel (N, V) keep their own shape while those of a
#: pixel·light (L) carry the light dimension.
Vec3 = tuple[Tensor, Tensor, Tensor]


def tiny(dtype: torch.dtype) -> float:
    """A positive floor far below any physical value but safe to square in ``dtype``."""
    return 1e-30 if dtype == torch.float64 else 1e-18


def components(x: Tensor) -> Vec3:
    """(..., 3) -> its three components, each (...) (views, no copy)."""
    return x.unbind(-1)  # type: ignore[return-value]


def dot3(a: Vec3, b: Vec3) -> Tensor:
    """a · b of component triples: (...) each -> (...) (a reduction over a trailing dimension of
    size 3 is several times slower in torch). Plain products and sums, not fused multiply-adds: N·L
    near the terminator is a cancelling sum whose rounding the result is proportional to."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross3(a: Vec3, b: Vec3) -> Vec3:
    """a × b of component triples (explicit: ``linalg.cross`` on (..., 3) is several times slower)."""
    return (
        torch.addcmul(a[1] * b[2], a[2], b[1], value=-1.0),
        torch.addcmul(a[2] * b[0], a[0], b[2], value=-1.0),
        torch.addcmul(a[0] * b[1], a[1], b[0], value=-1.0),
    )


def safe_norm3(x: Vec3) -> Tensor:
    """|x| of a component triple with a finite gradient at 0: (...)."""
    eps = tiny(x[0].dtype)
    return torch.sqrt(dot3(x, x).clamp_min(eps * eps))


def safe_normalize3(x: Vec3) -> Vec3:
    """x / |x| of a component triple; a zero vector stays (numerically) zero."""
    n = safe_norm3(x)
    return (x[0] / n, x[1] / n, x[2] / n)


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last dimension: (..., 3), (..., 3) -> (...) (see :func:`dot3`)."""
    return dot3(components(a), components(b))


def safe_norm(x: Tensor) -> Tensor:
    """Euclidean norm over the last dimension with a finite gradient at 0: (..., 3) -> (...)."""
    return safe_norm3(components(x))


def safe_normalize(x: Tensor) -> Tensor:
    """``x / |x|`` over the last dimension; a zero vector stays (numerically) zero: (..., 3)."""
    return x / safe_norm(x).unsqueeze(-1)


def angle_from(cross: Vec3, cos_part: Tensor) -> Tensor:
    """The angle atan2(|a × b|, a · b) in [0, π] from a × b (components) and a · b (spec §7, "Numerics").

    Both arguments may carry a common positive factor (it cancels in atan2): e.g. the angle of N and
    H = (L + V)/|L + V| is that of N and L + V."""
    return torch.atan2(safe_norm3(cross), cos_part)


def angle_between(a: Tensor, b: Tensor) -> Tensor:
    """Angle in [0, π] between ``a`` and ``b`` (any lengths) as atan2(|a×b|, a·b): (...)."""
    ca, cb = components(a), components(b)
    return angle_from(cross3(ca, cb), dot3(ca, cb))


def safe_atan2(y: Tensor, x: Tensor) -> Tensor:
    """``atan2(y, x)`` whose gradient is finite (zero) at the origin.

    At the origin y is replaced by 0 and x by 1 (atan2 = 0, zero gradient); written with a 0/1
    mask, not ``torch.where`` (several times slower on CPU)."""
    eps = tiny(y.dtype)
    at_origin = ((x * x + y * y) <= eps * eps).to(y.dtype)
    return torch.atan2(y * (1.0 - at_origin), x + at_origin)


def tangent_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors (..., 3) orthogonal to the unit vectors n (..., 3) and to each other
    (t1 = n × x̂ normalised, or n × ŷ where n is within 26° of x̂; t2 = n × t1)."""
    use_x = (n[..., 0].abs() < 0.9).unsqueeze(-1)  # (..., 1)
    ref = torch.where(use_x, n.new_tensor([1.0, 0.0, 0.0]), n.new_tensor([0.0, 1.0, 0.0]))
    t1 = torch.linalg.cross(n, ref.expand_as(n))
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(n, t1)
    return t1, t2


def stokes_frame3(view: Vec3) -> tuple[Vec3, Vec3]:
    """:func:`stokes_frame` of components: (e_x, e_y) as component triples of V's shape."""
    d = (-view[0], -view[1], -view[2])
    # x̂ − (x̂·d) d
    e_x = safe_normalize3((1.0 - d[0] * d[0], -(d[0] * d[1]), -(d[0] * d[2])))
    return e_x, cross3(d, e_x)


def stokes_frame(view: Tensor) -> tuple[Tensor, Tensor]:
    """The pixel's Stokes frame of spec §1.

    Args:
        view: (..., 3) unit vectors from the surface point to the camera (V).

    Returns:
        ``(e_x, e_y)``, each (..., 3): with the ray d = −V, e_x = normalise(x̂ − (x̂·d) d) and
        e_y = d × e_x. Orthographic (V = (0, 0, −1)): e_x = x̂, e_y = ŷ (image down).
    """
    e_x, e_y = stokes_frame3(components(view))
    return torch.stack(e_x, -1), torch.stack(e_y, -1)


def double_angle_of(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """cos 2ψ and sin 2ψ of ψ = atan2(b, a), algebraically ((a²−b²)/(a²+b²), 2ab/(a²+b²)); both 0
    at the origin (then the Fresnel factor they multiply vanishes too). A common positive factor of
    a and b cancels. Shapes (...) -> (...), (...)."""
    a2, b2 = a * a, b * b
    r2 = (a2 + b2).clamp_min(tiny(a.dtype))
    return (a2 - b2) / r2, 2.0 * a * b / r2


def double_angle(vec: Tensor, e_x: Tensor, e_y: Tensor) -> tuple[Tensor, Tensor]:
    """cos 2ψ and sin 2ψ of ψ = atan2(vec·e_y, vec·e_x), the angle of ``vec`` projected into a frame
    (:func:`double_angle_of`). Shapes (..., 3) -> (...), (...)."""
    return double_angle_of(dot(vec, e_x), dot(vec, e_y))


def rotate_linear_stokes(q: Tensor, u: Tensor, cos2chi: Tensor, sin2chi: Tensor) -> tuple[Tensor, Tensor]:
    """Express (s1, s2) given in a frame rotated by χ (from the target frame's e_x toward e_y)
    in the target frame: a polarisation angle ψ' in the source frame is ψ' + χ in the target."""
    return q * cos2chi - u * sin2chi, q * sin2chi + u * cos2chi


class ShadingGeometry(NamedTuple):
    """What the surface and body terms both need of a (N, L, V) configuration, computed once.

    Every field broadcasts to the evaluation shape (...) but keeps the shape it was computed at:
    quantities of N and V alone (n_dot_v, theta_v, n_cross_v, e_x, e_y) stay per pixel when N and V
    are given per pixel, so they are computed once per pixel, not once per pixel·light.

    Attributes:
        normal, light, view: N, L, V as component triples (:data:`Vec3`).
        n_dot_l, n_dot_v: cosines; theta_l, theta_v: polar angles from N in [0, π/2] (via atan2).
        n_cross_l, n_cross_v: N × L and N × V (component triples; θ_H of the surface term is the
            angle of N and L + V, whose cross product with N is their sum).
        e_x, e_y: the pixel Stokes frame (component triples, V's shape).
    """

    normal: Vec3
    light: Vec3
    view: Vec3
    n_dot_l: Tensor
    n_dot_v: Tensor
    theta_l: Tensor
    theta_v: Tensor
    n_cross_l: Vec3
    n_cross_v: Vec3
    e_x: Vec3
    e_y: Vec3

    @property
    def front(self) -> Tensor:
        """(...) bool: N·L > 0 and N·V > 0 (the terms are zero elsewhere)."""
        return (self.n_dot_l > 0) & (self.n_dot_v > 0)

    @property
    def view_mask(self) -> Tensor:
        """N·V > 0 as 0/1 in the dtype, V's shape (the N·L > 0 half of :attr:`front` is carried by the
        factor [N·L]₊ both terms have)."""
        return (self.n_dot_v > 0).to(self.n_dot_v.dtype)


def shading_geometry3(normal: Vec3, light: Vec3, view: Vec3) -> ShadingGeometry:
    """:class:`ShadingGeometry` of unit vectors N, L, V given as broadcastable component triples."""
    n_dot_l = dot3(normal, light)
    n_dot_v = dot3(normal, view)
    n_cross_l = cross3(normal, light)
    n_cross_v = cross3(normal, view)
    e_x, e_y = stokes_frame3(view)
    return ShadingGeometry(
        normal=normal,
        light=light,
        view=view,
        n_dot_l=n_dot_l,
        n_dot_v=n_dot_v,
        theta_l=angle_from(n_cross_l, n_dot_l).clamp(max=torch.pi / 2),
        theta_v=angle_from(n_cross_v, n_dot_v).clamp(max=torch.pi / 2),
        n_cross_l=n_cross_l,
        n_cross_v=n_cross_v,
        e_x=e_x,
        e_y=e_y,
    )


def shading_geometry(normal: Tensor, light: Tensor, view: Tensor) -> ShadingGeometry:
    """:class:`ShadingGeometry` of broadcastable (..., 3) unit vectors N, L, V (not broadcast here:
    what depends on N and V only is computed at their shape)."""
    return shading_geometry3(components(normal), components(light), components(view))


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
