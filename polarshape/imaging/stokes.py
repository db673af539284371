"""Linear Stokes vectors from polariser intensities and back, DoLP and AoLP.

Convention (spec fmbrdf.md §1): angles are measured in the image plane from the image x axis
(right) toward the image y axis (down), in radians. A polariser at angle θ transmits
``I_θ = ½ (s0 + s1 cos 2θ + s2 sin 2θ)``; the AoLP is ``φ = ½ atan2(s2, s1)`` in (−π/2, π/2].
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from polarshape.checks import check_dtype_floating, check_shape, format_shape
from polarshape.errors import ShapeError

__all__ = ["analyser_rows", "aolp", "dolp", "intensities_from_stokes", "polariser_matrix", "stokes_from_four_angles",
           "stokes_from_intensities"]


def _check_stokes(stokes: object, name: str = "stokes") -> Tensor:
    stokes = check_dtype_floating(stokes, name)
    check_shape(stokes, ["*", "3", "H", "W"], name, "(s0, s1, s2)")
    return stokes


def analyser_rows(angle_rad: Tensor, diattenuation: Tensor | float = 1.0, gain: Tensor | float = 1.0) -> Tensor:
    """Rows ``½ g [1, D cos 2θ, D sin 2θ]`` of real linear analysers (spec §1, generalised).

    A polariser whose transmission axis is at ``θ`` and which transmits ``t_max`` of light polarised
    along it and ``t_min`` across it sends ``I = ½ ((t_max + t_min) s0 + (t_max − t_min)(s1 cos 2θ +
    s2 sin 2θ))`` to its pixel; with the gain ``g = t_max + t_min`` (times the pixel's response) and
    the diattenuation ``D = (t_max − t_min) / (t_max + t_min) = (ER − 1) / (ER + 1)`` (ER = extinction
    ratio) that is ``I = row · s``. The ideal polariser of spec §1 is ``D = 1, g = 1``.

    Args:
        angle_rad: (*) transmission-axis angles, radians, our convention (from x toward y-down).
        diattenuation: (*) or scalar D in (0, 1].
        gain: (*) or scalar g > 0.

    Returns:
        (*, 3) rows with ``I = row @ s`` (dtype and device of ``angle_rad``).
    """
    angle_rad = check_dtype_floating(angle_rad, "angle_rad")
    two = 2.0 * angle_rad
    d = torch.as_tensor(diattenuation, dtype=angle_rad.dtype, device=angle_rad.device)
    g = torch.as_tensor(gain, dtype=angle_rad.dtype, device=angle_rad.device)
    rows = torch.stack([torch.ones_like(two), d * torch.cos(two), d * torch.sin(two)], dim=-1)
    return (0.5 * g).unsqueeze(-1) * rows


def polariser_matrix(angles_rad: Tensor) -> Tensor:
    """Rows ``½ [1, cos 2θ, sin 2θ]`` mapping a linear Stokes vector to ideal polariser intensities.

    Args:
        angles_rad: (K,) polariser angles in radians (our convention, from x toward y-down).

    Returns:
        (K, 3) matrix ``A`` with ``I = A @ s`` (same dtype and device as ``angles_rad``);
        :func:`analyser_rows` with D = 1, g = 1.
    """
    angles_rad = check_dtype_floating(angles_rad, "angles_rad")
    check_shape(angles_rad, ["K"], "angles_rad")
    if angles_rad.numel() == 0:
        raise ShapeError("angles_rad must have shape (K,) with K >= 1; got (0,)")
    return analyser_rows(angles_rad)


def stokes_from_intensities(intensities: Tensor, angles_rad: Tensor) -> Tensor:
    """Least-squares linear Stokes vector from images behind polarisers at known angles.

    Fits ``I_θ = ½ (s0 + s1 cos 2θ + s2 sin 2θ)`` (spec §1) per pixel. For the angles
    0, π/4, π/2, 3π/4 this is the exact inverse ``s0 = ½ ΣI, s1 = I0 − I90, s2 = I45 − I135``.

    Args:
        intensities: (*, K, H, W) float intensities, K >= 3, any float dtype and device.
        angles_rad: (K,) polariser angles in radians (from image x toward image y, down); at least
            three of them distinct modulo π.

    Returns:
        (*, 3, H, W) Stokes vectors (s0, s1, s2), same dtype and device as ``intensities``.

    Example:
        >>> ang = torch.tensor([0.0, 0.25, 0.5, 0.75]) * torch.pi
        >>> stokes_from_intensities(torch.ones(1, 4, 2, 2), ang)[0, :, 0, 0]
        tensor([2., 0., 0.])
    """
    intensities = check_dtype_floating(intensities, "intensities")
    angles_rad = check_dtype_floating(angles_rad, "angles_rad")
    check_shape(intensities, ["*", "K", "H", "W"], "intensities")
    k = intensities.shape[-3]
    match = f"to match intensities (*, K, H, W) = {format_shape(intensities.shape)}"
    check_shape(angles_rad, [str(k)], "angles_rad", match)
    # The pseudo-inverse is computed once in float64 so the 0/45/90/135 case is exact to rounding.
    a = polariser_matrix(angles_rad.detach().to(torch.float64))  # (K, 3)
    sv = torch.linalg.svdvals(a)
    if k < 3 or float(sv[-1]) < 1e-6 * float(sv[0]):
        angles_deg = [round(math.degrees(float(t)), 3) for t in angles_rad.detach().cpu()]
        raise ValueError(
            f"angles_rad {angles_deg} (degrees) cannot determine (s0, s1, s2): give at least three "
            "polariser angles that are distinct modulo 180°"
        )
    pinv = torch.linalg.pinv(a).to(device=intensities.device, dtype=intensities.dtype)  # (3, K)
    return torch.einsum("ck,...khw->...chw", pinv, intensities)


def stokes_from_four_angles(intensities: Tensor, *, out: Tensor | None = None) -> Tensor:
    """Stokes vectors from images behind ideal polarisers at 0°, 45°, 90°, 135° (spec §1):
    ``s0 = ½ ΣI, s1 = I0 − I90, s2 = I45 − I135`` — :func:`stokes_from_intensities` of these angles,
    written out: exact whenever the sums are (integer counts in float32), where the float32 product
    with the float64 pseudo-inverse is off by up to 2⁻²⁴ of the intensities.

    Args:
        intensities: (*, 4, H, W) images at 0°, 45°, 90°, 135° (:func:`polarshape.imaging.mosaic.split_mosaic`).
        out: (*, 3, H, W) where to write the result (default: a new tensor).

    Returns:
        (*, 3, H, W) Stokes vectors (s0, s1, s2), same dtype and device as ``intensities``.
    """
    intensities = check_dtype_floating(intensities, "intensities")
    check_shape(intensities, ["*", "4", "H", "W"], "intensities", "(0°, 45°, 90°, 135°)")
    i0, i45, i90, i135 = intensities.unbind(-3)
    if out is None:
        out = intensities.new_empty((*intensities.shape[:-3], 3, *intensities.shape[-2:]))
    s0, s1, s2 = out.unbind(-3)
    torch.add(i0, i45, out=s0).add_(i90).add_(i135).mul_(0.5)
    torch.sub(i0, i90, out=s1)
    torch.sub(i45, i135, out=s2)
    return out


def intensities_from_stokes(stokes: Tensor, angles_rad: Tensor) -> Tensor:
    """Images behind ideal linear polarisers at the given angles (Malus, spec §1).

    Args:
        stokes: (*, 3, H, W) linear Stokes vectors.
        angles_rad: (K,) polariser angles in radians (from image x toward image y, down).

    Returns:
        (*, K, H, W) intensities ``½ (s0 + s1 cos 2θ + s2 sin 2θ)``, same dtype/device as ``stokes``.
    """
    stokes = _check_stokes(stokes)
    a = polariser_matrix(angles_rad).to(device=stokes.device, dtype=stokes.dtype)
    return torch.einsum("kc,...chw->...khw", a, stokes)


def _upcast(x: Tensor) -> Tensor:
    """Half-precision input is evaluated in float32 (ratios and their gradients overflow float16)."""
    return x.float() if x.dtype in (torch.float16, torch.bfloat16) else x


def _safe_norm2(x: Tensor, y: Tensor) -> Tensor:
    """sqrt(x² + y²) with a zero (not NaN) gradient at the origin."""
    r2 = x * x + y * y
    positive = r2 > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, r2, torch.ones_like(r2))), torch.zeros_like(r2))


def _stokes_along(stokes: object, dim: int) -> Tensor:
    """``stokes`` checked to be a float tensor holding (s0, s1, s2) along ``dim``."""
    if dim == -3:
        return _check_stokes(stokes)  # the image layout (*, 3, H, W)
    stokes = check_dtype_floating(stokes, "stokes")
    after = -dim - 1 if dim < 0 else stokes.ndim - dim - 1  # dimensions after the Stokes axis
    if after < 0:
        raise ShapeError(f"stokes has no dim {dim} to hold (s0, s1, s2); got {format_shape(stokes.shape)}")
    trailing = [f"N{i}" for i in range(1, after + 1)]
    check_shape(stokes, ["*", "3", *trailing], "stokes", f"((s0, s1, s2) along dim {dim})")
    return stokes


def dolp(stokes: Tensor, *, dim: int = -3, eps: float = 1e-8) -> Tensor:
    """Degree of linear polarisation ``ρ = √(s1² + s2²) / s0`` (spec §1).

    Args:
        stokes: linear Stokes vectors with (s0, s1, s2) along ``dim``: (*, 3, H, W) images for the
            default ``dim=-3``, (*, 3) vectors for ``dim=-1``.
        dim: the axis of the three Stokes components.
        eps: lower bound on the denominator, so ``s0 <= 0`` gives a finite value (0 where also
            s1 = s2 = 0). The bound is raised to the dtype's smallest normal number if smaller
            (``eps=0``: plain ``lin / s0`` wherever s0 is a positive normal number).

    Returns:
        ``stokes`` without ``dim``, e.g. (*, H, W). Not clipped: with noise it can exceed 1 (clip
        with ``.clamp(0, 1)``). Finite everywhere for finite input, with finite gradients.

    Example:
        >>> dolp(torch.tensor([2.0, 1.0, 0.0]), dim=-1)
        tensor(0.5000)
    """
    stokes = _stokes_along(stokes, dim)
    s0, s1, s2 = _upcast(stokes).unbind(dim=dim)
    floor = max(float(eps), float(torch.finfo(s0.dtype).tiny))
    rho = _safe_norm2(s1, s2) / s0.clamp_min(floor)
    return rho.clamp_max(torch.finfo(stokes.dtype).max).to(stokes.dtype)


def aolp(stokes: Tensor, *, dim: int = -3) -> Tensor:
    """Angle of linear polarisation ``φ = ½ atan2(s2, s1)`` in (−π/2, π/2] radians (spec §1).

    Measured from the image x axis toward the image y axis (down). Where s1 = s2 = 0 the angle is
    undefined and 0 is returned (with a zero gradient).

    Args:
        stokes: linear Stokes vectors with (s0, s1, s2) along ``dim`` ((*, 3, H, W) by default).
        dim: the axis of the three Stokes components.

    Returns:
        AoLP in radians, ``stokes`` without ``dim``, e.g. (*, H, W).
    """
    stokes = _stokes_along(stokes, dim)
    _, s1, s2 = _upcast(stokes).unbind(dim=dim)
    defined = (s1 != 0) | (s2 != 0)
    # atan2(0, 0) has a NaN gradient; evaluate a harmless point there instead.
    phi = 0.5 * torch.atan2(
        torch.where(defined, s2, torch.zeros_like(s2)), torch.where(defined, s1, torch.ones_like(s1))
    )
    # atan2(-0.0, x < 0) = -π would give -π/2, outside (−π/2, π/2].
    return torch.where(phi <= -math.pi / 2, phi + math.pi, phi).to(stokes.dtype)
