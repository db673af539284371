"""``polarshape run``: end to end on a small simulated sphere, atomic result folders, evaluation helpers."""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
import yaml

from polarshape.cli.run import add_parsers
from polarshape.config import ConfigError, parse_run_config
from polarshape.io.export import read_exr, read_normal_map_png
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import load_capture
from polarshape.io.images import read_image
from polarshape.metrics import depth_rmse_aligned
from polarshape.pipeline import STAGES, PipelineError, run_pipeline

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "configs" / "scenes" / "sphere.yaml"

# Figures measured on this scene (lambertian model, seed 3): mean 4.6°, median 3.3°, depth 1.3 % of
# its range; the bounds leave room for noise-seed and platform differences, and fail on a sign or
# frame error (tens of degrees).
MAX_MEAN_ERROR_DEG = 8.0
MAX_MEDIAN_ERROR_DEG = 6.0
MAX_DEPTH_RELATIVE_RMSE = 0.05


def _small_scene(folder: Path) -> Path:
    """The shipped sphere at 128×128 raw pixels (64×64 super-pixels) under its first 8 lights."""
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=128, height=128, pixel_size_m=2.0e-4)
    scene["lights"] = scene["lights"][:8]
    path = folder / "small_sphere.yaml"
    path.write_text(yaml.safe_dump(scene))
    return path


