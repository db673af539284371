"""Tests of polarshape.imaging.stokes: Malus intensities <-> Stokes, DoLP, AoLP."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.errors import ShapeError
from polarshape.imaging.stokes import aolp, dolp, intensities_from_stokes, polariser_matrix, stokes_from_intensities

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]
QUAD = torch.tensor([0.0, 45.0, 90.0, 135.0]).deg2rad()


def _random_stokes(shape: tuple[int, ...], dtype: torch.dtype, device: str, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    s0 = torch.rand(shape, generator=g, dtype=torch.float64) + 0.1
    rho = torch.rand(shape, generator=g, dtype=torch.float64)
    phi = (torch.rand(shape, generator=g, dtype=torch.float64) - 0.5) * math.pi
    s = torch.stack([s0, s0 * rho * torch.cos(2 * phi), s0 * rho * torch.sin(2 * phi)], dim=-3)
    return s.to(device=device, dtype=dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_quad_inverse_is_the_spec_formula(dtype: torch.dtype, device: str) -> None:
    i = torch.rand(2, 4, 3, 5, dtype=dtype, device=device)
    s = stokes_from_intensities(i, QUAD.to(device))
    i0, i45, i90, i135 = i.unbind(-3)
    expected = torch.stack([0.5 * (i0 + i45 + i90 + i135), i0 - i90, i45 - i135], dim=-3)
    assert s.dtype == dtype and s.device.type == device
    torch.testing.assert_close(s, expected)


@pytest.mark.parametrize("dtype", DTYPES)
def test_round_trip_any_angles(dtype: torch.dtype) -> None:
    s = _random_stokes((7, 6), dtype, "cpu")[None]  # (1, 3, 7, 6)
    for angles_deg in ([0, 45, 90, 135], [10, 70, 130], [0, 30, 60, 90, 120, 150], [5, 50, 95, 140, 175]):
        angles = torch.tensor(angles_deg, dtype=dtype).deg2rad()
        back = stokes_from_intensities(intensities_from_stokes(s, angles), angles)
        torch.testing.assert_close(back, s)


def test_malus_values() -> None:
    # Fully polarised beam at 30°: I(θ) = s0 cos²(θ − 30°).
    s = torch.tensor([2.0, 2 * math.cos(math.radians(60)), 2 * math.sin(math.radians(60))]).view(1, 3, 1, 1)
    angles = torch.tensor([0.0, 30.0, 120.0]).deg2rad()
    i = intensities_from_stokes(s, angles).flatten()
    torch.testing.assert_close(i, 2 * torch.cos(angles - math.radians(30)) ** 2)


def test_degenerate_angles_rejected() -> None:
    with pytest.raises(ValueError, match="distinct modulo 180"):
        stokes_from_intensities(torch.rand(3, 2, 2), torch.tensor([0.0, math.pi, 0.5]))
    with pytest.raises(ShapeError, match=r"angles_rad must have shape \(4,\) to match intensities"):
        stokes_from_intensities(torch.rand(4, 2, 2), torch.tensor([0.0, 1.0, 2.0]))
    with pytest.raises(TypeError, match="floating-point"):
        stokes_from_intensities(torch.ones(4, 2, 2, dtype=torch.int32), QUAD)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_dolp_aolp_values(dtype: torch.dtype, device: str) -> None:
    phi = torch.linspace(-89.0, 90.0, 180, dtype=torch.float64).deg2rad()
    rho = torch.linspace(0.05, 1.0, 180, dtype=torch.float64)
    s = torch.stack([torch.ones_like(phi), rho * torch.cos(2 * phi), rho * torch.sin(2 * phi)]).view(3, 1, -1)
    s = s.to(device=device, dtype=dtype)
    torch.testing.assert_close(aolp(s).flatten().double().cpu(), phi, atol=1e-5, rtol=0)
    torch.testing.assert_close(dolp(s).flatten().double().cpu(), rho, atol=1e-6, rtol=0)


def test_aolp_range_and_direction() -> None:
    # s2 > 0 means polarisation between +x and +y (image down): positive AoLP in our convention.
    s = torch.tensor([[1.0, 0.0, 0.5], [1.0, -0.5, 0.0], [1.0, -0.5, -0.0], [1.0, 0.0, -0.5]]).T.reshape(3, 1, 4)
    out = aolp(s).flatten()
    assert out[0] == pytest.approx(math.pi / 4)
    assert out[1] == pytest.approx(math.pi / 2) and out[2] == pytest.approx(math.pi / 2)  # -0.0 maps to +π/2
    assert out[3] == pytest.approx(-math.pi / 4)
    assert bool(((out > -math.pi / 2) & (out <= math.pi / 2)).all())


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_no_nan_or_inf_at_zero(dtype: torch.dtype) -> None:
    s = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [-0.1, 0.0, 0.1], [1.0, 0.0, 0.0]], dtype=dtype).T.reshape(
        3, 1, 4
    )
    s.requires_grad_(True)
    r, p = dolp(s), aolp(s)
    assert torch.isfinite(r).all() and torch.isfinite(p).all()
    assert float(r[0, 0].detach()) == 0.0 and float(p[0, 0].detach()) == 0.0
    (r.sum() + p.sum()).backward()
    assert torch.isfinite(s.grad).all()


def test_gradcheck() -> None:
    s = _random_stokes((2, 3), torch.float64, "cpu", seed=3)[None].requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: (dolp(x), aolp(x)), (s,))
    i = torch.rand(1, 4, 2, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: stokes_from_intensities(x, QUAD.double()), (i,))


def test_polariser_matrix_rows() -> None:
    a = polariser_matrix(torch.tensor([0.0, math.pi / 4], dtype=torch.float64))
    torch.testing.assert_close(a, torch.tensor([[0.5, 0.5, 0.0], [0.5, 0.0, 0.5]], dtype=torch.float64))


def test_dolp_aolp_take_the_stokes_axis() -> None:
    s = _random_stokes((2, 4, 5), torch.float64, "cpu")  # (K, 3, H, W)
    last = s.movedim(1, -1)  # (K, H, W, 3)
    torch.testing.assert_close(dolp(last, dim=-1), dolp(s), rtol=0, atol=0)
    torch.testing.assert_close(aolp(last, dim=3), aolp(s), rtol=0, atol=0)
    torch.testing.assert_close(dolp(s, dim=1, eps=0.5), dolp(s, eps=0.5), rtol=0, atol=0)
    v = torch.tensor([2.0, 0.0, -1.0], dtype=torch.float64)
    assert float(dolp(v, dim=0)) == pytest.approx(0.5) and float(aolp(v, dim=-1)) == pytest.approx(-math.pi / 4)
    with pytest.raises(ShapeError, match=r"\(\*, 3\) \(\(s0, s1, s2\) along dim -1\); got \(4, 2\)"):
        dolp(torch.rand(4, 2), dim=-1)
    with pytest.raises(ShapeError, match="no dim 1"):
        aolp(torch.rand(3), dim=1)


def test_shape_errors_name_the_expected_shape() -> None:
    with pytest.raises(ShapeError, match=r"\(\*, 3, H, W\)"):
        dolp(torch.rand(4, 2, 2))
    with pytest.raises(TypeError, match="torch.Tensor"):
        aolp([[1.0]])  # type: ignore[arg-type]


def test_stokes_from_four_angles_is_the_exact_inverse_of_the_ideal_polarisers() -> None:
    from polarshape.imaging.mosaic import channel_angles_rad
    from polarshape.imaging.stokes import stokes_from_four_angles

    counts = torch.randint(0, 4096, (2, 4, 5, 7), generator=torch.Generator().manual_seed(0)).double()
    general = stokes_from_intensities(counts, channel_angles_rad(dtype=torch.float64))
    torch.testing.assert_close(stokes_from_four_angles(counts), general, rtol=0, atol=1e-9)
    exact = stokes_from_four_angles(counts.float())  # integer counts: every sum exact in float32
    assert torch.equal(exact.double(), general.round(decimals=1))
    out = torch.empty(2, 3, 5, 7)
    assert stokes_from_four_angles(counts.float(), out=out) is out
