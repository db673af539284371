"""Concave objects: normal error with and without the light the object sends onto itself (issue 15).

The crater of configs/scenes/crater.yaml (a plate with a dish, 12 distant lights, FMBRDF k_b 0.7,
12-bit, shot and read noise) is rendered twice with the same noise seed — with one bounce of
interreflection and without — and recovered by ``polarshape run``:

- ``direct-only render``: the crater without interreflection (what the recovery's model assumes);
- ``today (bounce not modelled)``: the interreflected render, ``interreflection.mode: off``;
- ``marked``: the same, default ``auto`` without an albedo scale (the self-lit pixels marked, warning);
- ``taken out``: ``interreflection.albedo_scale`` given (the scene's electrons_per_radiance / full well:
  what a white reference target would measure), 3 rounds.

It prints mean / median / 90th-percentile normal error over the object and the mean inside the dish
(and the time). Usage: ``python benchmarks/interreflection.py [--size 128]``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from polarshape.config import parse_run_config
from polarshape.pipeline import run_pipeline
from polarshape.scene.config import load_scene_config

REPO = Path(__file__).resolve().parents[1]


def scene(size: int, bounce: bool) -> dict:
    d = yaml.safe_load((REPO / "configs" / "scenes" / "crater.yaml").read_text())
    d["camera"]["pixel_size_m"] = d["camera"]["pixel_size_m"] * d["camera"]["width"] / (2 * size)
    d["camera"]["width"] = d["camera"]["height"] = 2 * size
    if not bounce:
        d["render"]["interreflection"] = None
    return d


def run(folder: Path, name: str, scene_path: Path, **interreflection: object) -> dict:
    config = parse_run_config({
        "input": {"type": "simulated", "scene": str(scene_path), "save_capture": False},
        "recovery": {"model": "fmbrdf"}, "progress": False, "report": {"enabled": False},
        "validation": {"holdout": "none"}, "interreflection": interreflection,
    }, name)
    t0 = time.perf_counter()
    run_pipeline(config, folder / name)
    seconds = time.perf_counter() - t0
    e = np.load(folder / name / "error_map.npy")
    h, w = e.shape
    yy, xx = np.mgrid[0:h, 0:w]
    pixel = 2 * yaml.safe_load(scene_path.read_text())["camera"]["pixel_size_m"]
    dish = yaml.safe_load(scene_path.read_text())["objects"][0]["shape"]["radius"]
    inside = np.isfinite(e) & (np.hypot(xx - (w - 1) / 2, yy - (h - 1) / 2) * pixel < dish)
    return {"case": name, "mean": float(np.nanmean(e)), "median": float(np.nanmedian(e)),
            "p90": float(np.nanpercentile(e, 90)), "inside_mean": float(e[inside].mean()), "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128, help="super-pixels across (default 128)")
    ap.add_argument("--out", type=Path, default=None, help="write the rows as JSON")
    args = ap.parse_args()
    crater = load_scene_config(REPO / "configs" / "scenes" / "crater.yaml")
    scale = crater.sensor.to_model().full_scale_per_radiance(crater.camera.exposure_us, crater.camera.gain_db, 12)
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for bounce in (False, True):
            (tmp / f"scene_{bounce}.yaml").write_text(yaml.safe_dump(scene(args.size, bounce)))
        rows.append(run(tmp, "direct-only render", tmp / "scene_False.yaml", mode="off"))
        rows.append(run(tmp, "today (bounce not modelled)", tmp / "scene_True.yaml", mode="off"))
        rows.append(run(tmp, "marked (auto, no albedo scale)", tmp / "scene_True.yaml"))
        rows.append(run(tmp, "taken out (albedo_scale given)", tmp / "scene_True.yaml", albedo_scale=scale))
    print(f"crater {args.size}x{args.size} super-pixels, 12 lights, one bounce of interreflection in the render")
    print("| case | mean | median | p90 | mean inside the dish | time (s) |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['case']} | {r['mean']:.2f}° | {r['median']:.2f}° | {r['p90']:.2f}° | {r['inside_mean']:.2f}° | {r['seconds']:.1f} |")
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
