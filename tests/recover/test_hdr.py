"""Exposure brackets merged into one radiance per site (recover/hdr.py) and through preprocessing."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.errors import CaptureError
from polarshape.io.capture import CAPTURE_FORMAT_BRACKETS, Capture, load_capture, parse_capture_spec
from polarshape.recover.hdr import SiteNoise, merge_exposures, merge_light
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[2]
TOP = 4095.0
RATIOS = torch.tensor([1.0, 1 / 8, 1 / 64], dtype=torch.float64)
NOISE = SiteNoise(read_var=(2.0 / TOP) ** 2, gain=1.0 / TOP)  # 2 counts read noise, ~1 e⁻ per count shot noise


def _expose(radiance: torch.Tensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N) values (fractions of each frame's full scale) and clipped flags of ``radiance`` (N,) at RATIOS."""
    g = torch.Generator().manual_seed(seed)
    mean = RATIOS[:, None] * radiance[None]  # (B, N)
    noisy = mean + NOISE.variance(mean).sqrt() * torch.randn(mean.shape, generator=g, dtype=torch.float64)
    counts = torch.clamp(torch.round(noisy * TOP), 0, TOP)
    return counts / TOP, counts >= TOP


def test_merge_recovers_a_known_radiance_beyond_full_scale() -> None:
    truth = torch.linspace(0.05, 50.0, 20000, dtype=torch.float64)  # up to 50× the reference's full scale
    values, clipped = _expose(truth, 0)
    merged = merge_exposures(values, clipped, RATIOS, NOISE, dark_threshold=0.005)
    assert not bool(merged.clipped.any())
    rel = (merged.radiance - truth) / truth
    bias = [float(part.mean()) for part in torch.tensor_split(rel, 10)]  # unbiased everywhere, also above 1
    assert max(abs(b) for b in bias) < 3e-3, bias
    z = (merged.radiance - truth) / merged.variance.sqrt()
    assert 0.85 < float(z.std()) < 1.15  # the variance it reports is the error it makes
    # noise weighting: below the reference's clipping level the merged value beats the short exposure alone
    low = truth < 0.8
    short_only = values[1, low] / RATIOS[1]
    assert float((merged.radiance[low] - truth[low]).pow(2).mean()) < 0.5 * float((short_only - truth[low]).pow(2).mean())
    # and it uses the reference exposure there (which alone would do as well)
    ref_only = values[0, low]
    assert float((merged.radiance[low] - truth[low]).pow(2).mean()) <= 1.05 * float((ref_only - truth[low]).pow(2).mean())
    assert bool(merged.reference_used[truth < 0.8].all()) and not bool(merged.reference_used[truth > 1.1].any())


def test_sites_clipped_in_every_exposure_stay_flagged() -> None:
    truth = torch.tensor([0.5, 10.0, 70.0, 200.0], dtype=torch.float64)
    values, clipped = _expose(truth, 1)
    merged = merge_exposures(values, clipped, RATIOS, NOISE, dark_threshold=0.005)
    assert merged.clipped.tolist() == [False, False, True, True]
    assert float(merged.radiance[2]) == pytest.approx(64.0, rel=1e-6)  # the shortest exposure's clipped value


def test_dark_samples_of_short_exposures_are_left_out() -> None:
    truth = torch.full((4000,), 0.2, dtype=torch.float64)
    values, clipped = _expose(truth, 2)
    values = values.clone()
    values[2] += 3.0 / TOP  # a black-level error of 3 counts in the 1/64 frame: 0.047 of the radiance there
    merged = merge_exposures(values, clipped, RATIOS, NOISE, dark_threshold=0.005)  # 1/64 frame below 0.005: dark
    assert abs(float(merged.radiance.mean()) - 0.2) < 2e-3


def _scene(n: int, exposures: list[float] | None, *, reference_us: float = 40000.0) -> dict:
    d = yaml.safe_load((REPO / "configs/scenes/sphere.yaml").read_text())
    d["camera"].update(width=2 * n, height=2 * n, pixel_size_m=1e-4 * 128 / n, exposure_us=reference_us)
    if exposures is not None:
        d["camera"].update(exposures_us=exposures, exposure_us=exposures[0])
    d["objects"][0]["material"].update(alpha=0.03, k_b=0.135)
    d["lights"] = d["lights"][:6]
    return d


@pytest.fixture(scope="module")
def bracketed() -> Capture:
    """A 32² glossy sphere (α 0.03) whose highlights clip at the 40 ms reference, with 5 and 0.625 ms brackets."""
    return SimulatedCamera(parse_scene_config(_scene(32, [40000.0, 5000.0, 625.0])), seed=0).render_capture(progress=False)


