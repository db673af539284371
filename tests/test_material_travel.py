"""Materials that travel: a ``material.json`` as ``polarshape run``'s known material
(``recovery.material``, fixed or initial) and as a scene object's material (``material: {file: ...}``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.brdf.params import FMBRDF_PARAM_NAMES, FMBRDFParams
from polarshape.cli import main
from polarshape.config import ConfigError, load_run_config
from polarshape.io.material import MaterialFile, write_material
from polarshape.pipeline import run_pipeline
from polarshape.recover.options import RecoveryOptions
from polarshape.scene.config import load_scene_config
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "configs" / "scenes" / "sphere.yaml"

#: The same material fitted once and then fixed gives the same normals (measured on this 64-px
#: sphere: mean difference ≈ 0.001°); the brief's bound.
MAX_NORMAL_CHANGE_DEG = 0.05


def _true_material() -> FMBRDFParams:
    """The FMBRDF parameters of the shipped sphere scene's object."""
    material = yaml.safe_load(SPHERE.read_text())["objects"][0]["material"]
    return FMBRDFParams(**{name: float(material[name]) for name in FMBRDF_PARAM_NAMES})


def _run_config(folder: Path, capture: Path, name: str, **recovery: object) -> Path:
    """A fast fmbrdf run config over ``capture`` (relative paths start at ``folder``)."""
    data = {"progress": False, "input": {"type": "capture", "path": str(capture)},
            "recovery": {"model": "fmbrdf", **recovery}, "report": {"enabled": False},
            "mesh": {"poisson": False, "obj": False}, "export": {"exr": False}}
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _run(folder: Path, capture: Path, name: str, **recovery: object) -> tuple[dict, np.ndarray]:
    params = run_pipeline(load_run_config(_run_config(folder, capture, name, **recovery)), folder / f"res_{name}").params
    return params, np.load(folder / f"res_{name}" / "normals.npy")


def _mean_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    both = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    assert both.sum() > 100
    cos = np.clip((a[both] * b[both]).sum(-1) / np.linalg.norm(a[both], axis=-1) / np.linalg.norm(b[both], axis=-1), -1, 1)
    return float(np.degrees(np.arccos(cos)).mean())


