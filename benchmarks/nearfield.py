"""Benchmark: near-field recovery against today's plane-placed point lights, on the same captures.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/nearfield.py [--size 64] [--scenes nearfield_sphere,...]
        [--methods plane-placed,near-field] [--fit-kappa auto|true|false]

Renders each scene of configs/scenes/ (default: nearfield_sphere, nearfield_blob — a perspective camera, 12
LEDs on a ring 3.5 object radii away — and textured, orthographic under 4 point lights) at ``size``
super-pixels across (12-bit, shot and read noise), then runs ``polarshape run`` twice on the capture:

- **baseline** — ``nearfield.enabled: false``: the lights placed from the plane at
  ``integration.reference_depth_m`` = the object centre's true distance (a tape-measured guess, the best
  case for it);
- **near-field** — ``nearfield.enabled: auto`` from ``integration.reference_depth_m`` 1 m (no depth given:
  the distance comes from the shading).

Prints a Markdown table: mean / median normal error (degrees), the depth RMSE as a percentage of the camera
distance (absolute: no alignment) and of the depth range (scale/offset aligned), the estimated median depth
against the truth, the near-field rounds, and the run's seconds (validation and report off in both).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.config import RunConfig
from polarshape.pipeline import run_pipeline

SCENES = Path(__file__).resolve().parents[1] / "configs" / "scenes"


def render(folder: Path, name: str, size: int) -> tuple[Path, float]:
    """The scene at ``size`` × ``size`` super-pixels (same field of view); returns (capture, object centre z)."""
    scene = yaml.safe_load((SCENES / f"{name}.yaml").read_text())
    camera = scene["camera"]
    factor = 2 * size / camera["width"]
    if camera["projection"] == "perspective":
        k = camera["intrinsics"]
        camera["intrinsics"] = {"fx": k["fx"] * factor, "fy": k["fy"] * factor, "cx": size - 0.5, "cy": size - 0.5}
    else:
        camera["pixel_size_m"] = camera["pixel_size_m"] / factor
    camera.update(width=2 * size, height=2 * size)
    (folder / f"{name}.yaml").write_text(yaml.safe_dump(scene))
    with SimulatedCamera(folder / f"{name}.yaml") as cam:
        cam.render_capture(folder / name, progress=False)
    return folder / name, float(scene["objects"][0]["shape"]["center"][2])


def run(capture: Path, out: Path, *, nearfield: bool, reference: float, fit_kappa: bool | None = None
        ) -> tuple[dict, float]:
    config = RunConfig.model_validate({
        "input": {"type": "capture", "path": str(capture)}, "progress": False, "recovery": {"fit_kappa": fit_kappa},
        "nearfield": {"enabled": "auto" if nearfield else False},
        "integration": {"reference_depth_m": reference},
        "validation": {"holdout": "none"}, "report": {"enabled": False}, "mesh": {"obj": False},
        "export": {"exr": False},
    })
    t0 = time.perf_counter()
    params = run_pipeline(config, out, overwrite=True).params
    return params, time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=64, help="super-pixels across (default 64)")
    parser.add_argument("--scenes", default="nearfield_sphere,nearfield_blob,textured")
    parser.add_argument("--methods", default="plane-placed,near-field", help="which runs (default both)")
    parser.add_argument("--fit-kappa", choices=("auto", "true", "false"), default="auto",
                        help="recovery.fit_kappa: auto (the recovery's κ test, the default), or κ forced on / off")
    args = parser.parse_args()
    methods = args.methods.split(",")
    if unknown := set(methods) - {"plane-placed", "near-field"}:
        parser.error(f"--methods: unknown {sorted(unknown)}; use plane-placed and/or near-field")
    print("| scene | method | reference depth | mean ° | median ° | depth RMSE % of distance | depth RMSE % of range "
          "(aligned) | median depth m (truth) | rounds | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in args.scenes.split(","):
            capture, centre = render(folder, name, args.size)
            truth = np.load(capture / "ground_truth" / "depth.npy")
            for label, nearfield, reference in (("plane-placed", False, centre), ("near-field", True, 1.0)):
                if label not in methods:
                    continue
                params, seconds = run(capture, folder / f"{name}_{label}", nearfield=nearfield, reference=reference,
                                      fit_kappa={"auto": None, "true": True, "false": False}[args.fit_kappa])
                m = params["metrics"]
                record = params["nearfield"]
                rounds = len(record["iterations"]) if record.get("enabled") else "–"
                median = record["median_depth_m"] if record.get("enabled") else float(np.nanmedian(
                    np.load(folder / f"{name}_{label}" / "depth.npy")))
                print(f"| {name} | {label} | {reference:g} | {m['normals']['mean_deg']:.2f} | "
                      f"{m['normals']['median_deg']:.2f} | {100 * m['depth_absolute']['relative_to_distance']:.2f} | "
                      f"{100 * m['depth']['relative']:.2f} | {median:.4f} ({np.nanmedian(truth):.4f}) | {rounds} | "
                      f"{seconds:.1f} |", flush=True)


if __name__ == "__main__":
    main()
