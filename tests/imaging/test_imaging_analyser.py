"""Real analysers: the calibration type, the forward intensity and the calibrated Stokes estimate."""

from __future__ import annotations

import math

import pytest
import torch

from polarshape.errors import ShapeError
from polarshape.imaging.analyser import (
    PolarimetricCalibration,
    analysed_intensity,
    calibrated_pinv,
    calibrated_stokes,
    diattenuation_from_extinction,
    extinction_from_diattenuation,
)
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.mosaic import MosaicLayout

LAYOUT = MosaicLayout.imx250mzr()


def _real(h2: int = 8, w2: int = 12, seed: int = 0, defects: list[tuple[int, int]] | None = None) -> PolarimetricCalibration:
    g = torch.Generator().manual_seed(seed)
    ideal = PolarimetricCalibration.ideal(LAYOUT, h2, w2, bit_depth=12, black_level=64.0)
    mask = torch.zeros(h2, w2, dtype=torch.bool)
    for y, x in defects or []:
        mask[y, x] = True
    return PolarimetricCalibration(
        angle_rad=ideal.angle_rad + math.radians(2.0) * torch.randn(h2, w2, generator=g, dtype=torch.float64),
        diattenuation=torch.full((h2, w2), float(diattenuation_from_extinction(80.0))),
        gain=1.0 + 0.05 * torch.randn(h2, w2, generator=g, dtype=torch.float64),
        black_level=ideal.black_level, defects=mask, bit_depth=12,
    )


def _uniform_blocks(h: int, w: int, seed: int = 1) -> torch.Tensor:
    """(3, H, W) Stokes, constant over each block, DoLP < 1."""
    g = torch.Generator().manual_seed(seed)
    s0 = 0.2 + torch.rand(h, w, generator=g, dtype=torch.float64)
    ang = math.pi * torch.rand(h, w, generator=g, dtype=torch.float64)
    p = 0.9 * torch.rand(h, w, generator=g, dtype=torch.float64)
    return torch.stack([s0, s0 * p * torch.cos(2 * ang), s0 * p * torch.sin(2 * ang)])


def test_extinction_diattenuation_round_trip() -> None:
    d = diattenuation_from_extinction(torch.tensor([1.0, 150.0, math.inf]))
    assert d.tolist() == pytest.approx([0.0, 149 / 151, 1.0])
    assert extinction_from_diattenuation(d)[1].item() == pytest.approx(150.0)
    assert math.isinf(extinction_from_diattenuation(1.0).item())


