"""``polarshape simulate``: end to end on the shipped sphere scene."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from polarshape.cli import main
from polarshape.io.capture import load_capture

REPO = Path(__file__).resolve().parents[1]
SPHERE = REPO / "configs" / "scenes" / "sphere.yaml"


@pytest.mark.slow
def test_simulate_sphere_end_to_end_and_refuse_existing_output(tmp_path, capsys):
    out = tmp_path / "sphere"
    assert main(["simulate", str(SPHERE), "--out", str(out), "--quiet"]) == 0
    capture = load_capture(out)
    n_lights = len(yaml.safe_load(SPHERE.read_text())["lights"])
    assert capture.frames.shape == (n_lights, 256, 256) and capture.bit_depth == 12
    for name in ("normals.npy", "depth.npy", "scene.json"):
        assert (out / "ground_truth" / name).is_file()
    assert (out / "mask.png").is_file() and capture.mask.sum() > 10000
    normals = capture.ground_truth["normals"]
    assert np.allclose(np.linalg.norm(normals[capture.mask], axis=-1), 1.0, atol=1e-6)
    assert normals[128 // 2, 128 // 2, 2] < -0.99  # the sphere's centre faces the camera
    assert capture.frames.max() < 4095 and capture.frames.max() > 1500  # exposed, not saturated
    frames = capture.frames.copy()

    # an existing folder is refused and left untouched
    assert main(["simulate", str(SPHERE), "--out", str(out), "--quiet"]) == 1
    assert "already exists" in capsys.readouterr().err
    assert np.array_equal(load_capture(out).frames, frames)


SMALL = """
camera: {projection: orthographic, width: 32, height: 32, pixel_size_m: 5.0e-4, pixel_format: PolarizeMono8}
objects: [{shape: {type: sphere, center: [0, 0, 0.3], radius: 0.006}, material: {model: lambertian, k_d: 0.7}}]
lights: [{zenith_deg: 20, azimuth_deg: 45}]
"""


def test_simulate_overwrite_replaces_and_seed_changes_noise(tmp_path):
    scene = tmp_path / "small.yaml"
    scene.write_text(SMALL)
    out = tmp_path / "cap"
    assert main(["simulate", str(scene), "--out", str(out), "--quiet"]) == 0
    first = load_capture(out)
    assert first.bit_depth == 8 and first.frames.shape == (1, 32, 32)
    assert main(["simulate", str(scene), "--out", str(out), "--quiet"]) == 1
    assert main(["simulate", str(scene), "--out", str(out), "--overwrite", "--seed", "5", "--quiet"]) == 0
    assert not np.array_equal(load_capture(out).frames, first.frames)
    assert main(["simulate", str(scene), "--out", str(out), "--overwrite", "--quiet"]) == 0
    assert np.array_equal(load_capture(out).frames, first.frames)  # default seed again: bit-exact


def test_simulate_reports_a_bad_scene_file(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: {projection: orthographic}\nobjects: []\nlights: []\n")
    assert main(["simulate", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "camera" in err and "pixel_size_m" in err
    assert not (tmp_path / "x").exists()


def test_module_entry_point_shows_help():
    cmd = [sys.executable, "-m", "polarshape.cli", "simulate", "--help"]
    result = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert result.returncode == 0 and "--overwrite" in result.stdout


def test_simulate_exposure_brackets_writes_format_2(tmp_path, capsys):
    scene = yaml.safe_load(SPHERE.read_text())
    scene["camera"].update(width=32, height=32, pixel_size_m=8e-4, exposure_us=20000, exposures_us=[20000, 2500])
    scene["lights"] = scene["lights"][:3]
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene))
    assert main(["simulate", str(path), "--out", str(tmp_path / "cap"), "--quiet"]) == 0
    assert "(3 frames × 2 exposures)" in capsys.readouterr().out
    capture = load_capture(tmp_path / "cap")
    assert capture.spec.format == "polarshape-capture/2" and capture.brackets.shape == (3, 1, 32, 32)
    assert [light.exposure_us for light in capture.spec.lights] == [20000.0] * 3
    scene["camera"]["exposure_us"] = 10000  # disagrees with the reference exposure exposures_us[0]
    path.write_text(yaml.safe_dump(scene))
    assert main(["simulate", str(path), "--out", str(tmp_path / "cap2"), "--quiet"]) == 2
    assert "differs from the first of camera.exposures_us" in capsys.readouterr().err
