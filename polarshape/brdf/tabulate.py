"""The FMBRDF as a tabulated isotropic BRDF in the MERL half/difference-angle layout.

The MERL table (Matusik et al. 2003; file format in :mod:`polarshape.io.merl`) samples an isotropic
BRDF over Rusinkiewicz coordinates (θ_h, θ_d, φ_d) on a 90 × 90 × 180 grid: θ_h non-linearly,
θ_h = (i/90)² · π/2; θ_d = j/90 · π/2; φ_d = k/180 · π. This module holds that grid's geometry
(angles ↔ indices, the light and view direction of every cell) and renders the FMBRDF into it.

Frame: the table's local frame, normal N = +z, half vector in the x–z plane (φ_h = 0). The MERL
"incoming" direction is the light L, the "outgoing" one the view V (both pointing away from the
surface, as L and V of spec §1). Only the intensity s0 is tabulated, and s0 does not depend on the
Stokes frame or on a rotation of the whole configuration, so this frame gives the same values as
the camera frame of spec §1 for any pose with the same N·L, N·V and L·V.

Radiometry: :func:`polarshape.brdf.fmbrdf_stokes` returns the reflected radiance s0 for unit
irradiance *at normal incidence* (spec §6: s_s = k_s D G1 G1 /(4 N·V) R E; spec §7 likewise with the
factor (N·L) inside the body integral), i.e. s0 = f · (N·L) · E with f the BRDF in 1/sr. So the
tabulated value is f = s0 / (N·L) (spec §6–§7, the same "BRDF s0/(N·L)" spec §7 uses for
reciprocity; for the Lambertian baseline of spec §10 it gives k_d/π). Cells with N·L ≤ 0 or
N·V ≤ 0 are missing, written as a negative value (the MERL convention).

Reciprocity: the MERL table keeps φ_d ∈ [0, π) only, assuming f(L, V) = f(V, L). The FMBRDF's
surface term is reciprocal; its body term is not for κ > 0 (spec §7, 1–4.5 % at κ = 20–100): the
table then holds f(L = MERL in, V = MERL out).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from polarshape.brdf.fmbrdf import FMBRDFTables, fmbrdf_stokes
from polarshape.brdf.params import FMBRDFParams

__all__ = [
    "MERL_SHAPE",
    "fmbrdf_brdf_basis",
    "fmbrdf_merl_table",
    "half_diff_directions",
    "merl_angles",
    "merl_directions",
    "merl_indices",
]

#: MERL table dimensions (θ_h, θ_d, φ_d).
MERL_SHAPE: tuple[int, int, int] = (90, 90, 180)

_HALF_PI = math.pi / 2
_CHUNK = 262_144  # cells per fast-evaluator call (bounds the evaluator's temporary memory)


def merl_angles(i_h: np.ndarray | int, i_d: np.ndarray | int, i_phi: np.ndarray | int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample angles (radians) of MERL table indices.

    θ_h = (i_h/90)² · π/2, θ_d = i_d/90 · π/2, φ_d = i_phi/180 · π (the lower edge of each cell of
    :func:`merl_indices`). Inputs broadcast together; outputs are float64 of the broadcast shape.
    """
    i_h, i_d, i_phi = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (i_h, i_d, i_phi)))
    n_h, n_d, n_phi = MERL_SHAPE
    return (i_h / n_h) ** 2 * _HALF_PI, i_d / n_d * _HALF_PI, i_phi / n_phi * math.pi


def merl_indices(theta_h: np.ndarray | float, theta_d: np.ndarray | float, phi_d: np.ndarray | float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MERL table indices of half/difference angles (radians), as the reference reader looks them up.

    θ_h → ⌊√(θ_h/(π/2)) · 90⌋, θ_d → ⌊θ_d/(π/2) · 90⌋, φ_d → ⌊(φ_d mod π)/π · 180⌋ (φ_d and φ_d + π
    share a cell by reciprocity), each clamped to the table. A slack of 1e-9 of a cell makes the
    angles of :func:`merl_angles` map back to their own indices despite rounding.

    Returns:
        (i_h, i_d, i_phi), int64 arrays of the broadcast shape.
    """
    th, td, ph = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_h, theta_d, phi_d)))
    n_h, n_d, n_phi = MERL_SHAPE
    slack = 1e-9
    i_h = np.floor(np.sqrt(np.clip(th, 0.0, None) / _HALF_PI) * n_h + slack)
    i_d = np.floor(td / _HALF_PI * n_d + slack)
    i_phi = np.floor(np.mod(ph, math.pi) / math.pi * n_phi + slack)
    i_phi = np.where(i_phi >= n_phi, i_phi - n_phi, i_phi)  # φ_d a hair below π (mod π) is cell 0
    return (np.clip(i_h, 0, n_h - 1).astype(np.int64), np.clip(i_d, 0, n_d - 1).astype(np.int64),
            np.clip(i_phi, 0, n_phi - 1).astype(np.int64))


def half_diff_directions(theta_h: np.ndarray, theta_d: np.ndarray, phi_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Light and view directions of half/difference angles (Rusinkiewicz 1998), local frame N = +z, φ_h = 0.

    The difference vector (sin θ_d cos φ_d, sin θ_d sin φ_d, cos θ_d) is given in the half vector's
    frame; rotating it by θ_h about y gives L (the half vector H = (sin θ_h, 0, cos θ_h) is the
    rotated z), and V is L mirrored about H: V = 2 (L·H) H − L.

    Args:
        theta_h, theta_d, phi_d: (...) radians, broadcastable.

    Returns:
        (light, view), each (..., 3) float64 unit vectors.
    """
    th, td, ph = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (theta_h, theta_d, phi_d)))
    dx, dy, dz = np.sin(td) * np.cos(ph), np.sin(td) * np.sin(ph), np.cos(td)
    ch, sh = np.cos(th), np.sin(th)
    light = np.stack([ch * dx + sh * dz, dy, -sh * dx + ch * dz], axis=-1)
    half = np.stack([sh, np.zeros_like(sh), ch], axis=-1)
    view = 2.0 * np.cos(td)[..., None] * half - light  # L·H = cos θ_d
    return light, view


