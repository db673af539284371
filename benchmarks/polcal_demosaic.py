"""Benchmark: the calibrated Stokes estimate, block (superpixel) against per-pixel (bilinear).

    .venv/bin/python benchmarks/polcal_demosaic.py [--work DIR] [--no-runs]

Renders configs/scenes/real_sensor.yaml (a blob seen by an imperfect IMX250MZR: analyser angles σ 1.5°,
150:1, PRNU 1 %, black 64, 0.02 % hot pixels) and the same scene with that sensor made ideal (same noise
seed), renders the real sensor's bench frames (``polarshape simulate calibration``), calibrates them
(``polarshape calibrate polarisation``), and compares, for demosaic bilinear and superpixel, with and
without the calibration:

* the Stokes images against the ideal sensor's (same estimator): DoLP bias (mean over object
  observations with DoLP_ideal > 0.01, real − ideal) and the median |AoLP difference| there;
* unless ``--no-runs``: the mean normal error of ``polarshape run`` (FMBRDF) vs the ground truth.

Prints one table row per variant.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
import yaml

from polarshape.imaging.stokes import aolp, dolp
from polarshape.io.capture import load_capture
from polarshape.recover.preprocess import preprocess_capture

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "scenes" / "real_sensor.yaml"
CLI = [sys.executable, "-m", "polarshape.cli"]


def _sh(*args: str) -> None:
    subprocess.run([*CLI, *args], check=True, stdout=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})


def _ideal_scene(work: Path) -> Path:
    data = yaml.safe_load(SCENE.read_text())
    data["sensor"].update(analyser_angle_error_deg=0.0, extinction_ratio=None, prnu=0.0, hot_pixel_fraction=0.0,
                          dead_pixel_fraction=0.0)
    out = work / "ideal_scene.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def _prepare(work: Path) -> None:
    _sh("simulate", str(SCENE), "--out", str(work / "real"), "--overwrite", "-q")
    _sh("simulate", str(_ideal_scene(work)), "--out", str(work / "ideal"), "--overwrite", "-q")
    _sh("simulate", "calibration", str(SCENE), "--out", str(work / "bench"), "--overwrite", "-q")
    b = work / "bench"
    _sh("calibrate", "polarisation", "--polariser", *sorted(str(p) for p in (b / "polariser").glob("*.png")),
        "--angles-file", str(b / "polariser" / "angles.txt"), "--flat", *sorted(str(p) for p in (b / "flat").glob("*.png")),
        "--dark", *sorted(str(p) for p in (b / "dark").glob("*.png")), "--bit-depth", "12",
        "--out", str(work / "polcal.npz"), "--overwrite", "-q")
    shutil.rmtree(work / "real_cal", ignore_errors=True)
    shutil.copytree(work / "real", work / "real_cal")
    shutil.copy(work / "polcal.npz", work / "real_cal" / "polcal.npz")
    spec = yaml.safe_load((work / "real_cal" / "capture.yaml").read_text())
    spec["camera"]["polarimetric_calibration"] = "polcal.npz"
    (work / "real_cal" / "capture.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))


def _stokes_metrics(work: Path, capture: str, demosaic: str) -> tuple[float, float]:
    kw = {"dtype": torch.float64, "demosaic": demosaic, "polarisation_check": False}
    ideal = preprocess_capture(load_capture(work / "ideal"), **kw)
    got = preprocess_capture(load_capture(work / capture), **kw)
    d_ideal, d_got = dolp(ideal.stokes), dolp(got.stokes)
    use = ideal.valid & got.valid & (d_ideal > 0.01)
    bias = float((d_got - d_ideal)[use].mean())
    diff = torch.remainder(aolp(got.stokes) - aolp(ideal.stokes) + math.pi / 2, math.pi) - math.pi / 2
    return bias, math.degrees(float(diff[use].abs().median()))


def _normal_error(work: Path, capture: str, demosaic: str) -> float:
    config = {"format": "polarshape-run/1", "input": {"type": "capture", "path": str(work / capture)}, "device": "cpu",
              "progress": False, "preprocess": {"demosaic": demosaic}, "recovery": {"model": "fmbrdf"},
              "integration": {"method": "bilateral"}, "mesh": {"poisson": False}}
    path = work / f"run_{capture}_{demosaic}.yaml"
    path.write_text(yaml.safe_dump(config))
    out = work / f"out_{capture}_{demosaic}"
    _sh("run", str(path), "--out", str(out), "--overwrite", "-q")
    return float(json.loads((out / "params.json").read_text())["metrics"]["normals"]["mean_deg"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", help="working folder (default: a temporary one)")
    parser.add_argument("--no-runs", action="store_true", help="Stokes figures only (no `polarshape run`)")
    args = parser.parse_args(argv)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="polcal_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    _prepare(work)
    print(f"{'capture':<22}{'demosaic':<12}{'DoLP bias':>11}{'|ΔAoLP| med °':>15}{'normal err °':>14}")
    for capture, label in (("ideal", "ideal sensor"), ("real", "real, uncalibrated"), ("real_cal", "real, calibrated")):
        for demosaic in ("bilinear", "superpixel"):
            bias, daolp = _stokes_metrics(work, capture, demosaic)
            normal = float("nan") if args.no_runs else _normal_error(work, capture, demosaic)
            print(f"{label:<22}{demosaic:<12}{bias:>11.5f}{daolp:>15.3f}{normal:>14.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
