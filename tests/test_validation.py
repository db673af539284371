"""Held-out-light validation (polarshape.recover.validation): which lights, the errors against the
noise floor, the model ranking on FMBRDF and Baek captures, the config's holdout key, auto's evidence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from polarshape.config import RunConfig
from polarshape.errors import ConfigError
from polarshape.io.capture import load_capture
from polarshape.normals import recover_normals
from polarshape.pipeline import run_pipeline
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions, ValidationOptions
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.validation import (
    ModelValidation, Validation, holdout_lights, model_evidence, select_input_lights, validate_holdout,
)

#: 64×64 super-pixels (the sphere 120 raw pixels across), the shipped scene's 9 lights, 12-bit,
#: shot + read noise (the scene's sensor).
WIDTH, PIXEL_SIZE_M, LIGHTS = 128, 2.0e-4, 9
BAEK = {"model": "baek", "ior": 1.5, "k_s": 1.0, "k_d": 0.5, "alpha": 0.2}


def _run(folder: Path):  # noqa: ANN202
    inputs = preprocess_capture(load_capture(folder))
    return inputs, recover_normals(inputs, RecoveryOptions(), InitialNormalsOptions())


@pytest.fixture(scope="module")
def fmbrdf_run(render_sphere, tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN001, ANN201
    """(inputs, result) of the FMBRDF recovery of a simulated FMBRDF sphere."""
    folder = render_sphere(tmp_path_factory.mktemp("fm"), width=WIDTH, pixel_size_m=PIXEL_SIZE_M, lights=LIGHTS, seed=1)
    return _run(folder)


@pytest.fixture(scope="module")
def fmbrdf_validation(fmbrdf_run) -> Validation:  # noqa: ANN001
    inputs, result = fmbrdf_run
    return validate_holdout(inputs, result, RecoveryOptions(), InitialNormalsOptions(), ValidationOptions())


def test_holdout_lights_spread_and_deterministic() -> None:
    # a ring of 8 lights at 40° zenith (a little off-centre), and one frontal light
    az = torch.arange(8, dtype=torch.float64) * (math.pi / 4)
    ring = torch.stack([math.sin(0.7) * az.cos(), math.sin(0.7) * az.sin(), -math.cos(0.7) * torch.ones(8)], -1)
    ring[0] *= torch.tensor([1.1, 1.0, 1.0], dtype=torch.float64)  # breaks the ring's symmetry
    two = holdout_lights(ring, 2)
    assert two == holdout_lights(ring.clone(), 2) == sorted(two)
    assert abs(two[0] - two[1]) == 4  # opposite sides of the ring: the farthest apart
    dirs = torch.cat([ring, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)])
    assert 8 in holdout_lights(dirs, 3)  # the centre of the dome starts the sampling
    assert holdout_lights(dirs, 20) == list(range(9))


def test_held_out_error_at_the_noise_floor_and_fmbrdf_ranks_first(fmbrdf_validation: Validation) -> None:
    v = fmbrdf_validation.as_dict()
    assert v["mode"] == "auto" and len(v["holdout"]) == 3 and v["reason"] is None
    fm = v["models"]["fmbrdf"]
    assert len(fm["per_light"]) == 3 and all(r["pixels"] > 100 for r in fm["per_light"])
    floor = v["noise_floor_s0_rel"]
    assert 0.001 < floor < 0.05  # shot + read noise of a 12-bit capture, not the quantisation alone
    assert fm["s0_rel_rmse"] <= 1.5 * floor, (fm["s0_rel_rmse"], floor)
    assert v["ranking"][0] == "fmbrdf", {m: r["s0_rel_rmse"] for m, r in v["models"].items()}
    assert v["ranking"][-1] == "lambertian"  # no specular lobe at all
    assert fm["aolp_mae_deg"] is not None and fm["aolp_mae_deg"] < 15.0
    assert v["models"]["lambertian"]["aolp_mae_deg"] is None  # it predicts no polarisation
    shape = fmbrdf_validation.observed.shape
    assert shape == fmbrdf_validation.predicted.shape and shape[:2] == (3, 3)
    assert np.isfinite(fmbrdf_validation.predicted).all()


@pytest.mark.slow
def test_baek_capture_ranks_baek_first(render_sphere, tmp_path: Path) -> None:  # noqa: ANN001
    folder = render_sphere(tmp_path, width=WIDTH, pixel_size_m=PIXEL_SIZE_M, lights=LIGHTS, seed=2, material=BAEK)
    inputs, result = _run(folder)
    v = validate_holdout(inputs, result, RecoveryOptions(), InitialNormalsOptions(), ValidationOptions()).as_dict()
    errors = {m: r["s0_rel_rmse"] for m, r in v["models"].items()}
    assert v["ranking"][0] == "baek", errors
    assert errors["baek"] < 0.8 * errors["fmbrdf"], errors


def test_holdout_none_list_and_too_few_lights(fmbrdf_run) -> None:  # noqa: ANN001
    inputs, result = fmbrdf_run
    opts, init = RecoveryOptions(), InitialNormalsOptions()
    none = validate_holdout(inputs, result, opts, init, ValidationOptions(holdout="none"))
    assert not none.ran and none.as_dict()["holdout"] == [] and "none" in none.reason
    few = select_input_lights(inputs, [0, 1, 2, 3, 4])
    skipped = validate_holdout(few, result, opts, init, ValidationOptions())
    assert not skipped.ran and "K = 5 < 6" in skipped.reason
    two = ValidationOptions(holdout=[4], models=["fmbrdf", "lambertian"])
    listed = validate_holdout(inputs, result, opts, init, two)
    assert listed.as_dict()["mode"] == "list" and listed.holdout == [4]
    assert set(listed.models) == {"fmbrdf", "lambertian"}
    for bad in ([9], [-1], [2, 2], list(range(7))):
        with pytest.raises(ConfigError, match="validation.holdout"):
            validate_holdout(inputs, result, opts, init, ValidationOptions(holdout=bad))


def _validation(fmbrdf: float, lambertian: float, floor: float = 0.005) -> Validation:
    models = {m: ModelValidation([{"light": 0, "s0_rel_rmse": e, "dolp_rmse": 0.01, "aolp_mae_deg": 5.0}])
              for m, e in (("fmbrdf", fmbrdf), ("lambertian", lambertian))}
    return Validation("auto", [0], None, models, floor)


def test_model_evidence_switches_only_on_clear_evidence() -> None:
    clear = model_evidence(_validation(fmbrdf=0.03, lambertian=0.01), "fmbrdf", "auto")
    assert clear["switch_to"] == "lambertian" and clear["clear"]
    assert model_evidence(_validation(fmbrdf=0.03, lambertian=0.01), "fmbrdf", "fmbrdf")["switch_to"] is None
    close = model_evidence(_validation(fmbrdf=0.0100, lambertian=0.0095), "fmbrdf", "auto")
    assert close["switch_to"] is None and "as well as" in close["verdict"]
    back = model_evidence(_validation(fmbrdf=0.006, lambertian=0.05), "lambertian", "auto")
    assert back["switch_to"] == "fmbrdf"
    assert model_evidence(_validation(fmbrdf=0.006, lambertian=0.05), "fmbrdf", "auto")["switch_to"] is None
    assert model_evidence(Validation("none", [], "validation.holdout is none"), "fmbrdf", "auto") is None


def test_pipeline_writes_the_validation(render_sphere, tmp_path: Path) -> None:  # noqa: ANN001
    folder = render_sphere(tmp_path, width=WIDTH, pixel_size_m=PIXEL_SIZE_M, lights=LIGHTS, seed=3)
    config = RunConfig.model_validate({
        "input": {"type": "capture", "path": str(folder)}, "progress": False, "report": {"enabled": False},
        "recovery": {"model": "auto"}, "validation": {"holdout": [0, 8], "models": ["fmbrdf", "lambertian"]},
    })
    params = run_pipeline(config, tmp_path / "out").params
    v = params["validation"]
    assert v["holdout"] == [0, 8] and v["mode"] == "list" and v["ranking"] == ["fmbrdf", "lambertian"]
    assert v["model_choice"]["switch_to"] is None and params["model"] == "fmbrdf"
    assert "validation" in params["timings_s"]


def test_pipeline_switches_model_on_clear_evidence(render_sphere, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """recovery.model auto + evidence that Lambertian predicts clearly better: the run is redone as lambertian."""
    folder = render_sphere(tmp_path, width=64, pixel_size_m=4.0e-4, lights=LIGHTS, seed=4)
    evidence = {"switch_to": "lambertian", "verdict": "lambertian predicts the held-out lights clearly better"}
    monkeypatch.setattr("polarshape.pipeline.model_evidence", lambda *args: dict(evidence))
    config = RunConfig.model_validate({
        "input": {"type": "capture", "path": str(folder)}, "progress": False, "report": {"enabled": False},
        "recovery": {"model": "auto"}, "validation": {"holdout": [8], "models": ["fmbrdf", "lambertian"]},
    })
    params = run_pipeline(config, tmp_path / "out").params
    assert params["model"] == "lambertian" and params["validation"]["model_choice"] == evidence
    assert any("clearly better" in s for s in params["skipped"] if s.startswith("validation:"))


@pytest.mark.slow
def test_warm_start_gives_the_cold_held_out_error(fmbrdf_run, fmbrdf_validation: Validation) -> None:  # noqa: ANN001
    inputs, result = fmbrdf_run
    cold = validate_holdout(inputs, result, RecoveryOptions(), InitialNormalsOptions(),
                            ValidationOptions(models=["fmbrdf"]), warm_start=False)
    warm_error = fmbrdf_validation.models["fmbrdf"].mean("s0_rel_rmse")
    cold_error = cold.models["fmbrdf"].mean("s0_rel_rmse")
    assert abs(warm_error - cold_error) <= 0.05 * cold_error, (warm_error, cold_error)
    assert fmbrdf_validation.timings_s["fmbrdf"] < cold.timings_s["fmbrdf"] / 3