def _config(folder: Path, **sections: object) -> Path:
    """A run config in ``folder`` (relative paths start there)."""
    data = {"progress": False, "recovery": {"model": "lambertian"}, **sections}
    path = folder / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def simulated_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """One full run from a config with a simulated input: (result folder, params.json)."""
    folder = tmp_path_factory.mktemp("run")
    _small_scene(folder)
    config_path = _config(
        folder,
        input={"type": "simulated", "scene": "small_sphere.yaml", "seed": 3},
        mesh={"poisson": True, "poisson_depth": 7, "watertight": True},
    )
    from polarshape.config import load_run_config

    result = run_pipeline(load_run_config(config_path), folder / "result", config_path=config_path)
    assert result.out_dir == (folder / "result").absolute()
    return result.out_dir, json.loads((result.out_dir / "params.json").read_text())


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small sphere rendered once into a capture folder (with mask and ground truth)."""
    from polarshape.acquisition.simulated import SimulatedCamera

    folder = tmp_path_factory.mktemp("capture")
    with SimulatedCamera(_small_scene(folder), seed=3) as camera:
        camera.render_capture(folder / "capture", progress=False)
    return folder / "capture"


@pytest.fixture
def capture_config(small_capture: Path, tmp_path: Path) -> Path:
    """A fast config reading the small capture (no mesh extras, no report)."""
    return _config(
        tmp_path,
        input={"type": "capture", "path": str(small_capture)},
        mesh={"obj": False},
        report={"enabled": False},
        export={"exr": False},
    )


def _load(path: Path):
    from polarshape.config import load_run_config

    return load_run_config(path)


@pytest.mark.slow
def test_end_to_end_simulated_capture(simulated_run: tuple[Path, dict]) -> None:
    out, params = simulated_run
    capture = load_capture(out / "capture")
    mask = capture.mask
    assert mask.shape == (64, 64) and mask.sum() > 1500

    normals = np.load(out / "normals.npy")
    assert normals.shape == (64, 64, 3) and normals.dtype == np.float32
    assert np.isnan(normals[~mask]).all()
    assert np.allclose(np.linalg.norm(normals[mask], axis=-1), 1.0, atol=1e-4)
    assert (normals[mask][:, 2] < 0).all()  # camera-facing: n_z < 0 (spec §1)
    png = read_normal_map_png(out / "normal_map.png")
    assert np.allclose(png[mask], normals[mask], atol=2e-4) and np.isnan(png[~mask]).all()
    alpha = cv2.imread(str(out / "normal_map.png"), cv2.IMREAD_UNCHANGED)[..., 3]  # 16-bit BGRA
    assert alpha.dtype == np.uint16 and np.array_equal(alpha, np.where(mask, 65535, 0))
    exr, names = read_exr(out / "normals.exr")
    assert names == ("R", "G", "B", "A") and np.allclose(exr[mask][:, :3], normals[mask])
    assert np.array_equal(exr[..., 3], mask.astype(np.float32)) and np.all(exr[~mask] == 0)
    assert read_image(out / "mask.png").astype(bool).sum() == mask.sum()
    filled = read_image(out / "filled.png").astype(bool)  # lambertian too: pixels without data are marked
    assert filled.shape == mask.shape and params["capture"]["filled_pixels"] == int(filled.sum()) < 0.05 * mask.sum()

    # ground truth: normals and scale/offset-aligned depth
    metrics = params["metrics"]
    assert metrics["normals"]["pixels"] == mask.sum()
    assert metrics["normals"]["mean_deg"] < MAX_MEAN_ERROR_DEG
    assert metrics["normals"]["median_deg"] < MAX_MEDIAN_ERROR_DEG
    assert metrics["normals"]["p90_deg"] >= metrics["normals"]["median_deg"]
    error_map = np.load(out / "error_map.npy")
    assert np.nanmean(error_map) == pytest.approx(metrics["normals"]["mean_deg"], rel=1e-5)
    depth = np.load(out / "depth.npy")
    assert depth.shape == (64, 64) and np.isfinite(depth[mask]).all() and np.isnan(depth[~mask]).all()
    check = depth_rmse_aligned(depth, capture.ground_truth["depth"], mask)
    assert check["relative"] < MAX_DEPTH_RELATIVE_RMSE
    assert metrics["depth"]["rmse"] == pytest.approx(check["rmse"], rel=1e-3)
    assert 0.5 < check["scale"] < 1.5  # metric depth from the scene's pixel size

    # meshes: one grid vertex per mask pixel, with normals and albedo colours, in the opengl frame
    # (default): the camera frame turned by diag(1, -1, -1), faces toward the viewer at +z
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.vertices) == mask.sum() == params["mesh"]["vertices"]
    assert len(mesh.faces) > 1.8 * mask.sum()
    assert mesh.visual.vertex_colors.shape == (mask.sum(), 4)
    assert params["mesh"]["frame"] == "opengl" and params["mesh"]["units"] == "metres"
    assert params["mesh"]["from_camera_frame"] == [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
    np.testing.assert_allclose(mesh.vertices[:, 2], -depth[mask], rtol=1e-6)  # float32 in the file
    assert np.all(mesh.face_normals[:, 2] > 0) and np.all(mesh.vertex_normals[:, 2] > 0)
    assert b"comment polarshape units: metres\n" in (out / "mesh.ply").read_bytes()[:1000]
    assert "# polarshape frame: opengl" in (out / "mesh.obj").read_text()[:1000]
    assert len(trimesh.load(out / "mesh.obj", process=False).vertices) == mask.sum()
    # Poisson solid: albedo colours, and params.json's flags are open3d's verdict on the file
    import open3d as o3d

    poisson = trimesh.load(out / "mesh_poisson.ply", process=False)
    assert poisson.visual.vertex_colors.shape == (len(poisson.vertices), 4)
    assert np.ptp(poisson.visual.vertex_colors[:, 0].astype(int)) > 0 and params["mesh"]["poisson"]["colours"]
    written = o3d.io.read_triangle_mesh(str(out / "mesh_poisson.ply"))
    flags = params["mesh"]["poisson"]
    assert flags["watertight"] == written.is_watertight() == params["metrics"]["mesh_poisson_watertight"]
    assert flags["self_intersecting"] == written.is_self_intersecting()
    assert flags["edge_manifold"] == written.is_edge_manifold()
    assert flags["vertex_manifold"] == written.is_vertex_manifold()
    assert flags["watertight"] and flags["triangles"] == len(poisson.faces)  # the mirror-closed sphere, repaired

    # albedo map, params.json, report
    albedo = np.load(out / "albedo.npy")
    assert np.isfinite(albedo[mask]).all() and (albedo[mask] > 0).all()
    assert read_image(out / "albedo.png").dtype == np.uint16
    assert params["model"] == "lambertian" and params["format"] == "polarshape-result/1"
    assert set(STAGES) <= set(params["timings_s"]) and params["timings_s"]["total"] > 0
    assert params["losses"]["final"]["loss"] > 0 and "albedo_median" in params["params"]
    assert any(s.startswith("recovery: reflectometry") for s in params["skipped"])
    assert params["integration"]["pixel_size_m"] == pytest.approx(4.0e-4)
    html = (out / "report.html").read_text()
    for name in ("maps", "polarisation", "fit_curves", "residuals", "error_map"):
        assert (out / "report" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"report/{name}.png" in html
    assert yaml.safe_load((out / "config.yaml").read_text())["input"]["type"] == "simulated"
    assert params["capture"]["source"] == str(out / "capture")  # not the temporary .partial-* folder
    assert params["warnings"] == []
    assert not list(out.parent.glob(".result.partial-*"))


def test_mesh_frame_opencv_units_and_an_open_poisson_surface(capture_config: Path, tmp_path: Path) -> None:
    import open3d as o3d

    config = _load(capture_config)
    mesh = config.mesh.model_copy(update={"frame": "opencv", "poisson": True, "poisson_depth": 6, "watertight": False})
    result = run_pipeline(config.model_copy(update={"mesh": mesh}), tmp_path / "res")
    out, info = result.out_dir, result.params["mesh"]
    assert info["frame"] == "opencv" and info["files"] == ["mesh.ply", "mesh_poisson.ply"]
    grid = trimesh.load(out / "mesh.ply", process=False)  # the camera frame as it is: faces toward −z
    depth = np.load(out / "depth.npy")[read_image(out / "mask.png") > 0]
    np.testing.assert_allclose(grid.vertices[:, 2], depth, rtol=1e-6)
    assert np.all(grid.face_normals[:, 2] < 0)
    assert b"comment polarshape frame: opencv: x right, y down" in (out / "mesh_poisson.ply").read_bytes()[:1000]
    # a trimmed (open) Poisson surface is not watertight, and params.json says so
    written = o3d.io.read_triangle_mesh(str(out / "mesh_poisson.ply"))
    assert info["poisson"]["boundary_edges"] > 0 and not info["poisson"]["mirror_closed"]
    assert info["poisson"]["watertight"] is written.is_watertight() is False
    assert info["poisson"]["self_intersecting"] == written.is_self_intersecting()
    assert result.params["metrics"]["mesh_poisson_watertight"] is False


def test_meshes_without_a_metric_scale_say_superpixels(small_capture: Path, tmp_path: Path) -> None:
    """An orthographic capture with no pixel size anywhere (no integration.pixel_size_m, no scene in
    its ground truth): depth and meshes are in super-pixels, and the files and params.json say so."""
    bare = tmp_path / "bare"
    shutil.copytree(small_capture, bare)
    (bare / "ground_truth" / "scene.json").unlink()
    config = _load(_config(tmp_path, input={"type": "capture", "path": str(bare)}, mesh={"obj": False},
                           report={"enabled": False}, export={"exr": False}, recovery={"model": "lambertian"}))
    result = run_pipeline(config, tmp_path / "res")
    assert result.params["mesh"]["units"] == "superpixels"
    assert b"comment polarshape units: super-pixels (no metric scale" in (result.out_dir / "mesh.ply").read_bytes()[:1000]


def test_cli_prints_summary_and_refuses_existing_folder(capture_config: Path, tmp_path: Path, capsys) -> None:
    parser = argparse.ArgumentParser()
    add_parsers(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "res"

    def main(*argv: str) -> int:
        args = parser.parse_args(["run", str(capture_config), *argv])
        return int(args.handler(args))

    assert main("--out", str(out), "--quiet") == 0
    line = capsys.readouterr().out.strip()
    assert str(out) in line and "normal error mean" in line and line.endswith(" s")
    before = (out / "params.json").read_bytes()
    assert main("--out", str(out), "--quiet") == 1
    assert "already exists" in capsys.readouterr().err
    assert (out / "params.json").read_bytes() == before
    assert main("--out", str(out), "--quiet", "--overwrite") == 0
    assert (out / "params.json").read_bytes() != before  # new timings
    assert main("--quiet") == 2  # no --out and no output: in the config
    assert "output" in capsys.readouterr().err


def test_refuses_to_overwrite_a_result_or_an_input(capture_config: Path, small_capture: Path, tmp_path: Path) -> None:
    config = _load(capture_config)
    out = tmp_path / "existing"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="refusing to overwrite"):
        run_pipeline(config, out)
    assert (out / "keep.txt").read_text() == "mine"
    capture_dir = small_capture
    frames_before = sorted(p.name for p in (capture_dir / "frames").iterdir())
    for target in (capture_dir, capture_dir.parent):  # the input, and a folder that holds it
        with pytest.raises(OutputExistsError, match="input"):
            run_pipeline(config, target, overwrite=True)
    assert sorted(p.name for p in (capture_dir / "frames").iterdir()) == frames_before
    with pytest.raises(OutputExistsError, match="input"):  # the config file's own folder
        run_pipeline(config, capture_config.parent, overwrite=True, config_path=capture_config)


def test_overwrite_replaces_only_a_result_and_nothing_inside_an_input(
    capture_config: Path, small_capture: Path, tmp_path: Path
) -> None:
    """Issue 12's data-loss cases: --overwrite into the capture's frames folder, onto its capture.yaml,
    or onto a folder that is not a polarshape result is refused and nothing is touched; a previous
    result (and an empty folder) is replaced."""
    config = _load(capture_config)
    frames = small_capture / "frames"
    before = sorted(p.name for p in frames.iterdir())
    yaml_before = (small_capture / "capture.yaml").read_text()
    for target, reason in ((frames, "inside the input"), (small_capture / "capture.yaml", "inside the input"),
                           (small_capture / "new_result", "inside the input")):
        with pytest.raises(OutputExistsError, match=reason):
            run_pipeline(config, target, overwrite=True)
    assert sorted(p.name for p in frames.iterdir()) == before
    assert (small_capture / "capture.yaml").read_text() == yaml_before and not (small_capture / "new_result").exists()
    other = tmp_path / "projects"
    (other / "cap_a").mkdir(parents=True)
    (other / "notes.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="not a polarshape result"):
        run_pipeline(config, other, overwrite=True)
    assert (other / "notes.txt").read_text() == "mine" and (other / "cap_a").is_dir()
    assert not [p for p in tmp_path.rglob(".*partial*")]  # refused before anything was created
    empty = tmp_path / "empty"
    empty.mkdir()
    first = run_pipeline(config, empty, overwrite=True)
    again = run_pipeline(config, empty, overwrite=True)  # a previous result: replaced
    assert first.params["format"] == again.params["format"] == "polarshape-result/1"


def test_sigterm_leaves_no_partial_folder(capture_config: Path, tmp_path: Path) -> None:
    """`kill` / `timeout` (SIGTERM) in the middle of a run: exit 143, no result, no .partial folder."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "res"
    cmd = [sys.executable, "-m", "polarshape.cli", "run", str(capture_config), "--out", str(out), "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".res.partial-*")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert not out.exists() and not list(tmp_path.glob(".res.*")), list(tmp_path.iterdir())


def test_interrupted_run_leaves_no_half_written_result(capture_config: Path, tmp_path: Path, monkeypatch) -> None:
    import polarshape.io.results as results

    config = _load(capture_config)
    out = tmp_path / "res"

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C in the middle of the run, after files were written

    monkeypatch.setattr(results, "write_image", interrupted)  # mask.png, in the export stage
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(config, out)
    assert not out.exists()
    assert os.listdir(tmp_path) == ["run.yaml"]  # no partial folder left behind

    monkeypatch.undo()
    first = run_pipeline(config, out)
    before = (out / "params.json").read_bytes()
    monkeypatch.setattr(results, "write_image", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(config, out, overwrite=True)
    assert (out / "params.json").read_bytes() == before  # the previous result is intact
    assert sorted(os.listdir(tmp_path)) == ["res", "run.yaml"]
    assert first.params["timings_s"]["total"] > 0


def test_mask_modes(capture_config: Path, small_capture: Path, tmp_path: Path) -> None:
    config = _load(capture_config)
    threshold = config.model_copy(update={"preprocess": config.preprocess.model_copy(update={"mask": "threshold"})})
    result = run_pipeline(threshold, tmp_path / "thr")
    capture_mask = load_capture(small_capture).mask
    mask = read_image(tmp_path / "thr" / "mask.png").astype(bool)
    # the lit sphere: close to the true outline (the threshold also keeps the mixed outline pixels)
    assert abs(int(mask.sum()) - int(capture_mask.sum())) < 0.1 * capture_mask.sum()
    assert any("threshold mask" in s for s in result.params["skipped"])
    eroded = threshold.model_copy(update={"preprocess": threshold.preprocess.model_copy(update={"erode_px": 2})})
    run_pipeline(eroded, tmp_path / "eroded")
    assert read_image(tmp_path / "eroded" / "mask.png").astype(bool).sum() < mask.sum()

    # preprocess.mask: capture on a capture without mask.png fails with the key to change
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(small_capture, bare)
    (bare / "mask.png").unlink()
    strict = parse_run_config(
        {"input": {"type": "capture", "path": str(bare)}, "preprocess": {"mask": "capture"}, "progress": False}
    )
    with pytest.raises(PipelineError, match="preprocess.mask"):
        run_pipeline(strict, tmp_path / "never")
    assert not (tmp_path / "never").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error without a GPU")
def test_cuda_without_gpu_is_a_device_error(capture_config: Path, tmp_path: Path) -> None:
    from polarshape.errors import DeviceError

    config = _load(capture_config).model_copy(update={"device": "cuda"})
    with pytest.raises(DeviceError, match="device 'cuda' requested but torch"):
        run_pipeline(config, tmp_path / "res")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_run_matches_cpu(capture_config: Path, tmp_path: Path) -> None:
    config = _load(capture_config)
    cpu = run_pipeline(config.model_copy(update={"device": "cpu"}), tmp_path / "cpu")
    gpu = run_pipeline(config.model_copy(update={"device": "cuda"}), tmp_path / "gpu")
    assert gpu.params["device"] == "cuda"
    assert gpu.params["metrics"]["normals"]["mean_deg"] == pytest.approx(cpu.params["metrics"]["normals"]["mean_deg"], abs=0.05)


# --- evaluation helpers ---------------------------------------------------------------------------


# --- shared captures (real-format data rendered by other renderers) -------------------------------

SHARED = REPO / ".." / "shared" / "data"


@pytest.mark.parametrize(
    ("name", "max_mean_deg"),
    [("official_sphere128", 6.5), pytest.param("mitsuba_sphere_a020", 6.5, marks=pytest.mark.slow)],
)
def test_lambertian_run_on_shared_captures(name: str, max_mean_deg: float, tmp_path: Path) -> None:
    capture = SHARED / name
    if not (capture / "capture.yaml").is_file():
        pytest.skip(f"shared capture {capture} not available")
    config = parse_run_config({
        "input": {"type": "capture", "path": str(capture)}, "recovery": {"model": "lambertian"},
        "progress": False, "report": {"enabled": False}, "export": {"exr": False}, "mesh": {"obj": False},
    })
    result = run_pipeline(config, tmp_path / "res")
    normals = result.params["metrics"]["normals"]
    # Lambertian PS on glossy data: measured 4.6° (official_sphere128), 4.4° (mitsuba_sphere_a020) mean
    assert normals["coverage"] > 0.95 and normals["mean_deg"] < max_mean_deg
    assert result.params["capture"]["has_polarisation"]


def test_session_input_records_a_capture_first(tmp_path: Path) -> None:
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=64, height=64, pixel_size_m=4.0e-4)
    scene["lights"] = scene["lights"][:6]
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))
    (tmp_path / "session.yaml").write_text(yaml.safe_dump({
        "camera": {"backend": "simulated", "scene": "scene.yaml", "pixel_format": "PolarizeMono12"},
        "rig": {"type": "simulated"},
    }))
    config_path = _config(tmp_path, input={"type": "session", "session": "session.yaml"}, report={"enabled": False})
    result = run_pipeline(_load(config_path), tmp_path / "res")
    capture = load_capture(tmp_path / "res" / "capture")  # the recorded capture is kept
    assert capture.num_lights == 6 and capture.frames.shape[1:] == (64, 64)
    assert result.params["capture"]["input_type"] == "session"
    # a session records no ground truth and no mask: threshold mask, evaluation skipped
    assert any("threshold mask" in s for s in result.params["skipped"])
    assert any(s.startswith("evaluation: the capture has no ground_truth") for s in result.params["skipped"])
    assert 400 < result.params["capture"]["mask_pixels"] < 1024 and "normals" not in result.params["metrics"]


