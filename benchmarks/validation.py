"""Benchmark: the held-out-light validation's cost as a fraction of ``polarshape run``, warm vs cold start.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/validation.py [--sizes 64,128] [--lights 12] [--cold]

Renders configs/scenes/sphere.yaml's FMBRDF sphere at each size (super-pixels across) under K lights
(zenith 15°–55° on a golden-angle spiral, plus a frontal one), runs the pipeline with
``validation.holdout: none`` and with the default ``auto`` (report on, as ``make run``) and prints:
the validation stage's seconds, its share of the run, and the run's extra time over the run
without it (goal ≤ 25 % at K = 12). With ``--cold``, also the held-out s0 relative RMSE and time of the
FMBRDF folds warm-started from the run and fitted from scratch.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.config import RunConfig
from polarshape.io.capture import load_capture
from polarshape.normals import recover_normals
from polarshape.pipeline import run_pipeline
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions, ValidationOptions
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.validation import validate_holdout

SCENE = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "sphere.yaml"


def render(folder: Path, size: int, lights: int) -> Path:
    """The sphere at ``size`` × ``size`` super-pixels (it spans ~94 % of the width) under ``lights`` lights."""
    scene = yaml.safe_load(SCENE.read_text())
    width = 2 * size
    scene["camera"].update(width=width, height=width, pixel_size_m=0.0256 / width)
    spiral = [{"zenith_deg": 15 + 40 * i / max(lights - 2, 1), "azimuth_deg": (137.5 * i) % 360, "intensity": 1.0}
              for i in range(lights - 1)]
    scene["lights"] = [*spiral, {"direction": [0.0, 0.0, -1.0], "intensity": 0.8}]
    (folder / "scene.yaml").write_text(yaml.safe_dump(scene))
    with SimulatedCamera(folder / "scene.yaml", seed=1) as camera:
        camera.render_capture(folder / "capture", progress=False)
    return folder / "capture"


def pipeline_times(capture: Path, out: Path, holdout: str) -> dict[str, float]:
    config = RunConfig.model_validate({"input": {"type": "capture", "path": str(capture)}, "progress": False,
                                       "validation": {"holdout": holdout}})
    return run_pipeline(config, out, overwrite=True).params["timings_s"]


def warm_cold(capture: Path) -> list[tuple[str, float, float]]:
    """(start, seconds of the FMBRDF folds, mean held-out s0 relative RMSE) warm and cold."""
    inputs = preprocess_capture(load_capture(capture))
    options, initial = RecoveryOptions(), InitialNormalsOptions()
    result = recover_normals(inputs, options, initial)
    rows = []
    for warm in (True, False):
        t0 = time.perf_counter()
        v = validate_holdout(inputs, result, options, initial, ValidationOptions(models=["fmbrdf"]), warm_start=warm)
        rows.append(("warm" if warm else "cold", time.perf_counter() - t0, v.models["fmbrdf"].mean("s0_rel_rmse")))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="64,128", help="super-pixels across, comma-separated")
    parser.add_argument("--lights", type=int, default=12)
    parser.add_argument("--cold", action="store_true", help="also time FMBRDF folds fitted from scratch")
    args = parser.parse_args()
    print(f"K = {args.lights} lights; times in seconds")
    print(f"{'size':>5} {'run (none)':>10} {'run (auto)':>10} {'validation':>10} {'share':>6} {'extra':>6}")
    cold_rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in (int(s) for s in args.sizes.split(",")):
            folder = Path(tmp) / str(size)
            folder.mkdir()
            capture = render(folder, size, args.lights)
            none = pipeline_times(capture, folder / "none", "none")
            auto = pipeline_times(capture, folder / "auto", "auto")
            share = auto["validation"] / auto["total"]
            extra = auto["total"] / none["total"] - 1
            print(f"{size:>4}² {none['total']:>10.2f} {auto['total']:>10.2f} {auto['validation']:>10.2f} "
                  f"{share:>6.1%} {extra:>+6.1%}")
            if args.cold:
                cold_rows += [(size, *row) for row in warm_cold(capture)]
    if cold_rows:
        print(f"\n{'size':>5} {'start':>6} {'fmbrdf folds s':>14} {'held-out s0 rel. RMSE':>22}")
        for size, start, seconds, error in cold_rows:
            print(f"{size:>4}² {start:>6} {seconds:>14.2f} {error:>22.5f}")


if __name__ == "__main__":
    main()
