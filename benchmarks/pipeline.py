"""Time per stage of ``polarshape run``: the default configuration and larger simulated captures.

Cases:
- ``default``: configs/default.yaml as it is (the sphere scene, 128×128 super-pixels, 9 lights);
- ``N`` (e.g. 1024): the same sphere, lights and settings rendered at N×N super-pixels (a 2N×2N raw
  mosaic, pixel size scaled so the sphere fills the same share of the view).

Each case runs the whole pipeline into a temporary folder and prints one markdown row: seconds per
stage (input = rendering the capture, for these simulated cases), the total, the number of object
pixels and the normal error against the simulator's ground truth.

Usage:
    python benchmarks/pipeline.py [--cases default 1024] [--model lambertian|fmbrdf|auto]
                                  [--device auto|cpu|cuda] [--no-report] [--no-poisson]

BLAS threads oversubscribe a busy 2-core machine: set OMP_NUM_THREADS there.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
from pathlib import Path

import torch
import yaml

from polarshape.config import load_run_config, parse_run_config
from polarshape.pipeline import STAGES, run_pipeline

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "configs" / "default.yaml"


def case_config(case: str, folder: Path, model: str | None, device: str, report: bool, poisson: bool):
    """The run configuration of one case (a scaled copy of the default scene for an N×N case)."""
    base = load_run_config(DEFAULT).model_dump(mode="json")
    if case != "default":
        size = int(case)
        scene = yaml.safe_load(Path(base["input"]["scene"]).read_text())
        camera = scene["camera"]
        scale = camera["width"] / (2 * size)
        camera.update(width=2 * size, height=2 * size, pixel_size_m=camera["pixel_size_m"] * scale)
        scene_path = folder / f"scene_{size}.yaml"
        scene_path.write_text(yaml.safe_dump(scene))
        base["input"]["scene"] = str(scene_path)
    base["input"]["save_capture"] = False
    base["progress"] = False
    base["device"] = device
    base["report"]["enabled"] = report
    base["mesh"]["poisson"] = poisson
    if model is not None:
        base["recovery"]["model"] = model
    base.pop("output", None)
    return parse_run_config(base, f"benchmark {case}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=["default", "1024"], help="'default' and/or sizes N (N×N super-pixels)")
    parser.add_argument("--model", choices=["lambertian", "fmbrdf", "auto"], default=None,
                        help="recovery.model (default: the one in configs/default.yaml)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--no-report", action="store_true", help="skip the report stage")
    parser.add_argument("--no-poisson", action="store_true", help="skip the Poisson mesh")
    args = parser.parse_args()

    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"cuda: {torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'none'}, "
          f"threads: {torch.get_num_threads()}")
    print()
    print("| case | model | device | pixels | " + " | ".join(STAGES) + " | total (s) | mean err (deg) |")
    print("|" + "---|" * (len(STAGES) + 6))
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            folder = Path(tmp) / case
            folder.mkdir()
            config = case_config(case, folder, args.model, args.device, not args.no_report, not args.no_poisson)
            result = run_pipeline(config, folder / "result")
            p = result.params
            times = " | ".join(f"{p['timings_s'].get(s, float('nan')):.2f}" for s in STAGES)
            err = p["metrics"].get("normals", {}).get("mean_deg", float("nan"))
            size = "x".join(str(v) for v in p["capture"]["superpixels_hw"])
            print(f"| {case} ({size}) | {p['model']} | {p['device']} | {p['capture']['mask_pixels']} | {times} | "
                  f"{p['timings_s']['total']:.2f} | {err:.2f} |", flush=True)


if __name__ == "__main__":
    main()