@pytest.mark.slow
def test_perspective_capture(tmp_path: Path) -> None:
    """A close, off-axis sphere seen by a pinhole camera: per-pixel view directions and intrinsics."""
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"] = {**scene["camera"], "projection": "perspective", "width": 128, "height": 128,
                       "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 63.5, "cy": 63.5}}
    del scene["camera"]["pixel_size_m"]
    scene["objects"][0]["shape"].update(center=[0.002, -0.001, 0.1], radius=0.01)
    scene["lights"] = scene["lights"][:8]
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))
    config_path = _config(tmp_path, input={"type": "simulated", "scene": "scene.yaml"}, report={"enabled": False},
                          integration={"reference_depth_m": 0.1})
    params = run_pipeline(_load(config_path), tmp_path / "res").params
    assert params["capture"]["projection"] == "perspective" and params["integration"]["pixel_size_m"] is None
    # measured: mean 4.8°, depth 1.5 % of range; treating the rays as parallel would tilt the normals
    # by the ray angle (up to 7° at the image border here) on top of that
    assert params["metrics"]["normals"]["mean_deg"] < 6.5
    assert params["metrics"]["depth"]["relative"] < 0.05


def test_fmbrdf_model_goes_through_the_joint_recovery(capture_config: Path, small_capture: Path, tmp_path: Path,
                                                      monkeypatch) -> None:
    """The pipeline hands the preprocessed inputs and options to polarshape.normals.recover_normals and
    uses what it returns (a stand-in here that returns the true normals, so the test does not depend on the fit)."""
    from polarshape.normals import NormalsResult

    seen: dict = {}
    truth = load_capture(small_capture).ground_truth["normals"]

    def recover_normals(inputs, options, initial, *, seed, progress):
        seen["config"], seen["mask"], seen["device"] = options, inputs.mask.numpy(), inputs.stokes.device.type
        mask = inputs.mask
        normals = torch.from_numpy(truth).where(mask[..., None], torch.tensor(float("nan")))
        observed = torch.rand(inputs.num_lights, 3, *mask.shape)
        filled = mask & (torch.arange(mask.shape[1]) % 7 == 0)  # "no data here, filled from neighbours"
        seen["filled"] = filled.numpy()
        return NormalsResult(
            normals=normals, albedo=torch.where(mask, 0.4, float("nan")), params={"ior": torch.tensor(1.5), "alpha": 0.25},
            model="fmbrdf", mask=mask, rendered=observed * 0.9, observed=observed, initial_normals=normals,
            initial_valid=mask, history=[{"iteration": 1, "loss": torch.tensor(0.01)}],
            timings={"reflectometry": 0.5, "joint": 1.0}, skipped=["kappa: fixed at 0"], filled=filled,
        )

    monkeypatch.setattr("polarshape.pipeline.recover_normals", recover_normals)

    config = _load(capture_config)
    config = config.model_copy(update={
        "recovery": config.recovery.model_copy(update={"model": "fmbrdf", "max_outer_iterations": 7, "propagate": False}),
        "report": config.report.model_copy(update={"enabled": True}),
    })
    params = run_pipeline(config, tmp_path / "res").params
    assert seen["config"].model == "fmbrdf" and seen["config"].max_outer_iterations == 7
    assert seen["config"].propagate is False
    filled_png = read_image(tmp_path / "res" / "filled.png").astype(bool)
    assert np.array_equal(filled_png, seen["filled"]) and seen["filled"].sum() > 10
    assert params["capture"]["filled_pixels"] == int(seen["filled"].sum())
    assert seen["device"] == "cpu" and seen["mask"].sum() == params["capture"]["mask_pixels"]
    assert params["model"] == "fmbrdf" and params["params"] == {"ior": 1.5, "alpha": 0.25}
    assert params["metrics"]["normals"]["mean_deg"] < 1e-3  # the returned normals are the result
    assert params["recovery_timings_s"] == {"reflectometry": 0.5, "joint": 1.0}
    assert "recovery: kappa: fixed at 0" in params["skipped"] and params["losses"]["final"]["loss"] == pytest.approx(0.01)
    assert np.load(tmp_path / "res" / "albedo.npy")[seen["mask"]] == pytest.approx(0.4)
    assert (tmp_path / "res" / "report" / "residuals.png").is_file()