def test_ideal_calibration_matches_todays_stokes() -> None:
    mosaic = torch.rand(2, 8, 12, dtype=torch.float64)
    cal = PolarimetricCalibration.ideal(LAYOUT, 8, 12, bit_depth=12)
    s, ok = calibrated_stokes(mosaic, cal, LAYOUT)
    torch.testing.assert_close(s, stokes_from_mosaic(mosaic, LAYOUT, "superpixel"))
    assert bool(ok.all())
    full, ok_full = calibrated_stokes(mosaic, cal, LAYOUT, method="bilinear")
    torch.testing.assert_close(full, stokes_from_mosaic(mosaic, LAYOUT, "bilinear"))
    assert bool(ok_full.all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_for_a_non_ideal_analyser(dtype: torch.dtype) -> None:
    cal = _real()
    truth = _uniform_blocks(4, 6)  # (3, H, W)
    full = truth.repeat_interleave(2, -1).repeat_interleave(2, -2)  # (3, 2H, 2W) constant per block
    mosaic = analysed_intensity(full, cal.angle_rad, cal.diattenuation, cal.gain).to(dtype)
    s, ok = calibrated_stokes(mosaic, cal, LAYOUT)
    assert s.dtype == dtype and bool(ok.all())
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(s.double(), truth, atol=tol, rtol=tol)
    naive = stokes_from_mosaic(mosaic.double(), LAYOUT, "superpixel")  # ignores the calibration
    assert float((naive - truth).abs().max()) > 1e-2


def test_bilinear_exact_for_a_uniform_field() -> None:
    cal = _real(defects=[(3, 4)])
    s_true = torch.tensor([0.6, 0.1, -0.2], dtype=torch.float64)
    full = s_true[:, None, None].expand(3, *cal.shape)
    mosaic = analysed_intensity(full, cal.angle_rad, cal.diattenuation, cal.gain)
    mosaic[3, 4] = 0.99  # a hot pixel: ignored
    s, ok = calibrated_stokes(mosaic, cal, LAYOUT, method="bilinear")
    assert bool(ok.all())
    torch.testing.assert_close(s, full, atol=1e-12, rtol=0)


def test_defects_three_sites_suffice_two_invalidate() -> None:
    cal = _real(defects=[(0, 0), (2, 2), (2, 3)])  # block (0, 0): one; block (1, 1): two
    truth = _uniform_blocks(4, 6)
    full = truth.repeat_interleave(2, -1).repeat_interleave(2, -2)
    mosaic = analysed_intensity(full, cal.angle_rad, cal.diattenuation, cal.gain)
    mosaic[0, 0] = mosaic[2, 2] = mosaic[2, 3] = 1.0  # defective counts carry nothing
    s, ok = calibrated_stokes(mosaic, cal, LAYOUT)
    assert not bool(ok[1, 1]) and int((~ok).sum()) == 1
    torch.testing.assert_close(s[:, 0, 0], truth[:, 0, 0], atol=1e-12, rtol=0)
    assert s[:, 1, 1].abs().max().item() == 0.0 and bool(torch.isfinite(s).all())
    p, valid = calibrated_pinv(cal, LAYOUT)
    assert p.shape == (4, 6, 3, 4) and torch.equal(valid, ok)


def test_shape_and_layout_errors() -> None:
    cal = _real()
    with pytest.raises(ShapeError, match="calibration's size"):
        calibrated_stokes(torch.zeros(8, 8, dtype=torch.float64), cal, LAYOUT)
    with pytest.raises(ValueError, match="another mosaic layout"):
        calibrated_stokes(torch.zeros(8, 12, dtype=torch.float64), cal, LAYOUT.shifted(1, 0))
    with pytest.raises(ValueError, match="method"):
        calibrated_pinv(cal, LAYOUT, method="nearest")  # type: ignore[arg-type]


def test_calibration_validation() -> None:
    ideal = PolarimetricCalibration.ideal(LAYOUT, 4, 4, bit_depth=12)
    assert ideal.shape == (4, 4) and bool(torch.isinf(ideal.extinction_ratio()).all())
    with pytest.raises(ShapeError):
        PolarimetricCalibration(angle_rad=torch.zeros(3, 4, dtype=torch.float64), diattenuation=torch.ones(3, 4),
                                gain=torch.ones(3, 4), black_level=torch.zeros(3, 4),
                                defects=torch.zeros(3, 4, dtype=torch.bool), bit_depth=12)
    with pytest.raises(ValueError, match="diattenuation"):
        PolarimetricCalibration(angle_rad=ideal.angle_rad, diattenuation=ideal.diattenuation * 0, gain=ideal.gain,
                                black_level=ideal.black_level, defects=ideal.defects, bit_depth=12)
    with pytest.raises(ValueError, match="NaN"):
        PolarimetricCalibration(angle_rad=ideal.angle_rad, diattenuation=ideal.diattenuation,
                                gain=ideal.gain * math.nan, black_level=ideal.black_level, defects=ideal.defects,
                                bit_depth=12)
    rows = ideal.rows()
    assert rows.shape == (4, 4, 3) and rows[..., 0].eq(0.5).all()


def test_ideal_equivalent_sites() -> None:
    from polarshape.imaging.analyser import ideal_equivalent_sites
    from polarshape.imaging.mosaic import split_mosaic

    mosaic = torch.rand(8, 12, dtype=torch.float64)
    ideal = PolarimetricCalibration.ideal(LAYOUT, 8, 12, bit_depth=12)
    torch.testing.assert_close(ideal_equivalent_sites(mosaic, ideal, LAYOUT), split_mosaic(mosaic, LAYOUT))
    cal = _real(defects=[(0, 0)])
    truth = _uniform_blocks(4, 6)
    full = truth.repeat_interleave(2, -1).repeat_interleave(2, -2)
    real = analysed_intensity(full, cal.angle_rad, cal.diattenuation, cal.gain)
    sites = ideal_equivalent_sites(real, cal, LAYOUT)  # (4, H, W): the ideal sensor's view of the same field
    ideal_view = split_mosaic(analysed_intensity(full, ideal.angle_rad, 1.0, 1.0), LAYOUT)
    torch.testing.assert_close(sites, ideal_view, atol=1e-12, rtol=0)
