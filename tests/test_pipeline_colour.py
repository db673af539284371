"""``polarshape run`` of a colour polarisation capture (configs/colour.yaml): RGB albedo files, coloured
meshes, params.json's colour, the report; a mono capture's result files as before."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml

from polarshape.cli import main
from polarshape.config import load_run_config
from polarshape.pipeline import run_pipeline

REPO = Path(__file__).resolve().parents[1]


def _colour_scene(folder: Path, *, bayer: str | None = "RGGB", n: int = 32) -> Path:
    """configs/scenes/colour.yaml at n × n super-pixels (``bayer`` None: the same scene on a mono sensor)."""
    scene = yaml.safe_load((REPO / "configs" / "scenes" / "colour.yaml").read_text())
    scene["camera"].update(width=2 * n, height=2 * n, pixel_size_m=1e-4 * 64 / n)
    scene["camera"]["mosaic"]["bayer"] = bayer
    if bayer is None:  # the same scene on a mono sensor: a PolarizeMono format
        scene["camera"]["pixel_format"] = "PolarizeMono12"
    path = folder / f"scene_{bayer or 'mono'}.yaml"
    path.write_text(yaml.safe_dump(scene))
    return path


def _run(folder: Path, scene: Path, **sections: object) -> tuple[Path, dict]:
    config = {"progress": False, "input": {"type": "simulated", "scene": scene.name}, "validation": {"holdout": "none"},
              "mesh": {"obj": True}, **sections}
    path = folder / f"run_{scene.stem}.yaml"
    path.write_text(yaml.safe_dump(config))
    result = run_pipeline(load_run_config(path), folder / f"result_{scene.stem}", config_path=path)
    return result.out_dir, json.loads((result.out_dir / "params.json").read_text())


@pytest.fixture(scope="module")
def colour_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("colour")
    return _run(folder, _colour_scene(folder), recovery={"model": "lambertian"})


def test_colour_result_files(colour_run: tuple[Path, dict]) -> None:
    out, params = colour_run
    mask = cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED) > 0
    h, w = mask.shape
    albedo = np.load(out / "albedo.npy")
    assert albedo.shape == (h, w, 3) and albedo.dtype == np.float32
    assert np.isfinite(albedo[mask]).all() and np.isnan(albedo[~mask]).all()
    png = cv2.imread(str(out / "albedo.png"), cv2.IMREAD_UNCHANGED)  # OpenCV: B, G, R
    assert png.shape == (h, w, 3) and png.dtype == np.uint16
    rgb = png[..., ::-1].astype(np.float64)
    # one linear scale for the three channels: the PNG's channel ratios are the albedo's
    ratio_png = np.median(rgb[mask][:, 0] / rgb[mask][:, 2])
    ratio_npy = np.median(albedo[mask][:, 0] / albedo[mask][:, 2])
    assert ratio_png == pytest.approx(ratio_npy, rel=0.02) and ratio_npy == pytest.approx(0.8 / 0.15, rel=0.1)
    # coloured vertices: orange (R > G > B) from the RGB albedo, in mesh.ply and mesh.obj
    for name in ("mesh.ply", "mesh.obj"):
        colours = np.asarray(trimesh.load(out / name, process=False).visual.vertex_colors)[:, :3].astype(int)
        med = np.median(colours, axis=0)
        assert med[0] > med[1] > med[2], (name, med)
    # params.json: the sensor's pattern, per-channel statistics, errors against the truth
    assert params["capture"]["bayer"] == "RGGB"
    colour = params["colour"]
    assert colour["channels"] == ["R", "G", "B"] and len(colour["median"]) == 3 and sum(colour["chromaticity"]) == pytest.approx(3)
    metrics = params["metrics"]["albedo_rgb"]
    assert metrics["max_abs_chromaticity_error_pct"] < 5.0, metrics
    assert "colour" in params["recovery_timings_s"]
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "Body albedo per colour channel" in page and (out / "report" / "maps.png").is_file()


def test_mono_capture_keeps_its_grey_albedo(tmp_path: Path) -> None:
    out, params = _run(tmp_path, _colour_scene(tmp_path, bayer=None, n=24), recovery={"model": "lambertian"},
                       report={"enabled": False}, mesh={"obj": False})
    albedo = np.load(out / "albedo.npy")
    assert albedo.ndim == 2
    assert cv2.imread(str(out / "albedo.png"), cv2.IMREAD_UNCHANGED).ndim == 2
    assert "colour" not in params and "bayer" not in params["capture"] and "albedo_rgb" not in params["metrics"]


@pytest.mark.slow
def test_shipped_colour_config_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``polarshape run configs/colour.yaml``: the FMBRDF fit of the shipped colour sphere."""
    out = tmp_path / "colour"
    assert main(["run", str(REPO / "configs" / "colour.yaml"), "--out", str(out), "-q"]) == 0
    params = json.loads((out / "params.json").read_text())
    assert params["model"] == "fmbrdf" and params["capture"]["bayer"] == "RGGB"
    assert params["metrics"]["normals"]["mean_deg"] < 0.4, params["metrics"]["normals"]  # measured 0.20°
    assert params["metrics"]["albedo_rgb"]["max_abs_chromaticity_error_pct"] < 3.0  # measured 0.3 %
    assert np.load(out / "albedo.npy").shape == (64, 64, 3)
    assert "result in" in capsys.readouterr().out
