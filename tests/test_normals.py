"""Tests of polarshape.normals (recover_capture / recover_normals) on simulated captures (12-bit, shot + read noise, ≥ 8 lights)
and on the shared captures (skipped when ../shared is absent)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.capture import Capture, load_capture
from polarshape.metrics import angular_error_deg
from polarshape.normals import NormalsResult, choose_model, initial_normals, recover_capture
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO / ".." / "shared"


def _simulate(kind: str, n: int, alpha: float, kappa: float = 0.0, ior: float = 1.5,
              exposure_us: float | None = None) -> Capture:
    """A capture of configs/scenes/<kind>.yaml at n × n super-pixels with the given material."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / f"{kind}.yaml").read_text())
    raw = 2 * n
    d["camera"]["width"] = d["camera"]["height"] = raw
    if exposure_us is not None:
        d["camera"]["exposure_us"] = exposure_us
    if kind == "sphere":
        d["camera"]["pixel_size_m"] = 1e-4 * 256 / raw
    else:
        f = 3200.0 * raw / 256
        d["camera"]["intrinsics"] = {"fx": f, "fy": f, "cx": (raw - 1) / 2, "cy": (raw - 1) / 2}
    d["objects"][0]["material"].update(alpha=alpha, kappa=kappa, ior=ior, k_b=0.5)
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def _errors(result: NormalsResult, capture: Capture, min_missing: int = 3) -> tuple[float, int]:
    """Mean angular error (deg) over mask pixels lit in ≥ K − min_missing observations (not shadowed)."""
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    valid = preprocess_capture(capture).valid
    lit = valid.sum(0) >= valid.shape[0] - min_missing
    m = result.mask & lit & torch.isfinite(gt).all(-1)
    return float(angular_error_deg(result.normals.double()[m], gt[m]).mean()), int(m.sum())


def _recover(capture: Capture, **options: object) -> NormalsResult:
    """recover_capture with these options (model ``fmbrdf`` unless given); demosaic and sample_at go
    to preprocessing."""
    pre = {k: options.pop(k) for k in ("demosaic", "sample_at") if k in options}
    return recover_capture(capture, RecoveryOptions(**{"model": "fmbrdf", **options}), **pre)


CASES = [("sphere", 0.05), ("sphere", 0.3), ("sphere", 0.8), ("blob", 0.05), ("blob", 0.3), ("blob", 0.8)]
#: Super-pixels across. The blob's bumps curve strongly inside one super-pixel at low resolution and
#: the 2×2 average of differently oriented sites depolarises (μ comes out high at 40²), so it is
#: tested at 80². The shiny lobe (α = 0.05: about 3° wide) must span several super-pixels: on a 56²
#: sphere the normal turns ≈ 3.2° per super-pixel and the interpolated Stokes broaden the lobe
#: (measured α: 0.0566 at 56², 0.0553 at 84², 0.0532 at 112²; with the true normals 0.0556, 0.0525,
#: 0.0514), so the shiny sphere is tested at 112².
SIZES = {("sphere", 0.05): 112, "sphere": 56, "blob": 80}
#: Exposure (µs) per roughness: at the scenes' 10 ms the shiny lobe saturates over its whole core and
#: only its flanks are left, where α trades off against β (measured on the 56² sphere: α 0.010,
#: β 0.63 instead of 0.05, 2); at 2.5 ms its peak still clips (378 saturated observations on the
#: 80² blob: α 0.0439, −12 %); at 1 ms none does, as a user would expose a shiny part (or bracket it
#: with `polarshape capture`).
EXPOSURE_US = {0.05: 1000.0}


@pytest.mark.slow
@pytest.mark.parametrize("kind,alpha", CASES)
def test_recovery_simulated(kind: str, alpha: float) -> None:
    capture = _simulate(kind, SIZES.get((kind, alpha), SIZES[kind]), alpha, exposure_us=EXPOSURE_US.get(alpha))
    result = _recover(capture, fit_kappa=False, max_outer_iterations=12)
    lamb = _recover(capture, model="lambertian")
    err, count = _errors(result, capture)
    err_l, _ = _errors(lamb, capture)
    assert count > 300
    assert err <= 1.0, f"{kind} α={alpha}: mean normal error {err:.3f}° (Lambertian {err_l:.3f}°)"
    assert err_l >= 1.5 * err, f"Lambertian PS {err_l:.3f}° not clearly worse than {err:.3f}°"
    # issue 4's targets: μ within ±0.05, α within ±10 %
    assert abs(result.params["ior"] - 1.5) <= 0.05, result.params
    assert abs(result.params["alpha"] - alpha) <= 0.1 * alpha, result.params
    # result contract
    h, w = capture.mask.shape
    assert result.normals.shape == (h, w, 3) and result.albedo is not None and result.albedo.shape == (h, w)
    assert bool(torch.isnan(result.normals[~result.mask]).all())
    assert bool(torch.isfinite(result.normals[result.mask]).all())
    assert result.rendered is not None and result.rendered.shape == result.observed.shape
    assert result.history and result.history[-1]["loss"] <= result.history[0]["loss"]
    assert "normals" in result.timings and "global_params" in result.timings


