"""Sensor model: noise statistics, reproducibility, saturation, bit depths, gain, exposure."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarshape.imaging.pixels import bit_depth_of
from polarshape.scene.sensor import SensorModel

SHAPE = (512, 512)


def _flat(value: float) -> torch.Tensor:
    return torch.full(SHAPE, value, dtype=torch.float64)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("shot_noise", ["poisson", "gaussian"])
def test_mean_and_variance_follow_the_model(shot_noise):
    model = SensorModel(full_well_e=20000.0, read_noise_e=6.0, e_per_count_12bit=2.0, electrons_per_radiance=1000.0,
                        reference_exposure_us=1000.0, black_level_12bit=64.0, shot_noise=shot_noise)
    radiance = 0.8  # -> λ = 800 e- at the reference exposure
    counts = model.expose(_flat(radiance), exposure_us=1000.0, bit_depth=12, generator=_gen(3)).astype(np.float64)
    lam = 800.0
    g = 2.0  # e- per count
    expected_mean = lam / g + 64.0
    expected_var = (lam + 6.0**2) / g**2 + 1.0 / 12.0  # shot + read, then rounding
    n = counts.size
    assert counts.mean() == pytest.approx(expected_mean, abs=4 * np.sqrt(expected_var / n) + 1e-3)
    assert counts.var() == pytest.approx(expected_var, rel=4 * np.sqrt(2.0 / n))


def test_read_noise_alone_has_its_variance():
    model = SensorModel(read_noise_e=3.0, e_per_count_12bit=1.0, black_level_12bit=100.0, shot_noise="none")
    counts = model.expose(_flat(0.0), exposure_us=10000.0, bit_depth=12, generator=_gen(0)).astype(np.float64)
    assert counts.mean() == pytest.approx(100.0, abs=0.05)
    assert counts.var() == pytest.approx(9.0 + 1 / 12, rel=0.02)


def test_poisson_shot_noise_is_integer_electrons_at_low_light():
    model = SensorModel(read_noise_e=0.0, e_per_count_12bit=1.0, electrons_per_radiance=1.0, reference_exposure_us=1.0)
    counts = model.expose(_flat(2.0), exposure_us=1.0, generator=_gen(5))
    p0 = np.mean(counts == 0)
    assert p0 == pytest.approx(np.exp(-2.0), abs=0.005)  # Poisson P(0) at λ = 2


def test_same_seed_is_bit_exact_and_other_seeds_differ():
    model = SensorModel()
    radiance = 0.1 * torch.rand(64, 64, generator=_gen(1), dtype=torch.float64)  # below saturation
    a = model.expose(radiance, exposure_us=10000.0, generator=_gen(42))
    b = model.expose(radiance, exposure_us=10000.0, generator=_gen(42))
    c = model.expose(radiance, exposure_us=10000.0, generator=_gen(43))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("bit_depth,dtype", [(8, np.uint8), (10, np.uint16), (12, np.uint16), (16, np.uint16)])
def test_saturation_clips_at_the_top_count(bit_depth, dtype):
    model = SensorModel(read_noise_e=2.0)
    counts = model.expose(_flat(1e3), exposure_us=10000.0, bit_depth=bit_depth, generator=_gen(0))
    assert counts.dtype == dtype
    top = counts.max()
    assert top <= 2**bit_depth - 1
    # full well maps to (about) the ADC maximum by default; 16-bit holds 12 significant bits shifted up
    assert top >= (2**bit_depth - 1) - 2 ** max(bit_depth - 12, 0) * 16


def test_full_well_saturates_below_the_adc_range():
    model = SensorModel(full_well_e=1000.0, e_per_count_12bit=1.0, read_noise_e=0.0, shot_noise="none")
    counts = model.expose(_flat(10.0), exposure_us=10000.0, bit_depth=12)
    assert np.all(counts == 1000)


def test_bit_depth_gain_and_exposure_scale_counts():
    model = SensorModel(read_noise_e=0.0, shot_noise="none", e_per_count_12bit=1.0, electrons_per_radiance=100.0,
                        full_well_e=1e6, black_level_12bit=16.0)
    rad = _flat(10.0)  # 1000 e-
    c12 = model.expose(rad, exposure_us=10000.0, bit_depth=12)
    assert np.all(c12 == 1016)
    assert np.all(model.expose(rad, exposure_us=10000.0, bit_depth=8) == round(1016 / 16))
    assert np.all(model.expose(rad, exposure_us=10000.0, bit_depth=16) == 1016 * 16)
    assert np.all(model.expose(rad, exposure_us=20000.0, bit_depth=12) == 2016)
    assert np.all(model.expose(rad, exposure_us=10000.0, gain_db=20 * np.log10(2.0), bit_depth=12) == 2016)
    assert model.black_level(8) == pytest.approx(1.0)


def test_negative_radiance_counts_as_dark():
    model = SensorModel(read_noise_e=0.0)
    assert np.all(model.expose(_flat(-1.0), exposure_us=1.0) == 0)


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="bit_depth"):
        SensorModel().expose(_flat(0.1), exposure_us=1.0, bit_depth=14)
    with pytest.raises(ValueError, match="exposure_us"):
        SensorModel().expose(_flat(0.1), exposure_us=0.0)
    with pytest.raises(ValueError, match="full_well_e"):
        SensorModel(full_well_e=0.0)
    with pytest.raises(ValueError, match="shot_noise"):
        SensorModel(shot_noise="laplace")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="PolarizeMono14"):
        bit_depth_of("PolarizeMono14")
    formats = ("PolarizeMono8", "PolarizeMono12p", "PolarizeMono12Packed", "PolarizeMono16")
    assert [bit_depth_of(f) for f in formats] == [8, 12, 12, 16]
