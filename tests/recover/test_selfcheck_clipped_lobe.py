"""ClippedLobeWarning: a specular lobe whose core is saturated everywhere is named (its α, β, k_s are
not identified); with exposure brackets the core is seen and nothing is said."""

from __future__ import annotations

import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.errors import ClippedLobeWarning
from polarshape.io.capture import Capture
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.selfcheck import clipped_lobe, run_self_checks
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[2]


def _capture(exposures: list[float] | None) -> Capture:
    d = yaml.safe_load((REPO / "configs/scenes/sphere.yaml").read_text())
    d["camera"].update(width=80, height=80, pixel_size_m=3.2e-4, exposure_us=40000.0)
    if exposures is not None:
        d["camera"].update(exposures_us=exposures, exposure_us=exposures[0])
    d["objects"][0]["material"].update(alpha=0.03, k_b=0.135)
    d["lights"] = d["lights"][:8]
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def _checks(capture: Capture, alpha: float, demosaic: str = "bilinear") -> tuple[dict, list[str]]:
    """Self-checks of a 'recovery' at the true normals with this α (the observations as its rendering)."""
    inputs = preprocess_capture(capture, demosaic=demosaic)
    gt = torch.from_numpy(capture.ground_truth["normals"]).to(torch.float32)
    normals = torch.where(torch.isfinite(gt), gt, torch.tensor([0.0, 0.0, -1.0]))
    result = SimpleNamespace(normals=normals, model="fmbrdf", mask=inputs.mask, rendered=inputs.stokes,
                             observed=inputs.stokes, initial_normals=normals, initial_valid=inputs.mask, filled=None,
                             params={"ior": 1.5, "alpha": alpha, "beta": 0.7, "kappa": 0.0, "k_s": 0.08, "k_b": 0.5})
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        checks = run_self_checks(capture, inputs, result)
    return checks.as_dict(), [w.category.__name__ for w in record]


@pytest.mark.parametrize("demosaic", ["bilinear", "superpixel"])
def test_clipped_core_warns_and_brackets_do_not(demosaic: str) -> None:
    checks, issued = _checks(_capture(None), alpha=0.01, demosaic=demosaic)  # what the fit gives there: α at its bound
    assert "ClippedLobeWarning" in issued
    lobe = checks["clipped_lobe"]
    assert lobe["lights_with_core"] >= 4 and lobe["lights_peak_clipped"] == lobe["lights_with_core"]
    named = [w for w in checks["warnings"] if w["name"] == "ClippedLobeWarning"]
    assert named and "not identified" in named[0]["message"] and "exposures_us" in named[0]["message"]

    checks, issued = _checks(_capture([40000.0, 5000.0, 625.0]), alpha=0.03, demosaic=demosaic)
    assert "ClippedLobeWarning" not in issued
    assert checks["clipped_lobe"]["lights_with_core"] >= 4 and checks["clipped_lobe"]["lights_peak_clipped"] == 0


def test_no_core_on_the_object_no_judgement() -> None:
    inputs = SimpleNamespace(lights=torch.tensor([[[[0.0, 0.0, -1.0]]]]).expand(1, 2, 2, 3),
                             view=torch.tensor([0.0, 0.0, -1.0]).expand(2, 2, 3),
                             mask=torch.ones(2, 2, dtype=torch.bool), saturated=torch.ones(1, 2, 2, dtype=torch.bool))
    tilted = torch.nn.functional.normalize(torch.tensor([0.5, 0.0, -1.0]), dim=0).expand(2, 2, 3)
    lobe = clipped_lobe(inputs, tilted, {"alpha": 0.03})  # half vector 26° from every normal: no core
    assert lobe["core_observations"] == 0 and lobe["clipped_fraction"] is None and lobe["lights_with_core"] == 0
    lobe = clipped_lobe(inputs, inputs.view, {"alpha": 0.03})  # facing the light and camera: all core, all clipped
    assert lobe["core_observations"] == 4 and lobe["clipped_fraction"] == 1.0
    assert lobe["lights_with_core"] == 1 and lobe["lights_peak_clipped"] == 1
    assert ClippedLobeWarning.__mro__[1].__name__ == "PolarshapeWarning"