def test_lambertian_model_and_result_contract() -> None:
    capture = _simulate("sphere", 24, 0.3)
    result = _recover(capture, model="lambertian")
    assert result.model == "lambertian"
    assert result.normals.shape == (24, 24, 3)
    n = result.normals[result.mask]
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(n.shape[0]), atol=1e-5, rtol=0)
    assert bool((n[:, 2] < 0).all())  # facing the camera
    assert result.rendered is not None and float(result.rendered[:, 1:].abs().max()) == 0.0


def test_kappa_skipped_when_it_adds_nothing() -> None:
    capture = _simulate("sphere", 24, 0.3)
    result = _recover(capture, fit_kappa=None)
    assert result.params["kappa"] == 0.0
    assert any(s.startswith("kappa") for s in result.skipped), result.skipped
    assert any(s.startswith("crop") for s in result.skipped)


def test_config_validation_and_too_few_lights() -> None:
    capture = _simulate("sphere", 16, 0.3)
    with pytest.raises(ValueError, match="model"):
        _recover(capture, model="phong")
    two = Capture(spec=capture.spec.model_copy(update={"lights": capture.spec.lights[:2]}),
                  frames=capture.frames[:2], mask=capture.mask)
    for model in ("fmbrdf", "lambertian"):  # the Lambertian answer is refused too, not invented
        with pytest.raises(ValueError, match="at least 3"):
            _recover(two, model=model)


def test_stress_dark_and_saturated_pixels_stay_finite() -> None:
    capture = _simulate("sphere", 24, 0.3)
    frames = capture.frames.copy()
    frames[:, 10:16, 10:16] = 0  # all dark
    frames[:, 30:36, 30:36] = 4095  # all saturated
    frames[0] = np.minimum(frames[0].astype(np.int64) * 8, 4095).astype(np.uint16)  # one over-exposed light
    stressed = Capture(spec=capture.spec, frames=frames, mask=capture.mask)
    result = _recover(stressed, fit_kappa=False, max_outer_iterations=4)
    n = result.normals[result.mask]
    assert bool(torch.isfinite(n).all())
    assert all(math.isfinite(v) for v in result.params.values())
    assert result.albedo is not None and bool(torch.isfinite(result.albedo[result.mask]).all())


def _shared(name: str) -> Path:
    path = SHARED / "data" / name
    if not path.is_dir():
        pytest.skip(f"shared capture {path} not available")
    return path


@pytest.mark.slow
def test_official_sphere128() -> None:
    """The paper's benchmark capture; its ground truth is at each block's 90° site (top left)."""
    capture = load_capture(_shared("official_sphere128"))
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    errors = {}
    for name, cfg in {
        "superpixel": dict(demosaic="superpixel"),
        "site": dict(sample_at="top_left"),
        "site_smooth": dict(sample_at="top_left", smoothness=0.5),
        "lambertian": dict(model="lambertian", sample_at="top_left"),
    }.items():
        result = _recover(capture, **cfg)
        m = result.mask & torch.isfinite(gt).all(-1)
        errors[name] = float(angular_error_deg(result.normals.double()[m], gt[m]).mean())
        if name == "site":
            params = result.params
    # measured: super-pixel Stokes 0.89° (sites half a pixel apart, and away from the ground truth's);
    # bilinear at the 90° site 0.57° (per-pixel maximum likelihood with the true material from the
    # true normals: 0.578°, the noise floor); + smoothness 0.5: 0.39° (issue 4's target: ≤ 0.5°);
    # Lambertian ≈ 3.4°
    assert errors["site_smooth"] <= 0.5 < errors["site"] <= 0.65 < errors["superpixel"], errors
    assert errors["lambertian"] >= 5 * errors["site_smooth"], errors
    assert abs(params["ior"] - 1.5) <= 0.01 and abs(params["alpha"] - 0.25) <= 0.0125, params
    assert abs(params["beta"] - 2.0) <= 0.1 and abs(params["r_k"] - 0.5) <= 0.025, params


@pytest.mark.slow
def test_mitsuba_sphere_model_mismatch() -> None:
    capture = load_capture(_shared("mitsuba_sphere_a020"))
    result = _recover(capture)
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    m = result.mask & torch.isfinite(gt).all(-1)
    err = float(angular_error_deg(result.normals.double()[m], gt[m]).mean())
    assert err <= 3.0


