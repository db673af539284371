"""Benchmark: a colour polarisation capture (IMX250MYR-style, Bayer RGGB over the polariser blocks)
against a mono capture (IMX250MZR) of the same scene.

    .venv/bin/python benchmarks/colour.py [--sizes 32 64] [--work DIR]

Renders configs/scenes/colour.yaml (an orange FMBRDF sphere, k_b = [0.8, 0.45, 0.15], k_s = 1, 8
lights) at each size (super-pixels across; the sphere fills the same part of the frame) with its
colour sensor and with ``camera.mosaic.bayer: null`` (mono, same noise seed), runs ``polarshape run``
with configs/colour.yaml's settings (report off) on both, and prints one row per run:

* the mean and median normal error against the ground truth;
* k_b / k_s per channel (scale-free: the albedos' scale follows the irradiance units, k_s is shared)
  against the truth, and the largest per-channel error in %; a mono capture has one k_b, compared with
  the mean of the three (what a grey sensor sees under white light);
* the seconds of the run, of its recovery and preprocess stages and of the per-channel albedo
  (``recovery_timings_s.colour``), and colour / mono ratios, measured in the same process one after
  the other.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import yaml

from polarshape.config import load_run_config
from polarshape.pipeline import run_pipeline

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "configs" / "scenes" / "colour.yaml"
CONFIG = ROOT / "configs" / "colour.yaml"


def _run(work: Path, n: int, bayer: str | None) -> dict:
    scene = yaml.safe_load(SCENE.read_text())
    scene["camera"].update(width=2 * n, height=2 * n, pixel_size_m=1e-4 * 64 / n)
    scene["camera"]["mosaic"]["bayer"] = bayer
    name = f"{bayer or 'mono'}_{n}"
    (work / f"{name}.yaml").write_text(yaml.safe_dump(scene))
    config = yaml.safe_load(CONFIG.read_text())
    config["input"]["scene"] = f"{name}.yaml"
    config.update(progress=False, report={"enabled": False})
    path = work / f"run_{name}.yaml"
    path.write_text(yaml.safe_dump(config))
    result = run_pipeline(load_run_config(path), work / name, overwrite=True)
    params = json.loads((result.out_dir / "params.json").read_text())
    truth = np.array(scene["objects"][0]["material"]["k_b"], dtype=float) / scene["objects"][0]["material"]["k_s"]
    k_s = params["params"]["k_s"]
    if bayer is None:
        got = np.array([params["params"]["k_b"]]) / k_s
        truth = np.array([truth.mean()])
    else:
        got = np.array(params["colour"]["median"]) / k_s
    err = 100.0 * (got - truth) / truth
    normals = params["metrics"]["normals"]
    return {"size": n, "sensor": bayer or "mono", "mean_deg": normals["mean_deg"], "median_deg": normals["median_deg"],
            "k_b_over_k_s": got.tolist(), "truth": truth.tolist(), "max_err_pct": float(np.abs(err).max()),
            "seconds": params["timings_s"]["total"], "recovery_s": params["timings_s"]["recovery"],
            "preprocess_s": params["timings_s"]["preprocess"], "colour_s": params["recovery_timings_s"].get("colour", 0.0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64], help="super-pixels across (default: 64, the shipped scene)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the scenes and results (default: a temporary one)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        print(f"{'size':>4} {'sensor':>6} {'mean°':>6} {'median°':>7} {'k_b/k_s (R, G, B | grey)':>26} "
              f"{'max err %':>9} {'run s':>6} {'rec s':>6} {'pre s':>6} {'colour s':>8}")
        for n in args.sizes:
            rows = [_run(work, n, "RGGB"), _run(work, n, None)]
            for r in rows:
                kb = ", ".join(f"{v:.3f}" for v in r["k_b_over_k_s"])
                print(f"{r['size']:>4} {r['sensor']:>6} {r['mean_deg']:6.3f} {r['median_deg']:7.3f} {kb:>26} "
                      f"{r['max_err_pct']:9.2f} {r['seconds']:6.1f} {r['recovery_s']:6.1f} {r['preprocess_s']:6.2f} "
                      f"{r['colour_s']:8.3f}")
            c, m = rows
            print(f"{n:>4} colour/mono: normal error ×{c['mean_deg'] / m['mean_deg']:.2f}, run time ×{c['seconds'] / m['seconds']:.2f}, "
                  f"recovery time ×{c['recovery_s'] / m['recovery_s']:.2f}, preprocess time ×{c['preprocess_s'] / m['preprocess_s']:.2f}")


if __name__ == "__main__":
    main()
