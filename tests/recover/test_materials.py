"""Tests of polarshape.recover.materials: Potts labelling, per-pixel losses, and the several-material
solve on a small sphere cap whose two halves are different materials."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch

from polarshape.brdf import baek_pbrdf_stokes, fmbrdf_stokes
from polarshape.brdf.params import FMBRDFParams
import polarshape.recover.materials as materials_module
from polarshape.recover.coarse_to_fine import FMBRDFState, TableCache, solve_fmbrdf
from polarshape.recover.materials import (
    MIN_HELD_OUT_GAIN, boundary_pixels, material_tables, pixel_losses, potts_energy, potts_icm, region_inputs,
    select_materials, solve_materials,
)
from polarshape.recover.observations import RecoveryInputs, flatten_observations
from polarshape.recover.options import RecoveryOptions

GLOSSY = FMBRDFParams(ior=1.6, alpha=0.08, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5)
ROUGH = FMBRDFParams(ior=1.45, alpha=0.45, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5)


def _cap_inputs(n: int, materials: tuple[FMBRDFParams, ...], *, k: int = 12, noise: float = 2e-3,
                seed: int = 0, render: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor] | None = None
                ) -> tuple[RecoveryInputs, torch.Tensor, torch.Tensor]:
    """A sphere cap (n × n pixels, K directional lights) whose right half (x > 0) is ``materials[-1]``
    and left half ``materials[0]`` (or all of it rendered by ``render(normals, lights, view)`` → Stokes
    (K, n, n, 3)), with Gaussian noise; returns inputs, true normals, true labels."""
    y, x = torch.meshgrid(torch.linspace(-0.8, 0.8, n, dtype=torch.float64),
                          torch.linspace(-0.8, 0.8, n, dtype=torch.float64), indexing="ij")
    mask = x * x + y * y < 0.6
    normals = torch.nn.functional.normalize(torch.stack([x, y, -(1 - x * x - y * y).clamp_min(0.05).sqrt()], -1),
                                            dim=-1)
    zen = torch.tensor([10, 20, 20, 35, 35, 35, 50, 50, 50, 65, 65, 65], dtype=torch.float64)[:k] * math.pi / 180
    azi = torch.tensor([0, 120, 240, 30, 150, 270, 90, 210, 330, 0, 120, 240], dtype=torch.float64)[:k] * math.pi / 180
    dirs = torch.stack([zen.sin() * azi.cos(), zen.sin() * azi.sin(), -zen.cos()], -1)  # (K, 3)
    lights = dirs[:, None, None].expand(k, n, n, 3)
    view = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(n, n, 3)
    labels = torch.where(x > 0, len(materials) - 1, 0)
    s = torch.zeros(k, n, n, 3, dtype=torch.float64)
    for m, p in enumerate(materials):
        sm = fmbrdf_stokes(normals.unsqueeze(0), lights, view.unsqueeze(0), **p.as_kwargs())  # (K, n, n, 3)
        s = torch.where((labels == m)[None, ..., None], sm, s)
    if render is not None:
        s = render(normals.unsqueeze(0), lights, view.unsqueeze(0))
    gen = torch.Generator().manual_seed(seed)
    s = 0.25 * s + noise * torch.randn(s.shape, generator=gen, dtype=torch.float64)
    valid = mask.expand(k, n, n) & (s[..., 0] > 5 * noise)
    inputs = RecoveryInputs(s.permute(0, 3, 1, 2).contiguous(), valid, torch.zeros_like(valid), mask, lights,
                            torch.ones(k, n, n, dtype=torch.float64), view, noise, True)
    return inputs, torch.where(mask[..., None], normals, torch.nan), torch.where(mask, labels, -1)


def _start(normals: torch.Tensor, degrees: float = 4.0) -> torch.Tensor:
    """The true normals (H, W, 3) tilted at random by about ``degrees``: a photometric-stereo-like start."""
    gen = torch.Generator().manual_seed(3)
    tilt = math.radians(degrees) * torch.randn(normals.shape, generator=gen, dtype=normals.dtype)
    return torch.nn.functional.normalize(torch.nan_to_num(normals, nan=0.0) + tilt, dim=-1)


def test_potts_icm_cleans_noisy_labels() -> None:
    gen = torch.Generator().manual_seed(1)
    truth = torch.zeros(20, 20, dtype=torch.int64)
    truth[:, 10:] = 1
    costs = torch.stack([(truth != 0).double(), (truth != 1).double()]) * 2.0
    costs = costs + 1.5 * torch.randn(costs.shape, generator=gen, dtype=torch.float64)  # noisy evidence
    pixels = torch.ones(20, 20, dtype=torch.bool)
    alone = potts_icm(costs, pixels, 0.0)
    smooth = potts_icm(costs, pixels, 1.0)
    assert bool((alone == costs.argmin(0)).all())  # weight 0: each pixel its cheapest label
    assert (smooth == truth).double().mean() > (alone == truth).double().mean()
    assert (smooth == truth).double().mean() > 0.95
    assert potts_energy(smooth, pixels) < potts_energy(alone, pixels)
    assert potts_energy(truth, pixels) == 20 + 2 * 19  # one straight edge: 20 side pairs, 38 diagonal pairs
    off = pixels.clone()
    off[0, 0] = False
    assert int(potts_icm(costs, off, 1.0)[0, 0]) == -1


def test_boundary_pixels_mark_the_material_edge() -> None:
    labels = torch.zeros(6, 6, dtype=torch.int64)
    labels[:, 3:] = 1
    edge = boundary_pixels(labels, torch.ones(6, 6, dtype=torch.bool))
    assert bool(edge[:, 2:4].all()) and not bool(edge[:, :2].any()) and not bool(edge[:, 4:].any())
    assert not bool(boundary_pixels(torch.zeros(6, 6, dtype=torch.int64), torch.ones(6, 6, dtype=torch.bool)).any())


def test_pixel_losses_prefer_each_pixels_own_material() -> None:
    inputs, normals, labels = _cap_inputs(16, (ROUGH, GLOSSY), noise=1e-4)
    obs = flatten_observations(inputs, inputs.mask)
    scaled = [FMBRDFParams(**{**p.as_kwargs(), "k_s": 0.25, "k_b": 0.125}) for p in (ROUGH, GLOSSY)]
    loss = pixel_losses(scaled, normals[inputs.mask], obs, per_pixel_albedo=True, polarised=True, delta=0.01)
    assert loss.shape == (2, int(inputs.mask.sum()))
    truth = labels[inputs.mask]
    lit = (obs.weight.sum(1) >= 6)  # pixels seen by enough lights to tell
    assert (loss.argmin(0)[lit] == truth[lit]).double().mean() > 0.9


@pytest.mark.slow
def test_one_material_stays_one_and_materials_1_is_todays_solve() -> None:
    inputs, normals, _ = _cap_inputs(14, (ROUGH,))
    ps = _start(normals)
    options = RecoveryOptions(max_outer_iterations=4, subsample_pixels=128, fit_kappa=False)
    today, _ = solve_fmbrdf(inputs, ps, options)
    one = solve_materials(inputs, ps, options.model_copy(update={"materials": 1}))
    assert len(one.params) == 1 and one.selection == []
    assert torch.equal(torch.nan_to_num(one.normals), torch.nan_to_num(today.normals))  # bit for bit
    assert one.params[0] == today.params
    auto = solve_materials(inputs, ps, options)
    assert len(auto.params) == 1, auto.selection
    assert auto.selection and not auto.selection[0]["kept"]  # a split was tried and did not pay
    tried = auto.selection[0]  # refused by the early test (the 80² benchmark captures) or held out
    assert tried["decided"] == "early" or tried["held_out_gain"] < MIN_HELD_OUT_GAIN, auto.selection
    assert torch.equal(torch.nan_to_num(auto.normals), torch.nan_to_num(today.normals))
    assert bool((auto.labels[inputs.mask] == 0).all()) and not bool(auto.mixed.any())


@pytest.mark.slow
def test_two_materials_found_and_assigned() -> None:
    inputs, normals, labels = _cap_inputs(24, (ROUGH, GLOSSY), noise=2e-4)
    ps = _start(normals)
    options = RecoveryOptions(max_outer_iterations=6, subsample_pixels=256, fit_kappa=False)
    got = solve_materials(inputs, ps, options)
    assert len(got.params) == 2, got.selection
    first = got.selection[0]
    assert first["decided"] == "held-out" and first["kept"]
    assert first["held_out_gain"] > MIN_HELD_OUT_GAIN, got.selection  # the lights that did not label agree
    glossy = min(range(2), key=lambda m: got.params[m].alpha)
    predicted = torch.where(got.labels == glossy, 1, 0)
    inner = inputs.mask & ~boundary_pixels(labels, inputs.mask) & ~got.mixed
    assert (predicted[inner] == labels[inner]).double().mean() > 0.9
    # 24² pixels over ±50° put the glossy lobe (≈ 5° wide) on one or two pixels: α is told apart, not
    # measured (benchmarks/materials.py measures it on the 80² blob: within 6 %)
    assert got.params[glossy].alpha < 0.15 and 0.25 < got.params[1 - glossy].alpha < 0.8
    assert bool(got.mixed.any())
    region = region_inputs(inputs, got.labels == glossy)
    assert int(region.mask.sum()) == int((got.labels == glossy).sum())
    assert not bool((region.valid & ~region.mask).any())


def test_the_materials_option_is_auto_or_a_small_number() -> None:
    from pydantic import ValidationError

    assert RecoveryOptions().materials == "auto"
    assert RecoveryOptions(materials=2).materials == 2
    for bad in (0, 5, "two", 2.0):
        with pytest.raises(ValidationError, match="materials"):
            RecoveryOptions(materials=bad)


@pytest.mark.slow
def test_a_material_the_model_does_not_explain_stays_one() -> None:
    """Baek's pBRDF (GGX) rendered, the FMBRDF fitted: one material, and a split made anyway scores
    below the threshold on the held-out lights. (On this small cap the split buys nothing even
    in-sample; benchmarks/materials.py --cases mismatch_... measures Baek spheres and a blob at 80²,
    where it buys 14–38 % in-sample and predicts the held-out lights 5–26 % better.)"""
    def baek(normals: torch.Tensor, lights: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        return baek_pbrdf_stokes(normals, lights, view, ior=1.5, k_s=1.0, k_d=0.5, alpha=0.25, distribution="ggx")

    inputs, normals, _ = _cap_inputs(16, (ROUGH,), noise=5e-4, render=baek)
    options = RecoveryOptions(max_outer_iterations=4, subsample_pixels=128, fit_kappa=False)
    state, _ = solve_fmbrdf(inputs, _start(normals), options)
    chosen, records, _, _ = select_materials(inputs, state, options, wanted=None)
    assert len(chosen) == 1 and not records[0]["kept"], records
    # the split made anyway (materials: 2): its decision statistic stays below the threshold
    _, forced, _, _ = select_materials(inputs, state, options, wanted=2)
    assert forced[0]["decided"] == "held-out", forced
    assert forced[0]["held_out_gain"] < MIN_HELD_OUT_GAIN, forced


def test_material_tables_are_built_once_per_material() -> None:
    inputs, normals, _ = _cap_inputs(8, (ROUGH,), noise=1e-4)
    obs = flatten_observations(inputs, inputs.mask)
    cache = TableCache()
    first = material_tables(ROUGH, torch.device("cpu"), cache)
    assert material_tables(ROUGH, torch.device("cpu"), cache) is first
    assert material_tables(FMBRDFParams(**{**ROUGH.as_kwargs(), "k_s": 3.0}), torch.device("cpu"), cache) is first
    assert material_tables(ROUGH, torch.device("cpu"), cache, n_grid=33) is not first
    assert material_tables(GLOSSY, torch.device("cpu"), cache) is not first
    assert len(cache) == 3 and cache.builds == 3 and cache.hits == 2
    kw = {"per_pixel_albedo": True, "polarised": True, "delta": 0.01}
    assert torch.equal(pixel_losses([ROUGH, GLOSSY], normals[inputs.mask], obs, cache=cache, **kw),
                       pixel_losses([ROUGH, GLOSSY], normals[inputs.mask], obs, **kw))



def test_the_selection_takes_the_solve_s_tables_and_decides_as_without_them() -> None:
    """The one-material solve leaves its material's tables in the run's cache: the model choice builds
    them no more (only its start lobes and new materials) and decides, bit for bit, as with tables
    of its own."""
    inputs, normals, _ = _cap_inputs(12, (ROUGH,), noise=2e-4)
    options = RecoveryOptions(max_outer_iterations=3, subsample_pixels=64, fit_kappa=False)
    tables = TableCache()
    state, _ = solve_fmbrdf(inputs, _start(normals), options, tables=tables)
    builds = tables.builds
    shared = select_materials(inputs, state, options, wanted=None, tables=tables)
    own = select_materials(inputs, state, options, wanted=None)
    assert shared == own and shared[1], shared[1]
    assert shared[1][0]["decided"] == "early", shared[1]  # no new material: no table built for the run
    assert tables.builds == builds and tables.hits >= 2, (tables.builds, builds, tables.hits)