def merl_directions(i_h: np.ndarray | None = None, i_d: np.ndarray | None = None,
                    i_phi: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Light and view directions (local frame, N = +z) of MERL table cells.

    Args:
        i_h, i_d, i_phi: broadcastable index arrays; all None (default) for the whole table.

    Returns:
        (light, view), each (..., 3) float64: (90, 90, 180, 3) for the whole table.
    """
    if i_h is None and i_d is None and i_phi is None:
        i_h, i_d, i_phi = np.meshgrid(*(np.arange(n) for n in MERL_SHAPE), indexing="ij")
    elif i_h is None or i_d is None or i_phi is None:
        raise ValueError("merl_directions takes all three index arrays (i_h, i_d, i_phi) or none")
    return half_diff_directions(*merl_angles(i_h, i_d, i_phi))


def fmbrdf_brdf_basis(light: Tensor, view: Tensor, tables: FMBRDFTables) -> tuple[Tensor, Tensor, Tensor]:
    """The FMBRDF's intensity BRDF split by albedo: f = k_s · f_s + k_b · f_b (spec §6, §7).

    s0 is linear in k_s (spec §6) and in k_b (spec §7), so the two parts, evaluated at unit albedo,
    give the BRDF of any albedos (per colour channel too) without re-evaluating the model.

    Args:
        light, view: (..., 3) unit directions in the local frame N = +z (float64 recommended).
        tables: :func:`polarshape.brdf.build_tables` of the material's (μ, α, β, κ).

    Returns:
        (f_s, f_b, valid): (...) surface and body BRDF in 1/sr at k_s = 1 and k_b = 1 (f = s0/(N·L),
        see the module docstring), zero where invalid; ``valid`` (...) bool is N·L > 0 and N·V > 0.
        Differentiable in the tables' parameters.
    """
    normal = torch.zeros_like(light)
    normal[..., 2] = 1.0
    cos_l = light[..., 2]
    valid = (cos_l > 0) & (view[..., 2] > 0)
    both = torch.stack([light, view])  # (2, ..., 3) one call for the two parts
    ks = torch.tensor([1.0, 0.0], dtype=light.dtype).reshape(2, *([1] * (light.dim() - 1)))
    s0 = fmbrdf_stokes(normal, both[0], both[1], ior=tables.ior, k_s=ks, k_b=1.0 - ks,
                       alpha=tables.alpha, beta=tables.beta, kappa=tables.kappa, tables=tables)[..., 0]
    f = torch.where(valid, s0 / torch.where(valid, cos_l, torch.ones_like(cos_l)), torch.zeros_like(s0))  # f = s0/(N·L)
    return f[0], f[1], valid


def fmbrdf_merl_table(params: FMBRDFParams, *, tables: FMBRDFTables | None = None,
                      k_s_rgb: tuple[float, float, float] | None = None,
                      k_b_rgb: tuple[float, float, float] | None = None) -> np.ndarray:
    """Render the FMBRDF's intensity into the MERL table: (3, 90, 90, 180) float64 BRDF values (1/sr).

    Args:
        params: the material; its k_s, k_b are used for all three channels unless the per-channel
            albedos ``k_s_rgb`` / ``k_b_rgb`` (R, G, B) are given.
        tables: prebuilt tables of ``params``' (μ, α, β, κ) (default: built here).

    Returns:
        (3, 90, 90, 180) float64: f = s0/(N·L) per cell (module docstring), −1 where the cell's
        light or view lies below the horizon (a MERL missing sample). Takes ~seconds on a CPU.
    """
    if tables is None:
        tables = params.build_tables()
    ks = np.asarray(k_s_rgb if k_s_rgb is not None else (params.k_s,) * 3, dtype=np.float64).reshape(3, 1)
    kb = np.asarray(k_b_rgb if k_b_rgb is not None else (params.k_b,) * 3, dtype=np.float64).reshape(3, 1)
    if ks.shape != (3, 1) or kb.shape != (3, 1) or (ks < 0).any() or (kb < 0).any():
        raise ValueError(f"k_s_rgb and k_b_rgb take three albedos ≥ 0 (R, G, B); got {k_s_rgb!r}, {k_b_rgb!r}")
    light, view = merl_directions()
    light, view = light.reshape(-1, 3), view.reshape(-1, 3)  # (C, 3), C = 90·90·180
    out = np.empty((3, light.shape[0]), dtype=np.float64)
    with torch.no_grad():
        for start in range(0, light.shape[0], _CHUNK):
            sl = slice(start, start + _CHUNK)
            f_s, f_b, valid = fmbrdf_brdf_basis(torch.from_numpy(light[sl]), torch.from_numpy(view[sl]), tables)
            f = ks * f_s.numpy() + kb * f_b.numpy()  # (3, c)
            out[:, sl] = np.where(valid.numpy(), f, -1.0)
    return out.reshape(3, *MERL_SHAPE)