@pytest.mark.slow
@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_baek_rendered_capture_model_mismatch(distribution: str) -> None:
    """A capture rendered with the Baek et al. pBRDF (not our model) is still recovered to ≤ 3°."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    n = 64
    d["camera"]["width"] = d["camera"]["height"] = 2 * n
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / (2 * n)
    d["objects"][0]["material"] = {"model": "baek", "ior": 1.5, "k_s": 1.0, "k_d": 0.5, "alpha": 0.25,
                                   "distribution": distribution}
    capture = SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)
    result = _recover(capture, max_outer_iterations=10)
    lamb = _recover(capture, model="lambertian")
    err, count = _errors(result, capture)
    err_l, _ = _errors(lamb, capture)
    # measured: GGX 0.56° (Lambertian 3.45°), Beckmann 0.52° (3.74°); issue 4's bound is 3°
    assert count > 1000 and err <= 3.0, (err, err_l, result.params)
    assert 3 * err < err_l, (err, err_l)


def test_coplanar_lights_are_refused() -> None:
    capture = _simulate("sphere", 16, 0.3)
    data = capture.spec.model_dump(mode="json")
    for i, light in enumerate(data["lights"]):
        t = 0.2 + 0.08 * i  # every light in the plane y = 0
        light["direction"] = [math.sin(t) * (1 if i % 2 else -1), 0.0, -math.cos(t)]
    from polarshape.io.capture import parse_capture_spec

    coplanar = Capture(spec=parse_capture_spec(data), frames=capture.frames, mask=capture.mask)
    for model in ("fmbrdf", "lambertian"):
        with pytest.raises(ValueError, match="coplanar"):
            _recover(coplanar, model=model)


def test_grazing_lights_stay_finite() -> None:
    capture = _simulate("blob", 24, 0.3)  # three lights at 70° from the view axis
    result = _recover(capture, fit_kappa=False, max_outer_iterations=3)
    assert bool(torch.isfinite(result.normals[result.mask]).all())
    assert result.rendered is not None and bool(torch.isfinite(result.rendered).all())


def test_auto_picks_lambertian_for_a_matte_unpolarised_scene() -> None:
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    d["camera"]["width"] = d["camera"]["height"] = 48
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / 48
    d["objects"][0]["material"] = {"model": "lambertian", "k_d": 1.5}
    capture = SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)
    # the light is unpolarised, but the super-pixel estimate combines sites half a pixel apart on a
    # shaded sphere and reads the shading gradient as polarisation (measured median DoLP 0.135 at
    # 24² super-pixels); the bilinear estimate (the default) sees the noise level (0.010)
    for demosaic, low, high in (("superpixel", 0.05, 1.0), ("bilinear", 0.0, 0.02)):
        inputs = preprocess_capture(capture, demosaic=demosaic)
        dolp = (inputs.stokes[:, 1:].norm(dim=1) / inputs.stokes[:, 0].clamp_min(1e-6))[inputs.valid]
        assert low <= float(dolp.median()) <= high, (demosaic, float(dolp.median()))
    result = _recover(capture, model="auto")
    assert result.model == "lambertian", result.skipped
    assert any("Lambertian PS explains" in s for s in result.skipped)
    assert result.rendered is not None and float(result.rendered[:, 1:].abs().max()) == 0.0


def test_smoothness_config_is_checked() -> None:
    capture = _simulate("sphere", 16, 0.3)
    with pytest.raises(ValueError, match="smoothness"):
        _recover(capture, smoothness=-1.0)


@pytest.mark.slow
def test_checker_textured_sphere_propagation_and_fill() -> None:
    """An albedo texture (checker, 5:1 contrast) under 9 distant lights: blocks straddling a texture
    edge lose their observations (mixed sites) and get their neighbours' normal; propagation pulls
    pixels out of wrong basins. Measured at 64²: 0.75° mean, 3 pixels > 10° (without propagation
    0.94°, 17; before both: 2.5° mean on the 128² version, 233 pixels > 10°)."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "textured.yaml").read_text())
    lights = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())["lights"]
    d.update(lights=lights, objects=d["objects"][:1])  # distant lights, no backdrop
    n = 64
    d["camera"].update(width=2 * n, height=2 * n, pixel_size_m=1.2e-4 * 128 / n, pixel_format="PolarizeMono12")
    capture = SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    errors = {}
    for propagate in (True, False):
        result = _recover(capture, propagate=propagate)
        m = result.mask & torch.isfinite(gt).all(-1)
        errors[propagate] = angular_error_deg(result.normals.double()[m], gt[m])
        assert result.filled is not None and int(result.filled.sum()) > 20
        assert not bool((result.filled & ~result.mask).any())
        assert any(s.startswith("fill:") for s in result.skipped), result.skipped
        assert bool(torch.isfinite(result.normals[result.mask]).all())
    assert float(errors[True].mean()) <= 1.0, float(errors[True].mean())
    assert int((errors[True] > 10).sum()) * 3 <= int((errors[False] > 10).sum()), (
        int((errors[True] > 10).sum()), int((errors[False] > 10).sum()))


