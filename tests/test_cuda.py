"""Every stage on ``device: cuda`` against the CPU (issue 13): the FMBRDF forward model and its gradients,
preprocessing to Stokes, robust PS, ``recover_normals`` (one material, several, the joint solve), the
near-field stage, integration of a device result and a whole ``polarshape run``.

Each test runs once per device: ``cpu`` (always, so CI runs the bodies and their checks of device and
finiteness) and ``cuda`` (marked ``cuda``; skipped with the reason when torch sees no GPU). The reference
is always computed on the CPU, in float64 where the stage allows it, so the comparisons measure the
device, not the precision. The cheap stages run twice on ``cpu`` too (they must repeat themselves); the
solves run once there (:func:`_reference_and`) to keep CI small. Kept tiny: the CPU variants are part of CI.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.brdf import fmbrdf_stokes
from polarshape.checks import to_numpy
from polarshape.config import parse_run_config
from polarshape.io.capture import Capture
from polarshape.metrics import angular_error_deg
from polarshape.nearfield import NearFieldOptions, refine_near_field
from polarshape.normals import NormalsResult, initial_normals, recover_normals
from polarshape.pipeline import run_pipeline
from polarshape.recover.materials import solve_materials
from polarshape.recover.observations import RecoveryInputs
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import capture_camera, preprocess_capture
from polarshape.scene.config import parse_scene_config
from polarshape.surface.integrate import integrate_normals

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "configs" / "scenes" / "sphere.yaml"
T = TypeVar("T")

DEVICES = [
    pytest.param("cpu", id="cpu"),
    pytest.param("cuda", id="cuda", marks=[
        pytest.mark.cuda,
        pytest.mark.skipif(not torch.cuda.is_available(),
                           reason=f"needs a CUDA device (torch {torch.__version__}: torch.cuda.is_available() is False)"),
    ]),
]


def _on(x: torch.Tensor, device: str) -> None:
    assert x.device.type == torch.device(device).type, f"{tuple(x.shape)} tensor on {x.device}, expected {device}"


def _sphere_capture(folder: Path, *, raw: int = 64, lights: int = 8, seed: int = 3) -> Capture:
    """The shipped glossy sphere at ``raw``² raw pixels (``raw``/2 super-pixels) under its first ``lights`` lights."""
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=raw, height=raw, pixel_size_m=1e-4 * 256 / raw)
    scene["lights"] = scene["lights"][:lights]
    with SimulatedCamera(parse_scene_config(scene), seed=seed) as camera:
        return camera.render_capture(folder / "capture", progress=False)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Capture:
    return _sphere_capture(tmp_path_factory.mktemp("cuda_capture"))


def _reference_and(run: Callable[[str], T], device: str) -> tuple[T, T]:
    """(``run("cpu")``, ``run(device)``); on ``cpu`` the second is the first (a solve is not run twice in CI)."""
    ref = run("cpu")
    return ref, ref if device == "cpu" else run(device)


def _mean_angle_deg(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    m = to_numpy(mask)
    return float(np.nanmean(angular_error_deg(to_numpy(a, np.float64)[m], to_numpy(b, np.float64)[m])))


def _assert_same_recovery(got: NormalsResult, ref: NormalsResult, *, max_mean_deg: float, rel: float) -> None:
    """Two recoveries of the same inputs agree: mask, model, normals (mean angle) and the material."""
    assert torch.equal(got.mask.cpu(), ref.mask)
    assert got.model == ref.model
    assert _mean_angle_deg(got.normals, ref.normals, ref.mask) < max_mean_deg
    for name in ("ior", "alpha", "beta", "kappa"):
        if name in ref.params:
            assert got.params[name] == pytest.approx(ref.params[name], rel=rel, abs=1e-6), name


# --- the forward model --------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_fmbrdf_forward_and_gradients_match_the_cpu(device: str) -> None:
    gen = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64) + torch.tensor(
        [0.0, 0.0, -2.0], dtype=torch.float64), dim=-1)
    l = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen, dtype=torch.float64) + torch.tensor(
        [0.0, 0.0, -2.0], dtype=torch.float64), dim=-1)
    v = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(64, 3)

    def forward(dev: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
        # a fresh leaf per device: ``n.to("cpu")`` is ``n`` itself, and once the CPU pass made it require grad the
        # CUDA copy would be a non-leaf whose .grad stays None (seen on an H200)
        leaves = [n.detach().clone().to(dev).requires_grad_(), torch.tensor(0.3, dtype=torch.float64, device=dev, requires_grad=True),
                  torch.tensor(1.5, dtype=torch.float64, device=dev, requires_grad=True)]
        k_b = torch.full((64,), 0.5, dtype=torch.float64, device=dev, requires_grad=True)
        s = fmbrdf_stokes(leaves[0], l.to(dev), v.to(dev), ior=leaves[2], k_s=1.0, k_b=k_b, alpha=leaves[1],
                          beta=2.0, kappa=0.0)
        (s * torch.tensor([1.0, 0.3, -0.7], dtype=torch.float64, device=dev)).sum().backward()
        return s, [x.grad for x in (*leaves, k_b)]

    ref, ref_grads = forward("cpu")
    got, grads = forward(device)
    _on(got, device)
    assert torch.isfinite(got).all()
    assert torch.allclose(got.cpu(), ref, rtol=1e-9, atol=1e-12)
    for g, r in zip(grads, ref_grads):
        _on(g, device)
        assert torch.allclose(g.cpu(), r, rtol=1e-7, atol=1e-10)


# --- preprocessing, robust PS, recovery ----------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_preprocess_to_stokes_matches_the_cpu(capture: Capture, device: str) -> None:
    ref = preprocess_capture(capture, dtype=torch.float64)
    got = preprocess_capture(capture, dtype=torch.float64, device=device)
    for name in ("stokes", "valid", "saturated", "mask", "lights", "irradiance", "view"):
        _on(getattr(got, name), device)
        a, b = getattr(got, name).cpu(), getattr(ref, name)
        assert torch.equal(a, b) if a.dtype == torch.bool else torch.allclose(a, b, rtol=1e-10, atol=1e-12), name
    assert got.has_polarisation == ref.has_polarisation
    assert got.noise_std == pytest.approx(ref.noise_std, rel=1e-9)


@pytest.mark.parametrize("device", DEVICES)
def test_robust_ps_matches_the_cpu(capture: Capture, device: str) -> None:
    ref = initial_normals(preprocess_capture(capture, dtype=torch.float64))
    got = initial_normals(preprocess_capture(capture, dtype=torch.float64, device=device))
    _on(got.normals, device)
    # a residual at a trimming threshold may round the other way on a GPU (README: 3 of 721,312 pixels
    # between two CPU versions): a handful of pixels may part, no more
    assert (got.valid.cpu() == ref.valid).double().mean() > 0.995
    assert (got.used.cpu() == ref.used).double().mean() > 0.995
    both = got.valid.cpu() & ref.valid & (got.used.cpu() == ref.used).all(0)
    assert both.sum() > 0.9 * ref.valid.sum()
    assert torch.allclose(got.normals.cpu()[both], ref.normals[both], rtol=1e-8, atol=1e-10)


SMALL = {"max_outer_iterations": 2, "subsample_pixels": 256, "fit_kappa": False}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver", ["alternating", "joint"])
def test_recover_normals_matches_the_cpu(capture: Capture, device: str, solver: str) -> None:
    options = RecoveryOptions(model="fmbrdf", solver=solver, **SMALL)
    ref, got = _reference_and(lambda d: recover_normals(preprocess_capture(capture, dtype=torch.float64, device=d),
                                                        options), device)
    _on(got.normals, device)
    _on(got.rendered, device)
    assert torch.isfinite(got.normals[got.mask]).all()
    # GPU reductions sum in another order: the iterates may part by rounding, not by more
    _assert_same_recovery(got, ref, max_mean_deg=0.05, rel=1e-3)


def _two_material_inputs(n: int, device: str) -> tuple[RecoveryInputs, torch.Tensor]:
    """A sphere cap (n × n, 12 directional lights), glossy left half, rough right half, on ``device``;
    returns the inputs and the true normals (NaN outside the mask)."""
    kw = {"dtype": torch.float64, "device": device}
    y, x = torch.meshgrid(torch.linspace(-0.8, 0.8, n, **kw), torch.linspace(-0.8, 0.8, n, **kw), indexing="ij")
    mask = x * x + y * y < 0.6
    normals = torch.nn.functional.normalize(torch.stack([x, y, -(1 - x * x - y * y).clamp_min(0.05).sqrt()], -1), dim=-1)
    zen = torch.tensor([10, 20, 20, 35, 35, 35, 50, 50, 50, 65, 65, 65], **kw) * math.pi / 180
    azi = torch.tensor([0, 120, 240, 30, 150, 270, 90, 210, 330, 0, 120, 240], **kw) * math.pi / 180
    k = zen.numel()
    lights = torch.stack([zen.sin() * azi.cos(), zen.sin() * azi.sin(), -zen.cos()], -1)[:, None, None].expand(k, n, n, 3)
    view = torch.tensor([0.0, 0.0, -1.0], **kw).expand(n, n, 3)
    glossy = fmbrdf_stokes(normals[None], lights, view[None], ior=1.6, alpha=0.08, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5)
    rough = fmbrdf_stokes(normals[None], lights, view[None], ior=1.45, alpha=0.45, beta=2.0, kappa=0.0, k_s=1.0, k_b=0.5)
    s = 0.25 * torch.where((x > 0)[None, ..., None], rough, glossy)  # (K, n, n, 3)
    valid = mask.expand(k, n, n) & (s[..., 0] > 1e-3)
    inputs = RecoveryInputs(s.permute(0, 3, 1, 2).contiguous(), valid, torch.zeros_like(valid), mask, lights,
                            torch.ones(k, n, n, **kw), view, 2e-4, True)
    return inputs, torch.where(mask[..., None], normals, torch.nan)


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_materials_auto_matches_the_cpu(device: str) -> None:
    options = RecoveryOptions(max_outer_iterations=2, subsample_pixels=128, fit_kappa=False)  # materials: auto

    def solve(dev: str):  # noqa: ANN202
        inputs, normals = _two_material_inputs(16, dev)
        start = torch.nn.functional.normalize(torch.nan_to_num(normals) + 0.03, dim=-1)
        return solve_materials(inputs, start, options), inputs.mask

    (ref, mask), (got, _) = _reference_and(solve, device)
    _on(got.normals, device)
    _on(got.labels, device)
    assert len(got.params) == len(ref.params)
    assert (got.labels.cpu()[mask] == ref.labels[mask]).double().mean() > 0.98
    assert _mean_angle_deg(got.normals, ref.normals, mask) < 0.05
    for g, r in zip(got.params, ref.params):
        assert g.alpha == pytest.approx(r.alpha, rel=1e-3)


# --- near field, integration ---------------------------------------------------------------------


def _ring_capture(folder: Path) -> Capture:
    """A Lambertian sphere 8 cm across at 35 cm under a 12-LED ring (tests/test_nearfield.py's scene), 64² raw."""
    scene = {
        "camera": {"projection": "perspective", "width": 64, "height": 64, "pixel_format": "PolarizeMono12",
                   "intrinsics": {"fx": 225.0, "fy": 225.0, "cx": 31.5, "cy": 31.5}},
        "sensor": {"read_noise_e": 2.5, "shot_noise": "poisson", "seed": 5},
        "objects": [{"shape": {"type": "sphere", "center": [0.0, 0.0, 0.35], "radius": 0.04},
                     "material": {"model": "lambertian", "k_d": 0.5}}],
        "lights": [{"ring": {"count": 12, "radius_m": 0.10, "distance_m": 0.25, "intensity": 0.015}}],
    }
    with SimulatedCamera(parse_scene_config(scene), seed=5) as camera:
        return camera.render_capture(folder / "capture", progress=False)


@pytest.mark.parametrize("device", DEVICES)
def test_near_field_stage_matches_the_cpu(tmp_path: Path, device: str) -> None:
    ring = _ring_capture(tmp_path)
    camera = capture_camera(ring, "centre", None)
    reference = 0.3
    lambertian = RecoveryOptions(model="lambertian")

    def refine(dev: str):  # noqa: ANN202
        inputs = preprocess_capture(ring, points=camera.unproject(np.full((camera.height, camera.width), reference)),
                                    dtype=torch.float64, device=dev)
        return refine_near_field(
            inputs, recover_normals(inputs, lambertian), camera, ring.lights(),
            recover=lambda i: recover_normals(i, lambertian),
            integrate=lambda n, m, init: integrate_normals(n, m, camera=camera, reference_depth=reference, depth_init=init),
            reference_depth=reference, options=NearFieldOptions(max_iterations=3, full_model_rounds=1),
        )

    ref, got = _reference_and(refine, device)
    _on(got.result.normals, device)
    _on(got.inputs.lights, device)
    assert got.estimated == ref.estimated
    assert np.nanmedian(got.depth) == pytest.approx(np.nanmedian(ref.depth), rel=1e-4)
    assert _mean_angle_deg(got.result.normals, ref.result.normals, ref.result.mask) < 0.05


@pytest.mark.parametrize("device", DEVICES)
def test_integration_of_a_device_result_matches_the_cpu(capture: Capture, device: str) -> None:
    camera = capture_camera(capture, "centre", 2e-4)
    lambertian = RecoveryOptions(model="lambertian")

    def depth(dev: str) -> np.ndarray:
        result = recover_normals(preprocess_capture(capture, dtype=torch.float64, device=dev), lambertian)
        _on(result.normals, dev)
        normals = to_numpy(result.normals)  # the pipeline's one conversion at the boundary
        surface = to_numpy(result.mask) & np.all(np.isfinite(normals), axis=-1)
        return integrate_normals(normals, surface, camera=camera, reference_depth=1.0)

    ref, got = depth("cpu"), depth(device)
    assert np.array_equal(np.isfinite(got), np.isfinite(ref))
    diff = np.abs(got - ref)[np.isfinite(ref)]  # metres, on a sphere 1.3 cm deep
    assert diff.mean() < 1e-7 and diff.max() < 2e-5


# --- the whole run --------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_whole_run_on_the_device_matches_the_cpu(tmp_path: Path, device: str) -> None:
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=64, height=64, pixel_size_m=4e-4)
    scene["lights"] = scene["lights"][:8]
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))

    def run(dev: str) -> dict:
        config = parse_run_config({
            "input": {"type": "simulated", "scene": "scene.yaml", "seed": 3, "save_capture": False},
            "device": dev, "progress": False, "recovery": {"model": "auto", **SMALL},
            "validation": {"holdout": [0, 4]}, "report": {"enabled": False},
        }, "test_cuda", base_dir=tmp_path)
        return run_pipeline(config, tmp_path / f"result_{dev}", overwrite=True).params

    ref, got = _reference_and(run, device)
    assert got["device"] == device and ref["device"] == "cpu"
    assert got["model"] == ref["model"] == "fmbrdf"
    assert got["capture"]["mask_pixels"] == ref["capture"]["mask_pixels"]
    assert got["metrics"]["normals"]["mean_deg"] == pytest.approx(ref["metrics"]["normals"]["mean_deg"], abs=0.05)
    assert got["params"]["alpha"] == pytest.approx(ref["params"]["alpha"], rel=1e-2)
    assert set(got["timings_s"]) == set(ref["timings_s"])  # every stage ran (or was skipped) on both
    assert json.loads((tmp_path / f"result_{device}" / "params.json").read_text())["device"] == device
    got_normals, ref_normals = (np.load(tmp_path / f"result_{d}" / "normals.npy") for d in (device, "cpu"))
    assert np.array_equal(np.isfinite(got_normals), np.isfinite(ref_normals))
