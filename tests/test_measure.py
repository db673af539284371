"""polarshape.measure: the material of a sphere or a normal map, written as material.json + report."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from polarshape.errors import ConfigError, OutputExistsError, SuspiciousInputWarning
from polarshape.io.capture import load_capture
from polarshape.io.material import load_material
from polarshape.measure import load_pose, measure_material, mesh_normals, select_frames, sphere_normals

BAEK = {"model": "baek", "ior": 1.6, "k_s": 0.8, "k_d": 0.6, "alpha": 0.2}


def _perspective(scene: dict) -> None:
    """The sphere 0.5 m away from a pinhole camera, ~24 super-pixels across."""
    width = scene["camera"]["width"]
    scene["camera"] = {k: v for k, v in scene["camera"].items() if k != "pixel_size_m"}
    scene["camera"].update(projection="perspective",
                           intrinsics={"fx": 1100.0, "fy": 1100.0, "cx": width / 2 - 0.5, "cy": width / 2 - 0.5})
    scene["objects"][0]["shape"]["center"] = [0.002, -0.001, 0.5]


@pytest.fixture(scope="module")
def baek_capture(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Path:
    return render_sphere(tmp_path_factory.mktemp("baek"), width=64, pixel_size_m=0.028 / 64, lights=3, seed=2,
                         material=BAEK)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ok = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
    return np.degrees(np.arccos(np.clip((a[ok] * b[ok]).sum(-1), -1, 1)))


def test_sphere_normals_match_the_ground_truth(baek_capture: Path) -> None:
    cap = load_capture(baek_capture)
    err = _angle_deg(sphere_normals(cap), cap.ground_truth["normals"])
    assert err.size > 400
    assert np.median(err) < 0.6


def test_sphere_normals_perspective(tmp_path: Path, render_sphere: Callable[..., Path]) -> None:
    cap = load_capture(render_sphere(tmp_path, width=64, pixel_size_m=0.028 / 64, lights=1, seed=2, edit=_perspective))
    normals = sphere_normals(cap)
    gt = cap.ground_truth["normals"]
    facing = np.nan_to_num(-gt[..., 2]) >= 0.5  # the pixels a fit uses (MIN_COS_VIEW)
    err = _angle_deg(normals[facing], gt[facing])
    assert err.size > 100
    assert np.median(err) < 1.0


def test_sphere_without_mask_warns(baek_capture: Path, tmp_path: Path) -> None:
    import dataclasses

    cap = dataclasses.replace(load_capture(baek_capture), mask=None, root=None)
    with pytest.warns(SuspiciousInputWarning, match="no mask.png"):
        normals = sphere_normals(cap)
    assert np.isfinite(normals).all(-1).sum() > 300


def test_measure_writes_material_and_report(baek_capture: Path, tmp_path: Path) -> None:
    out = tmp_path / "mat"
    result = measure_material(baek_capture, shape="sphere", out=out, models=("baek", "lambertian"))
    material = load_material(out / "material.json")
    assert material.model == "baek"  # no fmbrdf asked for: the best model a material file can hold
    assert abs(material.parameters["ior"] - BAEK["ior"]) < 0.05
    assert result.fits["baek"].relative_rmse < result.fits["lambertian"].relative_rmse
    assert material.fit["best_model"] == "baek" == result.ranking[0]
    assert set(material.fit["models"]) == {"baek", "lambertian"}
    assert material.fit["held_out"]["baek"]["frames"] == [0, 1, 2]
    assert material.fit["ranked_by"].startswith("mean held-out")
    report = (out / "report.html").read_text()
    for png in ("intensity_curve.png", "dolp_curve.png", "held_out.png"):
        assert (out / png).stat().st_size > 1000 and png in report
    assert "index of refraction" in report
    with pytest.raises(OutputExistsError, match="already exists"):
        measure_material(baek_capture, shape="sphere", out=out, models=("baek",))
    measure_material(baek_capture, shape="sphere", out=out, models=("baek",), frames=[0], overwrite=True)
    again = json.loads((out / "material.json").read_text())
    assert again["source"]["frames"] == [0] and again["fit"]["held_out"] == {}


def test_measure_never_writes_over_the_capture(baek_capture: Path) -> None:
    with pytest.raises(OutputExistsError, match="input"):
        measure_material(baek_capture, shape="sphere", out=baek_capture, models=("baek",), overwrite=True)
    with pytest.raises(OutputExistsError, match="input"):
        measure_material(baek_capture, shape="sphere", out=baek_capture / "frames", models=("baek",))


def test_normal_map_shape(baek_capture: Path, tmp_path: Path) -> None:
    cap = load_capture(baek_capture)
    path = tmp_path / "normals.npy"
    np.save(path, cap.ground_truth["normals"])
    result = measure_material(baek_capture, shape=path, out=tmp_path / "m", models=("baek",), held_out=False)
    assert abs(result.fits["baek"].params["ior"] - BAEK["ior"]) < 0.05
    np.save(path, -cap.ground_truth["normals"])
    with pytest.raises(ConfigError, match="negate"):
        measure_material(baek_capture, shape=path, out=tmp_path / "m2", models=("baek",))
    np.save(path, cap.ground_truth["normals"][:-1])
    with pytest.raises(ConfigError, match="shape"):
        measure_material(baek_capture, shape=path, out=tmp_path / "m3", models=("baek",))


def test_bad_arguments_are_refused(baek_capture: Path, tmp_path: Path) -> None:
    (tmp_path / "obj.ply").write_text("ply\n")
    with pytest.raises(ConfigError, match="needs --pose"):
        measure_material(baek_capture, shape=tmp_path / "obj.ply", out=tmp_path / "a")
    with pytest.raises(ConfigError, match="unknown reflectance model"):
        measure_material(baek_capture, shape="sphere", out=tmp_path / "b", models=("phong",))
    with pytest.raises(ConfigError, match="composites"):
        measure_material(baek_capture, shape="sphere", out=tmp_path / "c", models=("l_ts",), held_out=False)
    with pytest.raises(ConfigError, match="distinct frame indices"):
        select_frames(load_capture(baek_capture), [0, 7])
    assert not any(p.name in ("a", "b", "c") for p in tmp_path.iterdir())


@pytest.mark.slow
def test_measure_fmbrdf_sphere_writes_the_fmbrdf_material(tmp_path: Path, render_sphere: Callable[..., Path]) -> None:
    capture = render_sphere(tmp_path, width=64, pixel_size_m=0.028 / 64, lights=1, seed=2)
    result = measure_material(capture, shape="sphere", out=tmp_path / "m", models=("fmbrdf", "baek"))
    material = load_material(tmp_path / "m" / "material.json")
    p = material.fmbrdf_params()
    assert abs(p.ior - 1.5) <= 0.03
    assert abs(p.alpha / 0.25 - 1) <= 0.10
    assert abs(p.k_b / p.k_s / 0.5 - 1) <= 0.10
    assert result.ranking[0] == "fmbrdf"


def _sphere_mesh(path: Path) -> Path:
    """sphere.yaml's sphere (radius 0.012 m) as an icosphere mesh centred at its origin."""
    import trimesh

    trimesh.creation.icosphere(subdivisions=5, radius=0.012).export(path)
    return path