@pytest.mark.slow
def test_camera_without_polariser_gives_an_intensity_only_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    """A camera with no polariser array (every site sees ½ s0): preprocessing finds no polarisation,
    the FMBRDF fit runs on intensity alone and says so, and still beats Lambertian PS clearly
    (measured at 56², α 0.3: 0.24° against 3.43°; before α was profiled over the normals the
    intensity-only fit dropped the lobe, k_s → 0: 3.18°)."""
    import polarshape.acquisition.simulated as simulated

    monkeypatch.setattr(simulated, "mosaic_radiance", lambda stokes, angle_map: 0.5 * stokes[..., 0, :, :])
    capture = _simulate("sphere", 56, 0.3)
    assert not preprocess_capture(capture).has_polarisation
    result = _recover(capture, fit_kappa=False)
    lamb = _recover(capture, model="lambertian")
    assert any(s.startswith("polarisation: no linear polarisation") for s in result.skipped), result.skipped
    err, count = _errors(result, capture)
    err_l, _ = _errors(lamb, capture)
    assert count > 1000 and err <= 1.0 and 3 * err <= err_l, (err, err_l, result.params)
    assert result.params["k_s"] > 0 and abs(result.params["alpha"] - 0.3) <= 0.1, result.params
    assert bool(torch.isfinite(result.normals[result.mask]).all())


def _matte_sphere(n: int) -> Capture:
    """configs/scenes/sphere.yaml with a Lambertian material (unpolarised) at n × n super-pixels."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    d["camera"]["width"] = d["camera"]["height"] = 2 * n
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / (2 * n)
    d["objects"][0]["material"] = {"model": "lambertian", "k_d": 0.5}
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def test_auto_keeps_the_fmbrdf_for_a_rough_lobe_lambertian_ps_fits_only_to_the_percent() -> None:
    """A rough FMBRDF sphere (α 0.8, κ 0) is nearly unpolarised (median DoLP 0.018) and Lambertian PS
    fits its s0 to 0.9 % of the median — under the old 3 % rule ``auto`` took Lambertian and the
    normals came out at 1.3–1.5° (256², against 0.16° with the FMBRDF); its residual is 1.5–1.9× the
    measured noise, a matte sphere's 0.84–0.88×."""
    for capture, expected in ((_simulate("sphere", 32, 0.8), "fmbrdf"), (_matte_sphere(32), "lambertian")):
        inputs = preprocess_capture(capture)
        skipped: list[str] = []
        assert choose_model(inputs, initial_normals(inputs), skipped) == expected, skipped


@pytest.mark.parametrize("model", ["lambertian", pytest.param("fmbrdf", marks=pytest.mark.slow), "auto"])
def test_pixels_with_too_few_observations_are_marked_filled(model: str) -> None:
    """Mask pixels lit in only 2 lights have no normal of their own: every model (``auto`` choosing
    Lambertian on a matte sphere) takes their neighbours' and marks them in result.filled
    (filled.png, params.json filled_pixels) instead of inventing one silently."""
    capture = _matte_sphere(16) if model == "auto" else _simulate("sphere", 16, 0.3)
    frames = capture.frames.copy()
    frames[2:, 12:18, 12:18] = 0  # a 3 × 3 super-pixel patch in the middle: dark in every light but 0, 1
    two_lit = Capture(spec=capture.spec, frames=frames, mask=capture.mask)
    valid = preprocess_capture(two_lit).valid
    unsupported = torch.from_numpy(capture.mask) & (valid.sum(0) < 3)
    assert int(unsupported.sum()) >= 9, int(unsupported.sum())
    result = _recover(two_lit, model=model, max_outer_iterations=1, fit_kappa=False, coarse_to_fine=False)
    assert result.model == ("fmbrdf" if model == "fmbrdf" else "lambertian"), result.skipped
    assert result.filled is not None, result.model
    assert torch.equal(result.filled, unsupported), result.model
    assert any(s.startswith("fill:") for s in result.skipped), result.skipped
    assert bool(torch.isfinite(result.normals[unsupported]).all())
    n = result.normals[6:9, 6:9].reshape(-1, 3)
    assert bool((n[:, 2] < -0.8).all()), n  # the patch took its neighbours' normals (near the sphere's centre)
