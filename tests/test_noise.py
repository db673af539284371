"""The noise model measured from the four-site redundancy against the simulator's true noise."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from polarshape.imaging.mosaic import MosaicLayout
from polarshape.io.capture import load_capture
from polarshape.recover.noise import NoiseModel, demosaic_variance_factor, estimate_noise, quantisation_noise
from polarshape.recover.observations import downsample_inputs
from polarshape.recover.preprocess import preprocess_capture, superpixel_stokes


@pytest.fixture(scope="module")
def two_seeds(render_sphere, tmp_path_factory) -> dict[str, tuple]:  # noqa: ANN001
    """The same 32² super-pixel sphere under 8 lights rendered with two noise seeds, for the default
    sensor and for one whose read noise (40 e⁻) dominates at low signal."""
    out = {}
    for name, read_e in (("default", None), ("read_noise", 40.0)):
        def edit(scene: dict, read_e: float | None = read_e) -> None:
            if read_e is not None:
                scene["sensor"]["read_noise_e"] = read_e
        caps = []
        for seed in (0, 1):
            folder = tmp_path_factory.mktemp(f"noise_{name}_{seed}")
            caps.append(load_capture(render_sphere(folder, width=64, pixel_size_m=4e-4, lights=8, seed=seed, edit=edit)))
        out[name] = tuple(caps)
    return out


def _true_and_predicted(caps: tuple, demosaic: str, lo: float, hi: float) -> tuple[float, float, int]:
    """σ of the observed s0 from the difference of two noise realisations (the truth) and from the
    first capture's noise model, over observations with lo < s0 < hi."""
    a, b = (preprocess_capture(c, demosaic=demosaic, dtype=torch.float64) for c in caps)
    assert a.noise is not None and a.noise.source == "four-site redundancy"
    v = a.valid & b.valid
    s0 = 0.5 * (a.stokes[:, 0] + b.stokes[:, 0])[v]
    diff = (a.stokes[:, 0] - b.stokes[:, 0])[v] / math.sqrt(2.0)
    sel = (s0 > lo) & (s0 < hi)
    return float(diff[sel].std()), float(a.noise.variance(s0[sel]).mean().sqrt()), int(sel.sum())


@pytest.mark.parametrize("demosaic", ["superpixel", "bilinear"])
@pytest.mark.parametrize("sensor", ["default", "read_noise"])
@pytest.mark.parametrize("level", [(0.03, 0.15), (0.4, 0.9)])
def test_noise_model_matches_the_simulated_sensor(two_seeds, demosaic: str, sensor: str, level: tuple) -> None:  # noqa: ANN001
    true, predicted, n = _true_and_predicted(two_seeds[sensor], demosaic, *level)
    assert n >= 150
    assert predicted == pytest.approx(true, rel=0.15), (true, predicted, n)


def test_linear_std_matches_s1_s2_noise(two_seeds) -> None:  # noqa: ANN001
    a, b = (preprocess_capture(c, demosaic="bilinear", dtype=torch.float64) for c in two_seeds["default"])
    v = a.valid & b.valid
    s0 = 0.5 * (a.stokes[:, 0] + b.stokes[:, 0])[v]
    for c in (1, 2):
        true = float(((a.stokes[:, c] - b.stokes[:, c])[v] / math.sqrt(2.0)).std())
        assert float(a.noise.linear_std(s0).pow(2).mean().sqrt()) == pytest.approx(true, rel=0.15)


def test_demosaic_variance_factor_is_the_stencil_sum_of_squares() -> None:
    layout = MosaicLayout.imx250mzr()

    def factor(demosaic: str, at: str = "centre") -> float:
        return demosaic_variance_factor(lambda m: superpixel_stokes(m, layout, demosaic=demosaic, sample_at=at)[0])

    assert factor("superpixel") == pytest.approx(1.0)
    assert factor("bilinear") == pytest.approx(100 / 256)  # weights 9/16, 3/16, 3/16, 1/16 per channel
    assert factor("bilinear", "top_left") == pytest.approx(0.5625)


def test_too_few_samples_fall_back_to_quantisation() -> None:
    d = torch.randn(1, 8, 8) * 0.01
    s0 = torch.full((1, 8, 8), 0.5)
    model = estimate_noise(d, s0, torch.ones(1, 8, 8, dtype=torch.bool), step=1 / 4095)
    assert model == quantisation_noise(1 / 4095)
    assert model.source == "quantisation only"
    assert float(model.std(torch.tensor(0.5))) == pytest.approx(1 / 4095 / math.sqrt(12))


def test_estimate_recovers_a_known_affine_variance() -> None:
    gen = torch.Generator().manual_seed(0)
    s0 = torch.linspace(0.0, 1.0, 4 * 64 * 64, dtype=torch.float64).reshape(4, 64, 64)  # smooth, like images
    read, gain = 4e-6, 2e-4  # of the super-pixel s0; var(d) is 4×
    d = torch.randn(s0.shape, generator=gen, dtype=torch.float64) * (4 * (read + gain * s0)).sqrt()
    model = estimate_noise(d, s0, torch.ones_like(s0, dtype=torch.bool), step=1 / 4095, variance_factor=0.5)
    assert model.read_var == pytest.approx(0.5 * read, rel=0.2)
    assert model.shot_gain == pytest.approx(0.5 * gain, rel=0.1)


def test_downsampled_inputs_carry_a_quarter_of_the_variance(two_seeds) -> None:  # noqa: ANN001
    inputs = preprocess_capture(two_seeds["default"][0], demosaic="superpixel")
    half = downsample_inputs(inputs)
    assert isinstance(half.noise, NoiseModel)
    assert half.noise.read_var == pytest.approx(inputs.noise.read_var / 4)
    assert half.noise.shot_gain == pytest.approx(inputs.noise.shot_gain / 4)


def test_noise_is_filled_for_a_capture_folder(two_seeds) -> None:  # noqa: ANN001
    capture = two_seeds["default"][0]
    assert isinstance(capture.root, Path)
    s0 = torch.tensor([0.0, 0.5], dtype=torch.float64)
    sigma = preprocess_capture(capture).noise.std(s0)
    assert torch.isfinite(sigma).all() and bool((sigma > 0).all()) and float(sigma[1]) > float(sigma[0])


def test_a_large_capture_is_sampled_on_rows_and_columns_of_blocks() -> None:
    """Above max_samples the estimate uses every s-th row/column of blocks: the same model, within the
    sampling error of the smaller sample (the full frame's cost is then that of a small capture)."""
    gen = torch.Generator().manual_seed(1)
    s0 = torch.linspace(0.0, 1.0, 4 * 256 * 256, dtype=torch.float64).reshape(4, 256, 256)
    read, gain = 4e-6, 2e-4
    d = torch.randn(s0.shape, generator=gen, dtype=torch.float64) * (4 * (read + gain * s0)).sqrt()
    usable = torch.ones_like(s0, dtype=torch.bool)
    full = estimate_noise(d, s0, usable, step=1 / 4095, max_samples=1 << 22)
    sampled = estimate_noise(d, s0, usable, step=1 / 4095, max_samples=1 << 15)  # stride 16
    assert sampled.shot_gain == pytest.approx(full.shot_gain, rel=0.05)
    assert sampled.read_var == pytest.approx(full.read_var, rel=0.25)
    assert sampled.shot_gain == pytest.approx(gain, rel=0.1)
