"""Self-checks: each wrong input of a simulated sphere capture raises its own named warning, the clean
capture none; --strict turns them into exit status 4 with the result folder kept."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.cli import main
from polarshape.errors import (
    BitDepthWarning,
    CaptureError,
    ConventionWarning,
    FilledPixelsWarning,
    FitResidualWarning,
    FrameOrderWarning,
    FrozenPixelsWarning,
    ModelEvidenceWarning,
    ParameterBoundWarning,
    PolarshapeWarning,
)
from polarshape.io.capture import Capture, load_capture, write_capture
from polarshape.normals import recover_normals
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.selfcheck import RESIDUAL_RATIO_MAX, SelfChecks, run_self_checks
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
PERMUTATION = [5, 0, 1, 4, 2, 6, 3, 7]  # frame i of the shuffled capture is frame PERMUTATION[i] of the clean one


@pytest.fixture(scope="module")
def sphere(render_sphere, tmp_path_factory) -> Capture:  # noqa: ANN001
    """The shipped glossy sphere at 32² super-pixels under its first 8 lights."""
    return load_capture(render_sphere(tmp_path_factory.mktemp("sphere"), width=64, pixel_size_m=4e-4, lights=8, seed=0))


def _lights(capture: Capture, scale: tuple[float, float, float]) -> Capture:
    """The capture with every light direction multiplied by ``scale`` (no validation: a z flip gets through)."""
    lights = tuple(light.model_copy(update={"direction": tuple(float(c * s) for c, s in zip(light.direction, scale))})
                   for light in capture.spec.lights)
    return dataclasses.replace(capture, spec=capture.spec.model_copy(update={"lights": lights}))


def _camera(capture: Capture, **update: object) -> Capture:
    camera = capture.spec.camera.model_copy(update=update)
    return dataclasses.replace(capture, spec=capture.spec.model_copy(update={"camera": camera}))


def _checks(capture: Capture) -> tuple[SelfChecks, list[warnings.WarningMessage]]:
    """Preprocess, recover (defaults: model auto), self-check; every warning issued on the way."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        inputs = preprocess_capture(capture)
        result = recover_normals(inputs)
        earlier = [f"{w.category.__name__}: {w.message}" for w in record if issubclass(w.category, PolarshapeWarning)]
        checks = run_self_checks(capture, inputs, result, earlier=earlier)
    return checks, [w for w in record if issubclass(w.category, PolarshapeWarning)]


def _clean(capture: Capture) -> SelfChecks:
    with warnings.catch_warnings():
        warnings.simplefilter("error", PolarshapeWarning)
        inputs = preprocess_capture(capture)
        result = recover_normals(inputs)
        checks = run_self_checks(capture, inputs, result)
    assert checks.warnings == []
    return checks


def test_clean_sphere_raises_nothing(sphere: Capture) -> None:
    checks = _clean(sphere)
    assert checks.measured["residual_to_noise"] < RESIDUAL_RATIO_MAX / 1.5, checks.measured  # measured 0.91
    assert checks.measured["frame_order"]["order"] == list(range(8))


def test_clean_sphere_under_four_lights_raises_nothing(sphere: Capture) -> None:
    lights = sphere.spec.lights[:4]
    _clean(dataclasses.replace(sphere, frames=sphere.frames[:4], spec=sphere.spec.model_copy(update={"lights": lights})))


