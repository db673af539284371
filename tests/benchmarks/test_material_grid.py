"""benchmarks/material_grid.py: its scenes are what it says, its convergence figures read the solver's
history right, and (slow) one tiny case runs end to end and prints its row."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from polarshape.scene.config import parse_scene_config

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def grid(benchmark_module):  # noqa: ANN001, ANN201 (a script module)
    return benchmark_module("material_grid")


def test_case_names_round_trip(grid) -> None:  # noqa: ANN001
    name = grid.case_name(0.03, 50.0, "perspective", 256, 13)
    assert name == "a0.03_k50_perspective_256@13"
    assert grid.parse_case(name) == (0.03, 50.0, "perspective", 256, 13)


def test_an_exposure_other_than_the_scenes_is_in_the_name_and_the_scene(grid, tmp_path: Path) -> None:  # noqa: ANN001
    import yaml

    name = grid.case_name(0.03, 0.0, "orthographic", 256, 13, 300.0)
    assert name == "a0.03_k0_orthographic_256@13_e300us"
    assert grid.parse_case(name) == (0.03, 0.0, "orthographic", 256, 13) and grid.parse_exposure(name) == 300.0
    assert grid.parse_exposure(grid.case_name(0.03, 0.0, "orthographic", 256, 13)) is None
    raw = yaml.safe_load(grid.scene_file(0.03, 0.0, "orthographic", 64, 13, tmp_path / "s.yaml", 300.0).read_text())
    assert parse_scene_config(raw).camera.exposure_us == 300.0
    default = yaml.safe_load(grid.scene_file(0.03, 0.0, "orthographic", 64, 13, tmp_path / "d.yaml").read_text())
    assert parse_scene_config(default).camera.exposure_us == 10000.0


def test_a_non_positive_exposure_is_refused_with_the_option_named() -> None:
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "material_grid.py"), "--exposure-us", "0"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--exposure-us must be a positive number" in proc.stderr, proc.stderr


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_scene_has_the_material_and_camera_of_the_case(grid, camera: str, tmp_path: Path) -> None:  # noqa: ANN001
    import yaml

    path = grid.scene_file(0.1, 50.0, camera, 64, 13, tmp_path / "scene.yaml")
    raw = yaml.safe_load(path.read_text())
    scene = parse_scene_config(raw)
    material = raw["objects"][0]["material"]
    assert (material["alpha"], material["kappa"]) == (0.1, 50.0)
    assert len(raw["lights"]) == 13 and scene.camera.projection == camera
    assert (scene.camera.width, scene.camera.height) == (128, 128)
    if camera == "perspective":  # the outline's radius 0.465 · 128 raw pixels, as the orthographic sphere's
        sphere = raw["objects"][0]["shape"]
        half = math.asin(sphere["radius"] / sphere["center"][2])
        assert scene.camera.intrinsics.fx * math.tan(half) == pytest.approx(0.465 * 128)


def _params(history: list[dict], skipped: list[str] | None = None) -> dict:
    return {"losses": {"history": history}, "skipped": skipped or []}


def test_convergence_of_the_alternation(grid) -> None:  # noqa: ANN001
    rounds = [{"stage": "level1", "iteration": i, "loss": v} for i, v in enumerate([4.0, 2.0, 1.5, 1.4996, 1.4995])]
    finer = [{"stage": "level0", "iteration": 0, "loss": 9.0}]
    c = grid.convergence(_params(rounds + finer), max_outer=20)
    assert c["outer"] == 5 and c["converged"] is True
    assert c["rel_change"] == pytest.approx(1e-4 / 1.4996)
    # ran out of outer iterations with the loss still falling: not converged
    falling = [{"stage": "level1", "iteration": i, "loss": 2.0 * 0.99**i} for i in range(20)]
    assert grid.convergence(_params(falling), max_outer=20)["converged"] is False
    # the Lambertian path has no solve
    assert grid.convergence(_params([{"iteration": 0, "loss": 1.0}]), max_outer=20)["outer"] == 0


def test_convergence_of_the_joint_solve(grid) -> None:  # noqa: ANN001
    history = [{"stage": "level1", "solver": "start", "iteration": 0, "loss": 3.0}] + [
        {"stage": "level1", "solver": "joint", "iteration": i, "loss": 1.0, "rel_change": r}
        for i, r in enumerate([1e-2, 1e-4, 3e-6], 1)]
    c = grid.convergence(_params(history), max_outer=20)
    assert (c["outer"], c["converged"], c["rel_change"]) == (3, True, 3e-6)
    c = grid.convergence(_params(history, ["recovery: joint: not converged within max_outer_iterations=3"]), 20)
    assert c["converged"] is False


@pytest.mark.slow
def test_one_tiny_case_end_to_end(tmp_path: Path) -> None:
    """24² super-pixels, 13 lights, one material: the row, the median line and the JSON record."""
    out = subprocess.run([sys.executable, str(BENCHMARKS / "material_grid.py"), "--size", "24", "--alphas", "0.3",
                          "--kappas", "0", "--cameras", "orthographic", "--work", str(tmp_path),
                          "--json", str(tmp_path / "grid.json")], capture_output=True, text=True, check=True).stdout
    assert "| 0.3 | 0 | orthographic |" in out and "max/median 1.00" in out
    record = json.loads((tmp_path / "grid.json").read_text())["a0.3_k0_orthographic_24@13"]
    assert record["total"] > 0 and record["model"] in ("fmbrdf", "lambertian")
    assert math.isfinite(record["mean_err_deg"]) and record["mean_err_deg"] < 5.0
