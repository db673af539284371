"""Peak memory (max RSS) and time per stage of a full-frame run (issue 12).

Each stage runs in its own process (``python benchmarks/memory.py --stage NAME …``), which reports
its own peak resident set size (``resource.getrusage(RUSAGE_SELF).ru_maxrss``) and wall time:

- ``simulate``: ``polarshape simulate`` of the sphere scene (configs/scenes/sphere.yaml) at
  ``--width`` × ``--height`` raw pixels under ``--lights`` directional lights, the sphere filling
  most of the frame (skipped with ``--capture``);
- ``load``: ``load_capture`` alone (the frames in memory: the floor of every later stage);
- ``preprocess``: ``load_capture`` + ``preprocess_capture`` (float32);
- ``tables``: ``build_tables`` of one material at ``--kappa`` (and ``--alpha``);
- ``run``: ``polarshape run`` end to end, one per ``--models`` entry (``recovery.max_outer_iterations``
  from ``--max-outer-iterations`` when given).

Usage (2448 × 2048, 12 lights: about 35 min on 2 CPU cores with --max-outer-iterations 2):

    python benchmarks/memory.py [--capture DIR | --width 2448 --height 2048 --lights 12]
        [--stages simulate load preprocess tables run] [--models lambertian fmbrdf]
        [--max-outer-iterations 2] [--kappa 1000] [--alpha 0.5] [--work DIR]

Everything it writes (the capture, run configurations, result folders) goes to ``--work`` (default: a
temporary folder, deleted at the end); never into the repository. Prints one markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENE = REPO / "configs" / "scenes" / "sphere.yaml"
STAGE_NAMES = ("simulate", "load", "preprocess", "tables", "run")


def full_frame_scene(width: int, height: int, n_lights: int, path: Path) -> Path:
    """The sphere scene at ``width`` × ``height`` raw pixels, the sphere 93 % of the frame height across,
    ``n_lights`` directional lights on a spiral (zenith 15–55°, golden-angle azimuths)."""
    import yaml

    scene = yaml.safe_load(SCENE.read_text())
    camera = scene["camera"]
    camera.update(width=width, height=height)
    sphere = scene["objects"][0]["shape"]
    sphere["radius"] = 0.465 * min(width, height) * float(camera["pixel_size_m"])
    scene["lights"] = [
        {"zenith_deg": 15.0 + 40.0 * i / max(n_lights - 1, 1), "azimuth_deg": (137.5 * i) % 360.0, "intensity": 1.0}
        for i in range(n_lights)
    ]
    path.write_text(yaml.safe_dump(scene, sort_keys=False))
    return path


def run_config(capture: Path, model: str, max_outer: int | None, path: Path) -> Path:
    import yaml

    recovery: dict = {"model": model}
    if max_outer is not None:
        recovery["max_outer_iterations"] = max_outer
    config = {"format": "polarshape-run/1", "input": {"type": "capture", "path": str(capture)}, "progress": False,
              "recovery": recovery}
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def stage(args: argparse.Namespace) -> dict:
    """Run one stage in this process; returns what it measured (its own peak RSS)."""
    t0 = time.perf_counter()
    extra: dict = {}
    if args.stage == "simulate":
        from polarshape.cli import main as cli

        status = cli(["simulate", str(args.scene), "--out", str(args.capture), "--overwrite", "--quiet"])
        extra["status"] = status
    elif args.stage in ("load", "preprocess"):
        import torch

        from polarshape.io.capture import load_capture
        from polarshape.recover.preprocess import preprocess_capture

        capture = load_capture(args.capture)
        extra["frames"] = list(capture.frames.shape)
        if args.stage == "preprocess":
            inputs = preprocess_capture(capture, dtype=torch.float32)
            extra["mask_px"] = int(inputs.mask.sum())
    elif args.stage == "tables":
        from polarshape.brdf import build_tables

        tables = build_tables(ior=1.5, alpha=args.alpha, beta=2.0, kappa=args.kappa)
        extra["modes"] = tables.body.n_modes
    else:  # run
        from polarshape.cli import main as cli

        extra["status"] = cli(["run", str(args.config), "--out", str(args.out), "--overwrite", "--quiet"])
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return {"seconds": time.perf_counter() - t0, "max_rss_mb": peak_mb, **extra}


def measure(label: str, argv: list[str]) -> dict:
    """Run ``memory.py --stage …`` in a subprocess; its last stdout line is its JSON report."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, *argv], capture_output=True, text=True)
    if proc.returncode != 0 or not proc.stdout.strip():
        sys.stderr.write(proc.stderr[-4000:])
        return {"label": label, "failed": proc.returncode, "seconds": time.perf_counter() - t0, "max_rss_mb": math.nan}
    return {"label": label, **json.loads(proc.stdout.strip().splitlines()[-1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, help="an existing capture folder (else one is simulated)")
    parser.add_argument("--width", type=int, default=2448, help="raw mosaic width of the simulated capture")
    parser.add_argument("--height", type=int, default=2048, help="raw mosaic height of the simulated capture")
    parser.add_argument("--lights", type=int, default=12, help="lights of the simulated capture")
    parser.add_argument("--stages", nargs="+", choices=STAGE_NAMES, default=list(STAGE_NAMES))
    parser.add_argument("--models", nargs="+", choices=["lambertian", "fmbrdf", "auto"], default=["lambertian"])
    parser.add_argument("--max-outer-iterations", type=int, default=None, help="recovery.max_outer_iterations")
    parser.add_argument("--kappa", type=float, default=1000.0, help="tables: microfacet correlation κ")
    parser.add_argument("--alpha", type=float, default=0.5, help="tables: roughness α (rad)")
    parser.add_argument("--work", type=Path, default=None, help="folder for captures and results (default: temporary)")
    # one stage in this process (what the parent runs in each subprocess)
    parser.add_argument("--stage", choices=STAGE_NAMES, help=argparse.SUPPRESS)
    parser.add_argument("--scene", help=argparse.SUPPRESS)
    parser.add_argument("--config", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stage:
        print(json.dumps(stage(args)))
        return

    import torch

    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"threads: {torch.get_num_threads()}")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work if args.work is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = []
        capture = args.capture
        if capture is None:
            capture = work / "capture"
            if "simulate" in args.stages or not capture.exists():
                scene = full_frame_scene(args.width, args.height, args.lights, work / "scene.yaml")
                rows.append(measure(f"simulate {args.width}×{args.height}, {args.lights} lights",
                                    ["--stage", "simulate", "--scene", str(scene), "--capture", str(capture)]))
        for name in ("load", "preprocess"):
            if name in args.stages:
                rows.append(measure(name, ["--stage", name, "--capture", str(capture)]))
        if "tables" in args.stages:
            rows.append(measure(f"tables κ={args.kappa:g}, α={args.alpha:g}",
                                ["--stage", "tables", "--kappa", str(args.kappa), "--alpha", str(args.alpha)]))
        if "run" in args.stages:
            for model in args.models:
                config = run_config(capture.absolute(), model, args.max_outer_iterations, work / f"run_{model}.yaml")
                label = f"run {model}" + (f" (max_outer_iterations {args.max_outer_iterations})"
                                          if args.max_outer_iterations is not None and model != "lambertian" else "")
                rows.append(measure(label, ["--stage", "run", "--config", str(config), "--out", str(work / f"result_{model}")]))
    print()
    print("| stage | time (s) | peak RSS (MB) | notes |")
    print("|---|---|---|---|")
    for row in rows:
        notes = {k: v for k, v in row.items() if k not in ("label", "seconds", "max_rss_mb")}
        print(f"| {row['label']} | {row['seconds']:.1f} | {row['max_rss_mb']:.0f} | {json.dumps(notes) if notes else ''} |")


if __name__ == "__main__":
    main()
