"""Benchmark: ``polarshape batch`` against sequential ``polarshape run`` processes, and the engine's overhead.

    .venv/bin/python benchmarks/batch.py [--captures 16] [--width 32] [--lights 6] [--engines local,ray]

Renders one small sphere capture (configs/scenes/sphere.yaml at --width raw pixels, its first
--lights lights) and copies it --captures times; then, with one fast configuration (FMBRDF, 2 outer
iterations, no report, no validation), times

* ``sequential``: one ``polarshape run`` subprocess per capture, one after the other (torch's default
  threads: all cores, unless OMP_NUM_THREADS says otherwise); ``sequential-1t``: the same with
  OMP_NUM_THREADS=1;
* ``local``: ``polarshape batch`` (a subprocess, like a user runs it), default pool (cores workers × 1 thread);
* ``local-1``: the same with ``--workers 1`` (the engine's overhead without parallelism);
* ``ray``: ``run_batch(engine="ray")`` on a local ``ray.init(num_cpus=cores)`` (when Ray is installed;
  Ray's start-up is timed separately and not included).

and prints a table: wall time, its ratio to the first sequential one, Σ of the in-process pipeline times
(params.json ``timings_s.total``) and the per-capture overhead (wall × workers − Σ pipeline) / captures.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.batch import available_cores, find_captures, run_batch
from polarshape.config import load_batch_config

SCENE = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "sphere.yaml"
CONFIG = {
    "progress": False, "recovery": {"model": "fmbrdf", "max_outer_iterations": 2}, "validation": {"holdout": "none"},
    "mesh": {"poisson": False, "obj": False}, "report": {"enabled": False}, "export": {"exr": False},
}


def _captures(folder: Path, n: int, width: int, lights: int) -> Path:
    scene = yaml.safe_load(SCENE.read_text())
    scene["camera"].update(width=width, height=width, pixel_size_m=0.0128 / width)
    scene["lights"] = scene["lights"][:lights]
    (folder / "scene.yaml").write_text(yaml.safe_dump(scene))
    with SimulatedCamera(folder / "scene.yaml", seed=1) as camera:
        camera.render_capture(folder / "capture", progress=False)
    caps = folder / "caps"
    for i in range(n):
        shutil.copytree(folder / "capture", caps / f"c{i:02d}")
    return caps


def _pipeline_seconds(out: Path) -> float:
    return sum(json.loads(p.read_text())["timings_s"]["total"] for p in out.glob("*/params.json"))


def _sequential(caps: Path, config: Path, out: Path, threads: int | None = None) -> float:
    env = dict(os.environ) if threads is None else {**os.environ, "OMP_NUM_THREADS": str(threads)}
    t0 = time.perf_counter()
    for cap in sorted(caps.iterdir()):
        run_config = out.parent / f"run_{cap.name}.yaml"
        run_config.write_text(yaml.safe_dump({**CONFIG, "input": {"type": "capture", "path": str(cap)}}))
        subprocess.run([sys.executable, "-m", "polarshape.cli", "run", str(run_config), "--out", str(out / cap.name),
                        "-q"], check=True, stdout=subprocess.DEVNULL, env=env)
    return time.perf_counter() - t0


def _batch_cli(caps: Path, config: Path, out: Path, *extra: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "polarshape.cli", "batch", str(config), str(caps / "*"), "--out", str(out),
                    "-q", *extra], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", type=int, default=16)
    parser.add_argument("--width", type=int, default=32, help="raw image width in pixels")
    parser.add_argument("--lights", type=int, default=6)
    parser.add_argument("--engines", default="sequential,sequential-1t,local,local-1,ray")
    args = parser.parse_args()
    cores = available_cores()
    print(f"{args.captures} captures of {args.width}x{args.width} raw px, {args.lights} lights; {cores} cores; "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        caps = _captures(folder, args.captures, args.width, args.lights)
        config = folder / "batch.yaml"
        config.write_text(yaml.safe_dump(CONFIG))
        rows: list[tuple[str, float, int, float]] = []  # (engine, wall, workers, Σ pipeline)
        for engine in args.engines.split(","):
            out = folder / f"out_{engine}"
            if engine in ("sequential", "sequential-1t"):
                out.mkdir()
                wall, workers = _sequential(caps, config, out, 1 if engine == "sequential-1t" else None), 1
            elif engine == "local":
                wall, workers = _batch_cli(caps, config, out), min(cores, args.captures)
            elif engine == "local-1":
                wall, workers = _batch_cli(caps, config, out, "--workers", "1"), 1
            elif engine == "ray":
                try:
                    import ray
                except ImportError:
                    print("ray: not installed (pip install -e '.[cluster]'), skipped")
                    continue
                t0 = time.perf_counter()
                ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False)
                print(f"ray.init: {time.perf_counter() - t0:.1f} s (not counted)")
                t0 = time.perf_counter()
                run_batch(load_batch_config(config), find_captures([str(caps / "*")]), out, engine="ray",
                          config_path=config, progress=False)
                wall, workers = time.perf_counter() - t0, min(cores, args.captures)
                ray.shutdown()
            else:
                raise SystemExit(f"unknown engine {engine!r}")
            rows.append((engine, wall, workers, _pipeline_seconds(out)))
        base = next((wall for engine, wall, _, _ in rows if engine.startswith("sequential")), None)
        print(f"{'engine':13s} {'workers':>7s} {'wall s':>8s} {'vs seq':>7s} {'Σ pipeline s':>12s} {'overhead s/capture':>18s}")
        for engine, wall, workers, pipeline in rows:
            ratio = f"{wall / base:.2f}" if base else "-"
            overhead = (wall * workers - pipeline) / args.captures
            print(f"{engine:13s} {workers:7d} {wall:8.1f} {ratio:>7s} {pipeline:12.1f} {overhead:18.2f}")


if __name__ == "__main__":
    main()
