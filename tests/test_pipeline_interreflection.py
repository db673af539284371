"""``polarshape run`` on a concave object: the light it sends onto itself marked, or taken out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from polarshape.config import parse_run_config
from polarshape.errors import InterreflectionWarning
from polarshape.pipeline import run_pipeline
from polarshape.scene.config import load_scene_config

REPO = Path(__file__).resolve().parents[1]
_CRATER = load_scene_config(REPO / "configs" / "scenes" / "crater.yaml")
#: the capture's albedo per physical albedo (what a white reference target would measure)
ALBEDO_SCALE = _CRATER.sensor.to_model().full_scale_per_radiance(_CRATER.camera.exposure_us, _CRATER.camera.gain_db)


def _crater(tmp_path: Path) -> Path:
    d = load_scene_config(REPO / "configs" / "scenes" / "crater.yaml").model_dump(mode="json")
    d["camera"].update(width=96, height=96, pixel_size_m=2.6e-4)
    d["objects"][0]["shape"]["resolution"] = 161
    d["render"]["interreflection"]["samples"] = 48
    path = tmp_path / "crater.yaml"
    path.write_text(json.dumps(d))
    return path


def _run(tmp_path: Path, scene: Path, name: str, **interreflection: object) -> tuple[dict, np.ndarray]:
    config = parse_run_config({
        "input": {"type": "simulated", "scene": str(scene), "save_capture": False},
        "recovery": {"model": "fmbrdf"}, "progress": False, "report": {"enabled": False},
        "validation": {"holdout": "none"}, "interreflection": interreflection,
    }, name)
    out = tmp_path / name
    run_pipeline(config, out)
    params = json.loads((out / "params.json").read_text())
    return params, np.load(out / "error_map.npy")


def _inside(errors: np.ndarray) -> np.ndarray:
    h, w = errors.shape
    yy, xx = np.mgrid[0:h, 0:w]
    rho = np.hypot(xx - (w - 1) / 2, yy - (h - 1) / 2) * 2 * 2.6e-4
    return np.isfinite(errors) & (rho < 0.0075)


@pytest.mark.slow
def test_concavity_marked_without_a_scale_and_taken_out_with_one(tmp_path: Path) -> None:
    scene = _crater(tmp_path)
    with pytest.warns(InterreflectionWarning, match="sees itself"):
        marked, e_marked = _run(tmp_path, scene, "marked")
    record = marked["interreflection"]
    assert not record["applied"] and record["marked_pixels"] > 0
    assert (tmp_path / "marked" / "interreflection.npy").is_file()
    corrected, e_corrected = _run(tmp_path, scene, "corrected", albedo_scale=ALBEDO_SCALE, iterations=2)
    assert corrected["interreflection"]["applied"]
    inside = _inside(e_marked) & _inside(e_corrected)
    # taking the bounce out straightens the normals inside the dish (measured: 2.1° -> 0.5° at 128²)
    assert float(np.mean(e_corrected[inside])) < 0.6 * float(np.mean(e_marked[inside]))
    assert float(np.nanmean(e_corrected)) <= float(np.nanmean(e_marked))


def test_convex_object_skips_the_bounce(tmp_path: Path) -> None:
    d = load_scene_config(REPO / "configs" / "scenes" / "sphere.yaml").model_dump(mode="json")
    d["camera"].update(width=48, height=48, pixel_size_m=5.4e-4)
    scene = tmp_path / "sphere.yaml"
    scene.write_text(json.dumps(d))
    params, _ = _run(tmp_path, scene, "sphere")
    record = params["interreflection"]
    assert record["mode"] == "auto" and not record["applied"] and record["rounds"][0]["area"] == 0.0
    assert any(s.startswith("interreflection: no concavity") for s in params["skipped"])


def test_mode_on_needs_an_albedo_scale() -> None:
    with pytest.raises(Exception, match="albedo_scale"):
        parse_run_config({"input": {"type": "simulated", "scene": "x.yaml"}, "interreflection": {"mode": "on"}}, "t")