@pytest.fixture(scope="module")
def sphere_capture(render_sphere, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped sphere at 64×64 raw pixels (32×32 super-pixels) under its first 8 lights."""
    return render_sphere(tmp_path_factory.mktemp("travel"), width=64, pixel_size_m=4.0e-4, lights=8, seed=3)


@pytest.fixture(scope="module")
def fitted_run(sphere_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, np.ndarray]:
    """A run that fits the material, and its material.json beside it: (folder, params.json, normals)."""
    folder = tmp_path_factory.mktemp("fitted")
    params, normals = _run(folder, sphere_capture, "fit")
    fitted = FMBRDFParams(**{name: params["params"][name] for name in FMBRDF_PARAM_NAMES})
    write_material(folder / "fitted.json", MaterialFile.from_fmbrdf(fitted, source={"run": str(folder / "res_fit")}))
    write_material(folder / "truth.json", MaterialFile.from_fmbrdf(_true_material(), source={"scene": str(SPHERE)}))
    return folder, params, normals


@pytest.mark.slow
def test_fixed_material_gives_the_same_normals_with_no_material_fit(fitted_run, sphere_capture: Path) -> None:
    folder, fit_params, fit_normals = fitted_run
    assert fit_params["recovery_counts"]["material_fits"] >= 3 and fit_params["material"] is None
    params, normals = _run(folder, sphere_capture, "fixed", material="fitted.json")  # relative to the config
    assert _mean_angle_deg(normals, fit_normals) < MAX_NORMAL_CHANGE_DEG
    counts = params["recovery_counts"]
    # faster: no non-linear fit, no κ test; only the closed-form albedo steps
    assert counts.get("material_fits", 0) == 0 and counts.get("material_fit_iterations", 0) == 0
    assert counts.get("kappa_probes", 0) == 0 and counts["albedo_solves"] >= 1
    record = params["material"]
    assert record["file"] == str(folder / "fitted.json") and record["use"] == "fixed" and record["applied"]
    for name in ("ior", "alpha", "beta", "kappa"):  # kept exactly
        assert params["params"][name] == pytest.approx(fit_params["params"][name], rel=1e-9)
        assert record["parameters"][name] == pytest.approx(fit_params["params"][name], rel=1e-9)
    assert any("fixed by recovery.material" in s for s in params["skipped"])


@pytest.mark.slow
def test_fixed_true_material_matches_the_fit_against_ground_truth(fitted_run, sphere_capture: Path) -> None:
    """The scene's own material, in scene units: its albedos are not the capture's (the sensor's
    electrons per radiance scale them), so k_s is solved again and the normals are as good."""
    folder, fit_params, fit_normals = fitted_run
    params, normals = _run(folder, sphere_capture, "truth", material=str(folder / "truth.json"))
    assert params["params"]["alpha"] == 0.25 and params["params"]["ior"] == 1.5
    assert params["params"]["k_s"] != pytest.approx(1.0, rel=0.05)  # re-solved in the capture's units
    fit_error = fit_params["metrics"]["normals"]["mean_deg"]
    assert abs(params["metrics"]["normals"]["mean_deg"] - fit_error) < MAX_NORMAL_CHANGE_DEG


@pytest.mark.slow
def test_a_material_measured_on_a_sphere_travels_to_a_run(fitted_run, sphere_capture: Path, render_sphere,
                                                          tmp_path: Path) -> None:  # noqa: ANN001
    """The issue's round trip: ``polarshape material`` on a one-light capture of the material →
    material.json → ``polarshape run`` of another capture with it fixed: no material fit, and normals
    as good as the run that fits the material (vs ground truth, within 0.05°)."""
    from polarshape.measure import measure_material

    (tmp_path / "m").mkdir()
    one_light = render_sphere(tmp_path / "m", width=64, pixel_size_m=4.0e-4, lights=1, seed=7)
    measured = measure_material(one_light, shape="sphere", out=tmp_path / "measured", models=("fmbrdf",),
                                held_out=False)
    folder, fit_params, _ = fitted_run
    params, _ = _run(tmp_path, sphere_capture, "measured", material=str(measured.out / "material.json"))
    assert params["recovery_counts"].get("material_fits", 0) == 0 and params["material"]["use"] == "fixed"
    assert params["params"]["ior"] == pytest.approx(measured.material.parameters["ior"])
    fit_error = fit_params["metrics"]["normals"]["mean_deg"]
    assert abs(params["metrics"]["normals"]["mean_deg"] - fit_error) < MAX_NORMAL_CHANGE_DEG


@pytest.mark.slow
def test_initial_material_converges_to_the_same(fitted_run, sphere_capture: Path) -> None:
    folder, fit_params, fit_normals = fitted_run
    start = FMBRDFParams(ior=1.3, alpha=0.4, beta=2.5, kappa=0.0, k_s=1.0, k_b=0.5)  # off, not the default guess
    write_material(folder / "start.json", MaterialFile.from_fmbrdf(start))
    params, normals = _run(folder, sphere_capture, "initial", material="start.json", material_use="initial")
    assert params["recovery_counts"]["material_fits"] >= 1 and params["material"]["use"] == "initial"
    assert params["params"]["alpha"] == pytest.approx(fit_params["params"]["alpha"], rel=0.02)
    assert params["params"]["ior"] == pytest.approx(fit_params["params"]["ior"], abs=0.02)
    assert _mean_angle_deg(normals, fit_normals) < MAX_NORMAL_CHANGE_DEG


def test_global_albedo_keeps_the_ratio_of_a_fixed_material(sphere_capture: Path, tmp_path: Path) -> None:
    write_material(tmp_path / "truth.json", MaterialFile.from_fmbrdf(_true_material()))
    params, _ = _run(tmp_path, sphere_capture, "global", material="truth.json", per_pixel_albedo=False,
                     max_outer_iterations=3, coarse_to_fine=False, propagate=False)
    assert params["params"]["r_k"] == pytest.approx(0.5, rel=1e-6)  # the scene's k_b / k_s
    assert params["params"]["k_s"] > 2.0  # scaled to the capture (≈ 7.6 here), not the scene's 1.0


def _write_bad(folder: Path) -> dict[str, Path]:
    lam = MaterialFile(model="lambertian", parameters={"k_d": 0.5})
    write_material(folder / "lambertian.json", lam, overwrite=True)
    (folder / "broken.json").write_text('{"format": "polarshape-material/1", "model": "fmbrdf", "parameters": {"ior": 1.5}}')
    (folder / "notjson.json").write_text("{ior: 1.5")
    return {"missing": folder / "missing.json", "lambertian": folder / "lambertian.json",
            "broken": folder / "broken.json", "notjson": folder / "notjson.json"}


@pytest.mark.parametrize("kind, problem", [
    ("missing", "cannot read"), ("lambertian", "not 'fmbrdf'"), ("broken", "missing"), ("notjson", "not valid JSON"),
])
def test_an_invalid_material_is_exit_2_naming_the_key(kind: str, problem: str, sphere_capture: Path, tmp_path: Path,
                                                       capsys) -> None:
    path = _write_bad(tmp_path)[kind]
    config = _run_config(tmp_path, sphere_capture, "bad", material=path.name)
    with pytest.raises(ConfigError, match="recovery.material") as err:
        load_run_config(config)
    assert problem in str(err.value) and str(path) in str(err.value)
    assert main(["run", str(config), "--out", str(tmp_path / "res")]) == 2
    assert "recovery.material" in capsys.readouterr().err
    assert not (tmp_path / "res").exists()  # refused before anything ran


def test_a_material_with_the_lambertian_model_is_refused(tmp_path: Path) -> None:
    write_material(tmp_path / "m.json", MaterialFile.from_fmbrdf(_true_material()))
    with pytest.raises(ValueError, match="recovery.material applies to the fmbrdf model"):
        RecoveryOptions(model="lambertian", material=str(tmp_path / "m.json"))
    assert RecoveryOptions(model="auto", material=str(tmp_path / "m.json")).material_use == "fixed"


def _scene(folder: Path, material: dict, name: str) -> Path:
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=32, height=32, pixel_size_m=8.0e-4)
    scene["lights"] = scene["lights"][:3]
    scene["objects"][0]["material"] = material
    path = folder / name
    path.write_text(yaml.safe_dump(scene))
    return path


def test_a_scene_material_file_renders_the_inline_material(tmp_path: Path) -> None:
    inline = yaml.safe_load(SPHERE.read_text())["objects"][0]["material"]
    (tmp_path / "materials").mkdir()
    write_material(tmp_path / "materials" / "sphere.json", MaterialFile.from_fmbrdf(_true_material()))
    frames = []
    for material, name in ((inline, "inline.yaml"), ({"file": "materials/sphere.json"}, "file.yaml")):
        with SimulatedCamera(_scene(tmp_path, material, name), seed=1) as camera:
            frames.append(camera.render_capture(progress=False).frames)
    assert frames[0].max() > 0
    np.testing.assert_array_equal(frames[0], frames[1])
    shifted = {**inline, "alpha": 0.4}  # the comparison sees a different material
    with SimulatedCamera(_scene(tmp_path, shifted, "other.yaml"), seed=1) as camera:
        assert not np.array_equal(camera.render_capture(progress=False).frames, frames[0])


def test_scene_material_files_map_to_the_baselines_or_are_refused(tmp_path: Path) -> None:
    write_material(tmp_path / "lam.json", MaterialFile(model="lambertian", parameters={"k_d": 0.7}))
    write_material(tmp_path / "baek.json", MaterialFile(
        model="baek", parameters={"ior": 1.4, "k_s": 0.8, "k_d": 0.3, "alpha": 0.2}))
    write_material(tmp_path / "on.json", MaterialFile(model="oren_nayar", parameters={"k_d": 0.5, "sigma": 0.3}))
    lam = load_scene_config(_scene(tmp_path, {"file": "lam.json"}, "lam.yaml")).build_scene().objects[0].material
    assert isinstance(lam, LambertianMaterial) and lam.k_d == 0.7
    baek = load_scene_config(_scene(tmp_path, {"file": "baek.json"}, "baek.yaml")).build_scene().objects[0].material
    assert isinstance(baek, BaekMaterial) and (baek.ior, baek.k_s, baek.k_d, baek.alpha) == (1.4, 0.8, 0.3, 0.2)
    fm = load_scene_config(_scene(tmp_path, {"file": str(tmp_path / "lam.json")}, "abs.yaml"))
    assert not isinstance(fm.build_scene().objects[0].material, FMBRDFMaterial)
    with pytest.raises(ValueError, match=r"objects\.0\.material.*oren_nayar.*no simulator material"):
        load_scene_config(_scene(tmp_path, {"file": "on.json"}, "on.yaml"))
    with pytest.raises(ValueError, match=r"objects\.0\.material.*missing\.json.*cannot read"):
        load_scene_config(_scene(tmp_path, {"file": "missing.json"}, "missing.yaml"))


@pytest.mark.slow
def test_params_json_records_no_material_without_one(fitted_run) -> None:
    folder, params, _ = fitted_run
    on_disk = json.loads((folder / "res_fit" / "params.json").read_text())
    assert on_disk["material"] is None and on_disk["recovery_counts"] == params["recovery_counts"]
