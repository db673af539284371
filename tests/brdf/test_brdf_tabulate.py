"""The MERL table's geometry and the FMBRDF rendered into it (polarshape.brdf.tabulate)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.brdf import FMBRDFParams, fmbrdf_stokes
from polarshape.brdf.tabulate import (
    MERL_SHAPE,
    fmbrdf_brdf_basis,
    fmbrdf_merl_table,
    half_diff_directions,
    merl_angles,
    merl_directions,
    merl_indices,
)


def test_indices_and_angles_round_trip_on_the_whole_grid() -> None:
    i_h, i_d, i_phi = np.meshgrid(*(np.arange(n) for n in MERL_SHAPE), indexing="ij")
    back = merl_indices(*merl_angles(i_h, i_d, i_phi))
    for got, want in zip(back, (i_h, i_d, i_phi)):
        assert np.array_equal(got, want)


def test_lookup_is_the_reference_mapping() -> None:
    th, td, ph = merl_angles(10, 45, 90)
    assert th == pytest.approx((10 / 90) ** 2 * math.pi / 2) and td == pytest.approx(math.pi / 4)
    assert ph == pytest.approx(math.pi / 2)
    # θ_h non-linear: the middle of the angle range is index √0.5·90 = 63
    assert merl_indices(math.pi / 4, 0.0, 0.0)[0] == 63
    # reciprocity: φ_d and φ_d ± π share a cell; out-of-range angles clamp
    assert merl_indices(0.1, 0.2, 0.3 - math.pi)[2] == merl_indices(0.1, 0.2, 0.3)[2] == int(0.3 / math.pi * 180)
    assert tuple(int(i) for i in merl_indices(2.0, 2.0, math.pi - 1e-15)) == (89, 89, 0)
    assert tuple(int(i) for i in merl_indices(-0.1, -0.1, 0.0)) == (0, 0, 0)


def test_directions_have_the_cells_half_and_difference_angles() -> None:
    rng = np.random.default_rng(0)
    idx = [rng.integers(0, n, 500) for n in MERL_SHAPE]
    light, view = merl_directions(*idx)
    th, td, _ = merl_angles(*idx)
    assert np.allclose(np.linalg.norm(light, axis=-1), 1) and np.allclose(np.linalg.norm(view, axis=-1), 1)
    half = (light + view) / np.linalg.norm(light + view, axis=-1, keepdims=True)
    assert np.allclose(np.arccos(np.clip(half[:, 2], -1, 1)), th, atol=1e-7)
    assert np.allclose(np.sum(light * half, axis=-1), np.cos(td))
    assert np.allclose(half[:, 1], 0.0)  # φ_h = 0
    # swapping light and view is φ_d → φ_d + π (the reciprocity the table relies on)
    l2, v2 = half_diff_directions(th, td, merl_angles(*idx)[2] + math.pi)
    assert np.allclose(l2, view) and np.allclose(v2, light)
    assert merl_directions()[0].shape == (*MERL_SHAPE, 3)
    with pytest.raises(ValueError, match="all three"):
        merl_directions(idx[0])


def _cells(n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    light, view = merl_directions(*(rng.integers(0, m, n) for m in MERL_SHAPE))
    return torch.from_numpy(light), torch.from_numpy(view)


def test_basis_is_s0_over_cos_theta_i_in_any_frame() -> None:
    """f = s0/(N·L): the same s0 in the camera frame (N toward the camera) for a rotated pose."""
    p = FMBRDFParams(ior=1.5, alpha=0.25, beta=1.8, kappa=10.0, k_s=0.7, k_b=0.4)
    tables = p.build_tables()
    light, view = _cells(64)
    f_s, f_b, valid = fmbrdf_brdf_basis(light, view, tables)
    assert valid.any() and (~valid).any()
    rot = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]], dtype=torch.float64)  # N = +z → (0, 0, −1)
    q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)))
    rot = q @ rot if torch.det(q) > 0 else -q @ rot
    n = rot @ torch.tensor([0.0, 0, 1], dtype=torch.float64)
    s0 = fmbrdf_stokes(n, light @ rot.T, view @ rot.T, **p.as_kwargs(), tables=tables)[..., 0]
    f = p.k_s * f_s + p.k_b * f_b
    assert torch.allclose((f * light[:, 2])[valid], s0[valid], rtol=1e-9, atol=1e-12)
    assert (f_s[~valid] == 0).all() and (f_b[~valid] == 0).all()


def test_basis_is_reciprocal_at_kappa_zero_and_not_above() -> None:
    light, view = _cells(400, seed=2)
    light, view = light[(light[:, 2] > 0.05) & (view[:, 2] > 0.05)], view[(light[:, 2] > 0.05) & (view[:, 2] > 0.05)]
    rel = {}
    for kappa in (0.0, 50.0):
        tables = FMBRDFParams(ior=1.5, alpha=0.4, beta=2.0, kappa=kappa).build_tables()
        fs, fb, _ = fmbrdf_brdf_basis(light, view, tables)
        fs2, fb2, _ = fmbrdf_brdf_basis(view, light, tables)
        assert torch.allclose(fs, fs2, rtol=1e-9)  # the surface term is reciprocal (spec §7)
        rel[kappa] = float(((fb - fb2).abs() / fb).max())
    assert rel[0.0] < 2e-3 < rel[50.0]  # the body term only at κ = 0 (spec §7: 1–4.5 % at κ 20–100)


@pytest.mark.slow
def test_full_table_is_finite_non_negative_and_missing_below_the_horizon() -> None:
    p = FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5)
    table = fmbrdf_merl_table(p, k_s_rgb=(1.0, 1.0, 1.0), k_b_rgb=(0.5, 0.4, 0.1))
    assert table.shape == (3, *MERL_SHAPE) and np.isfinite(table).all()
    light, view = merl_directions()
    below = (light[..., 2] <= 0) | (view[..., 2] <= 0)
    assert below.any() and (table[:, below] == -1.0).all() and (table[:, ~below] >= 0).all()
    # the specular peak is at θ_h = 0; the channels differ only by the body albedo
    assert table[0, 0, 10, 0] > table[0, 40, 10, 0]
    assert table[0, 0, 0, 0] > table[1, 0, 0, 0] > table[2, 0, 0, 0]


def test_table_refuses_bad_albedos() -> None:
    with pytest.raises(ValueError, match="three albedos"):
        fmbrdf_merl_table(FMBRDFParams(), k_s_rgb=(1.0, -1.0, 1.0))  # type: ignore[arg-type]