def test_preprocess_merges_brackets(bracketed: Capture) -> None:
    assert bracketed.spec.format == CAPTURE_FORMAT_BRACKETS and bracketed.brackets.shape[1] == 2
    single = dataclasses.replace(bracketed, spec=bracketed.spec.model_copy(update={"lights": tuple(
        light.model_copy(update={"brackets": ()}) for light in bracketed.spec.lights)}), brackets=None)
    merged_inputs = preprocess_capture(bracketed)
    single_inputs = preprocess_capture(single)
    in_mask = merged_inputs.mask.unsqueeze(0)
    assert int((single_inputs.saturated & in_mask).sum()) > 20  # the highlights clip at the reference exposure
    assert int((merged_inputs.saturated & in_mask).sum()) == 0
    s0 = merged_inputs.stokes[:, 0]
    assert float(s0[merged_inputs.valid].max()) > 2.0  # highlights kept, beyond the reference's full scale
    # where the reference is unclipped the merged radiance is the reference's within its noise
    both = single_inputs.valid & merged_inputs.valid
    diff = (s0 - single_inputs.stokes[:, 0])[both]
    assert float(diff.abs().median()) < 3e-3
    # the merged highlight observations are kept (not mistaken for edges by the mixed-block test)
    assert int((merged_inputs.valid & ~single_inputs.valid & ~single_inputs.saturated).sum()) < 0.02 * int(both.sum())


def test_one_exposure_is_bit_identical_to_format_1(bracketed: Capture) -> None:
    one = dataclasses.replace(bracketed, brackets=None, spec=bracketed.spec.model_copy(update={"lights": tuple(
        light.model_copy(update={"brackets": ()}) for light in bracketed.spec.lights)}))
    v1 = dataclasses.replace(one, spec=parse_capture_spec({
        "format": "polarshape-capture/1", "camera": one.spec.camera.model_dump(mode="json", exclude_none=True),
        "lights": [light.model_dump(mode="json", exclude_none=True, exclude={"exposure_us", "brackets"})
                   for light in one.spec.lights]}))
    a, b = preprocess_capture(one), preprocess_capture(v1)
    assert torch.equal(a.stokes, b.stokes) and torch.equal(a.valid, b.valid) and a.noise == b.noise


def test_mixed_up_exposures_are_refused(bracketed: Capture, tmp_path: Path) -> None:
    lights = list(bracketed.spec.lights)
    b = lights[2].brackets
    lights[2] = lights[2].model_copy(update={"brackets": (b[0].model_copy(update={"exposure_us": b[1].exposure_us}),
                                                         b[1].model_copy(update={"exposure_us": b[0].exposure_us}))})
    swapped = dataclasses.replace(bracketed, spec=bracketed.spec.model_copy(update={"lights": tuple(lights)}))
    with pytest.raises(CaptureError, match=r"lights\[2\].*frames of different exposures are mixed up"):
        preprocess_capture(swapped)
    merge_light(bracketed, 2, NOISE, dark_threshold=0.005)  # the right order passes


def test_simulate_writes_and_reloads_format_2(bracketed: Capture, tmp_path: Path) -> None:
    from polarshape.io.capture import write_capture

    write_capture(tmp_path / "cap", bracketed)
    loaded = load_capture(tmp_path / "cap")
    np.testing.assert_array_equal(loaded.spec.exposures_us[0], [40000.0, 5000.0, 625.0])
    np.testing.assert_array_equal(loaded.brackets, bracketed.brackets)
    assert (tmp_path / "cap" / "frames" / "000_b2.png").is_file()


def test_a_site_clipped_in_every_exposure_flags_its_observation() -> None:
    """Through preprocessing: a block clipped at every exposure is saturated; one clipped only at the
    reference is not (its shorter exposure is read instead)."""
    k, n = 3, 16
    lights = [{"direction": [0.0, 0.0, -1.0], "frame": f"frames/{i:03d}.png", "exposure_us": 4000.0,
               "brackets": [{"frame": f"frames/{i:03d}_b1.png", "exposure_us": 1000.0}]} for i in range(k)]
    spec = parse_capture_spec({"format": CAPTURE_FORMAT_BRACKETS,
                               "camera": {"projection": "orthographic", "bit_depth": 12}, "lights": lights})
    rng = np.random.default_rng(0)
    radiance = np.full((k, 2 * n, 2 * n), 0.4) + rng.normal(0, 0.002, (k, 2 * n, 2 * n))  # fraction at the reference
    radiance[:, 4:6, 4:6] = 2.0  # clipped at the reference only
    radiance[:, 20:22, 20:22] = 9.0  # clipped at both
    frames, short = (np.clip(np.rint(radiance * r * 4095), 0, 4095).astype(np.uint16) for r in (1.0, 0.25))
    capture = Capture(spec=spec, frames=frames, brackets=short[:, None],
                      mask=np.ones((n, n), dtype=bool))
    inputs = preprocess_capture(capture, demosaic="superpixel", polarisation_check=False)
    assert bool(inputs.saturated[:, 10, 10].all()) and not bool(inputs.valid[:, 10, 10].any())
    assert not bool(inputs.saturated[:, 2, 2].any()) and bool(inputs.valid[:, 2, 2].all())
    assert float(inputs.stokes[0, 0, 2, 2]) == pytest.approx(4.0, rel=0.01)  # s0 = ½ Σ of four sites at 2.0
    assert int(inputs.saturated.sum()) == k