def test_a_run_of_several_materials_writes_the_material_map(tmp_path, monkeypatch):
    """The export, params.json and the report carry a run's materials (the recovery's map is set on
    the run's own result here: the several-material solve itself is tested in tests/recover/test_materials.py)."""
    import dataclasses

    import polarshape.pipeline as pipeline
    from polarshape.config import load_run_config

    recover = pipeline.recover_normals

    def two_materials(inputs, *args, **kwargs):
        result = recover(inputs, *args, **kwargs)
        labels = torch.where(result.mask, 0, -1)
        labels[:, labels.shape[1] // 2:] = torch.where(result.mask[:, labels.shape[1] // 2:], 1, -1)
        mixed = torch.zeros_like(result.mask)
        mixed[:, labels.shape[1] // 2 - 1: labels.shape[1] // 2 + 1] = True
        params = [{"ior": 1.6, "alpha": 0.08, "beta": 2.0, "kappa": 0.0, "k_s": 1.0, "k_b": 0.5},
                  {"ior": 1.45, "alpha": 0.45, "beta": 2.0, "kappa": 0.0, "k_s": 1.0, "k_b": 0.5}]
        return dataclasses.replace(result, materials=labels, material_params=params, mixed=mixed & result.mask,
                                   material_selection=[{"materials": 2, "gain_nll": 10.0, "penalty": 1.0,
                                                        "kept": True}])

    monkeypatch.setattr(pipeline, "recover_normals", two_materials)
    _small_scene(tmp_path)
    config_path = _config(tmp_path, input={"type": "simulated", "scene": "small_sphere.yaml", "seed": 3},
                          validation={"holdout": "none"}, mesh={"poisson": False})
    out = run_pipeline(load_run_config(config_path), tmp_path / "result", config_path=config_path).out_dir
    params = json.loads((out / "params.json").read_text())
    index = np.load(out / "materials.npy")
    mask = np.load(out / "normals.npy")[..., 0] == np.load(out / "normals.npy")[..., 0]  # finite = in the mask
    assert index.dtype == np.int16 and set(np.unique(index[mask])) == {0, 1} and bool((index[~mask] == -1).all())
    assert (out / "materials.png").is_file() and (out / "mixed.png").is_file()
    assert [m["alpha"] for m in params["materials"]] == [0.08, 0.45]
    assert sum(m["pixels"] for m in params["materials"]) == int(mask.sum())
    assert params["mixed_pixels"] > 0 and params["material_selection"][0]["kept"] is True
    assert "Materials" in (out / "report.html").read_text()


@pytest.mark.slow
def test_a_textured_object_marks_its_albedo_edges_in_mixed_png(tmp_path):
    """A checker-textured sphere: the blocks on a texture step are left out of the fits (filled from their
    neighbours) and written into mixed.png (polarshape.recover.edges); a plain run marks none."""
    from polarshape.config import load_run_config

    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=64, height=64, pixel_size_m=4.0e-4)
    scene["lights"] = scene["lights"][:6]
    scene["objects"][0]["texture"] = {"kind": "checker", "mapping": "spherical", "cells": 6, "low": 0.25, "high": 1.0}
    (tmp_path / "small_sphere.yaml").write_text(yaml.safe_dump(scene))
    seen = {}
    for edges in (True, False):
        config_path = _config(tmp_path, input={"type": "simulated", "scene": "small_sphere.yaml", "seed": 3},
                              recovery={"model": "fmbrdf"}, preprocess={"albedo_edges": edges},
                              validation={"holdout": "none"}, report={"enabled": False}, mesh={"obj": False})
        out = run_pipeline(load_run_config(config_path), tmp_path / f"result_{edges}", config_path=config_path).out_dir
        seen[edges] = (json.loads((out / "params.json").read_text()), read_image(out / "mixed.png") > 0,
                       read_image(out / "filled.png") > 0, read_image(out / "mask.png") > 0)
    params, mixed, filled, mask = seen[True]
    assert params["mixed_pixels"] == int(mixed.sum()) > 0
    assert bool((mixed <= mask).all()) and bool((mixed <= filled).all())  # left out, hence filled
    assert seen[False][0]["mixed_pixels"] == 0