def test_mesh_normals_match_the_ground_truth(baek_capture: Path, tmp_path: Path) -> None:
    cap = load_capture(baek_capture)
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.5]  # sphere.yaml's centre
    np.savetxt(tmp_path / "pose.txt", pose[:3])
    normals = mesh_normals(cap, _sphere_mesh(tmp_path / "sphere.ply"), load_pose(tmp_path / "pose.txt"))
    err = _angle_deg(normals, cap.ground_truth["normals"])
    assert err.size > 400
    assert np.median(err) < 0.5
    shifted = mesh_normals(cap, tmp_path / "sphere.ply", load_pose(tmp_path / "pose.txt"), pixel_size_m=1e-3)
    assert np.isfinite(shifted).all(-1).sum() < np.isfinite(normals).all(-1).sum()  # the scale matters


def test_measure_with_a_mesh(baek_capture: Path, tmp_path: Path) -> None:
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.5]
    np.save(tmp_path / "pose.npy", pose)
    result = measure_material(baek_capture, shape=_sphere_mesh(tmp_path / "s.ply"), pose=tmp_path / "pose.npy",
                              out=tmp_path / "m", models=("baek",), held_out=False)
    assert abs(result.fits["baek"].params["ior"] - BAEK["ior"]) < 0.05
    assert load_material(tmp_path / "m" / "material.json").source["pose"].endswith("pose.npy")
    np.save(tmp_path / "bad.npy", 2 * pose)
    with pytest.raises(ConfigError, match="not a rotation"):
        load_pose(tmp_path / "bad.npy")
    np.save(tmp_path / "far.npy", np.array([[1, 0, 0, 5.0], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]))
    with pytest.raises(ConfigError, match="covers no pixel"):
        measure_material(baek_capture, shape=tmp_path / "s.ply", pose=tmp_path / "far.npy", out=tmp_path / "m2",
                         models=("baek",))