@pytest.mark.slow
def test_clean_textured_sphere_raises_nothing() -> None:
    """The checkered sphere of configs/scenes/textured.yaml under the sphere's distant lights at 64²
    (measured residual 1.5× the noise; at 32² its 3-pixel checker cells are below what the demosaic
    resolves: 7×, a warning)."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "textured.yaml").read_text())
    lights = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())["lights"][:8]
    d.update(lights=lights, objects=d["objects"][:1])
    d["camera"].update(width=128, height=128, pixel_size_m=2.4e-4, pixel_format="PolarizeMono12")
    _clean(SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False))


def _names(checks: SelfChecks) -> set[str]:
    return set(checks.names)


def test_light_y_flip_is_named(sphere: Capture) -> None:
    checks, issued = _checks(_lights(sphere, (1, -1, 1)))
    assert {"FitResidualWarning", "ConventionWarning"} <= _names(checks)
    convention = next(m for n, m in checks.warnings if n == "ConventionWarning")
    assert "y axis looks flipped" in convention and "negate y" in convention
    assert any(w.category is ConventionWarning for w in issued) and any(w.category is FitResidualWarning for w in issued)
    assert checks.measured["residual_to_noise"] > 1.5 * RESIDUAL_RATIO_MAX  # measured 3.4


def test_light_x_flip_is_named(sphere: Capture) -> None:
    checks, _ = _checks(_lights(sphere, (-1, 1, 1)))
    convention = next(m for n, m in checks.warnings if n == "ConventionWarning")
    assert "x axis looks flipped" in convention and "negate x" in convention


def test_reversed_mosaic_angles_are_named(sphere: Capture) -> None:
    mosaic = sphere.spec.camera.mosaic.model_copy(update={"angles": "clockwise_on_screen"})
    checks, _ = _checks(_camera(sphere, mosaic=mosaic))
    convention = next(m for n, m in checks.warnings if n == "ConventionWarning")
    assert "camera.mosaic.angles: counterclockwise_on_screen" in convention


def test_light_x_and_y_flip_is_named(sphere: Capture) -> None:
    """x and y both negated: every pixel's data are explained (a concave shape), but the silhouette's
    normals all point inward."""
    checks, _ = _checks(_lights(sphere, (-1, -1, 1)))
    assert checks.names == ["ConventionWarning"] and "both flipped" in checks.warnings[0][1]


def test_light_z_flip_is_refused_naming_the_fix(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match="flip the sign of z"):
        preprocess_capture(_lights(sphere, (1, 1, -1)))


def test_shuffled_frames_are_named_with_the_matching_lights(sphere: Capture) -> None:
    checks, _ = _checks(dataclasses.replace(sphere, frames=sphere.frames[PERMUTATION]))
    assert {"FitResidualWarning", "FrameOrderWarning"} <= _names(checks)
    assert checks.measured["frame_order"]["order"] == PERMUTATION
    message = next(m for n, m in checks.warnings if n == "FrameOrderWarning")
    assert "frames look shuffled" in message and "frame 0 (frames/000.png) matches lights[5]" in message


def test_wrong_declared_bit_depth_is_named(sphere: Capture) -> None:
    """12-bit counts declared 16-bit (data deeper than declared is refused: a count above full scale)."""
    checks, issued = _checks(_camera(sphere, bit_depth=16))
    assert "BitDepthWarning" in _names(checks)
    assert any(w.category is BitDepthWarning and "12-bit data declared bit_depth 16" in str(w.message) for w in issued)
    assert [w.category for w in issued].count(BitDepthWarning) == 1  # listed by the checks, not issued twice
    with pytest.raises(CaptureError, match="above 255"):
        write_capture(Path("/nonexistent/never-written"), _camera(sphere, bit_depth=8))


@pytest.fixture(scope="module")
def clean_run(sphere: Capture) -> tuple:
    inputs = preprocess_capture(sphere)
    return inputs, recover_normals(inputs)


@pytest.mark.parametrize(("edit", "kind"), [
    (lambda r: {"params": {**r.params, "beta": 5.99, "k_s": 0.0}}, ParameterBoundWarning),
    (lambda r: {"filled": r.mask.clone()}, FilledPixelsWarning),
    (lambda r: {"normals": r.initial_normals.clone()}, FrozenPixelsWarning),
])
def test_result_checks_name_their_warning(sphere: Capture, clean_run: tuple, edit, kind) -> None:  # noqa: ANN001
    inputs, result = clean_run
    with pytest.warns(kind) as record:
        checks = run_self_checks(sphere, inputs, dataclasses.replace(result, **edit(result)))
    assert kind.__name__ in checks.names
    assert all(issubclass(w.category, PolarshapeWarning) for w in record)


def test_lambertian_predicting_held_out_lights_better_is_named(sphere: Capture, clean_run: tuple) -> None:
    inputs, result = clean_run
    record = {"models": {"fmbrdf": {"s0_rel_rmse": 0.08}, "lambertian": {"s0_rel_rmse": 0.03}}}
    with pytest.warns(ModelEvidenceWarning, match=r"3\.0 % vs 8\.0 %"):
        checks = run_self_checks(sphere, inputs, result, record)
    assert checks.names == ["ModelEvidenceWarning"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", PolarshapeWarning)
        same = {"models": {"fmbrdf": {"s0_rel_rmse": 0.03}, "lambertian": {"s0_rel_rmse": 0.08}}}
        assert run_self_checks(sphere, inputs, result, same).warnings == []


def _run_config(folder: Path, capture: Path) -> Path:
    data = {"progress": False, "input": {"type": "capture", "path": str(capture)}, "validation": {"holdout": "none"},
            "mesh": {"poisson": False, "obj": False}, "report": {"enabled": False}, "export": {"exr": False}}
    path = folder / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_strict_run_exits_4_and_keeps_the_result(sphere: Capture, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    flipped = write_capture(tmp_path / "flipped", _lights(sphere, (1, -1, 1)))
    out = tmp_path / "res"
    assert main(["run", str(_run_config(tmp_path, flipped)), "--out", str(out), "--quiet", "--strict"]) == 4
    err = capsys.readouterr().err
    line = next(x for x in err.splitlines() if x.startswith("error: "))
    assert re.match(r"error: self-check failed: FitResidualWarning, ConventionWarning(, \w+)*: fit residual \d", line)
    assert line.endswith(f"(result kept in {out.absolute()})")
    params = json.loads((out / "params.json").read_text())
    names = [w["name"] for w in params["checks"]["warnings"]]
    assert {"FitResidualWarning", "ConventionWarning"} <= set(names)
    assert params["checks"]["residual_to_noise"] > RESIDUAL_RATIO_MAX
    # (the mirrored surface is also concave-looking: InterreflectionWarning may come first)
    assert "model fmbrdf" in params["summary"] and f"{len(params['warnings'])} warnings: " in params["summary"]
    assert all(name in params["summary"] for name in names)
    assert "checks" in params["timings_s"] and (out / "normals.npy").exists() or (out / "normal.png").exists()


def test_clean_run_summary_says_what_ran(sphere: Capture, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    clean = write_capture(tmp_path / "clean", sphere)
    out = tmp_path / "res"
    assert main(["run", str(_run_config(tmp_path, clean)), "--out", str(out), "--quiet", "--strict"]) == 0
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    params = json.loads((out / "params.json").read_text())
    assert params["checks"]["warnings"] == [] and "warning" not in summary and "model fmbrdf" in summary
    assert "no held-out validation" not in summary  # holdout: none is not a reason to show
    assert np.isfinite(params["checks"]["residual_to_noise"])
    assert torch.isfinite(torch.tensor(params["checks"]["convention"]["direct"]))


@pytest.mark.parametrize("model", ["fmbrdf", "lambertian"])
def test_residual_to_noise_is_the_full_frame_formula(model: str) -> None:
    """residual_to_noise works on each light's usable pixels only: the ratios of the formula over whole frames
    (χ² of the observations whose 3×3 neighbours are usable, their median and mean)."""
    from types import SimpleNamespace

    import torch.nn.functional as F

    from polarshape.recover.noise import NoiseModel
    from polarshape.recover.selfcheck import residual_to_noise

    gen = torch.Generator().manual_seed(0)
    k, h, w = 5, 23, 31
    observed = torch.rand(k, 3, h, w, generator=gen, dtype=torch.float32)
    rendered = observed + 0.01 * torch.randn(k, 3, h, w, generator=gen)
    valid = torch.rand(k, h, w, generator=gen) > 0.2
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[2:-3, 4:-2] = True
    noise = NoiseModel(1e-5, 2e-4, "four-site redundancy")
    inputs = SimpleNamespace(valid=valid, mask=mask, noise=noise, noise_std=1e-3, has_polarisation=True, num_lights=k)
    result = SimpleNamespace(observed=observed, rendered=rendered, model=model)
    use = (-F.max_pool2d(-(valid & mask).float().unsqueeze(1), 3, stride=1, padding=1)).squeeze(1) > 0.5
    chi = []
    for i in range(k):
        obs, pred = observed[i].double(), rendered[i].double()
        chi.append(((pred[0] - obs[0]) / noise.std(obs[0]))[use[i]].pow(2).float())
        if model == "fmbrdf":
            chi += [((pred[c] - obs[c]) / noise.linear_std(obs[0]))[use[i]].pow(2).float() for c in (1, 2)]
    chi2 = torch.cat(chi).double()
    want = (float((chi2.median() / 0.454936).sqrt()), float(chi2.mean().sqrt()), chi2.numel())
    assert residual_to_noise(inputs, result) == pytest.approx(want, rel=1e-12, abs=0)
