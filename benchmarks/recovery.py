"""Benchmark of shape and reflectance recovery (issue 4): run time against error.

For each (resolution, number of lights) it simulates a sphere capture (configs/scenes/sphere.yaml:
FMBRDF μ 1.5, α 0.25, β 2, 12-bit, shot + read noise; K lights on a spiral 10–55° from the view axis)
and reports, per method, wall time and mean normal error (degrees, over the mask), plus parameter
errors and the error after each stage (history):

- ``polarshape``: :func:`polarshape.normals.recover_capture` (coarse-to-fine alternation of
  per-pixel Levenberg–Marquardt normals and variable-projection global parameters);
- ``lambertian``: robust Lambertian photometric stereo on s0 (the initial normals);
- ``adam``: "Adam on the full model", mimicking the paper's released schedule: stages of Adam
  steps alternating global parameters (μ, r_k, k_s, α, β) and normals (all pixels), lr 1e-2,
  ``--adam-steps`` per stage (paper: 10 000) and up to ``--adam-alternations`` (paper: 100),
  stopped at ``--adam-budget`` seconds; the error is recorded after every stage.

Shared captures: ``--shared`` also runs ../shared/data/official_sphere128 and mitsuba_sphere_a020.

Usage:  python benchmarks/recovery.py [--sizes 128 256 512] [--lights 4 8 12 24] [--threads 2] [--solvers alternating joint]
                                      [--adam-budget 120] [--shared] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.brdf import build_tables
from polarshape.io.atomic import atomic_write_bytes
from polarshape.io.capture import Capture, load_capture
from polarshape.metrics import angular_error_deg
from polarshape.normals import initial_normals, recover_capture
from polarshape.recover.observations import flatten_observations
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import preprocess_capture
from polarshape.recover.reflectometry import render_parts
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
TRUTH = {"ior": 1.5, "alpha": 0.25, "beta": 2.0, "kappa": 0.0}


def simulate(size: int, n_lights: int, seed: int = 0) -> Capture:
    """Sphere capture of ``size`` × ``size`` super-pixels under ``n_lights`` directional lights."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    raw = 2 * size
    d["camera"]["width"] = d["camera"]["height"] = raw
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / raw
    d["objects"][0]["material"].update(TRUTH)
    d["lights"] = [
        {"zenith_deg": float(z), "azimuth_deg": float((137.5 * i) % 360), "intensity": 1.0}
        for i, z in enumerate(np.linspace(10, 55, n_lights))
    ]
    return SimulatedCamera(parse_scene_config(d), seed=seed).render_capture(progress=False)


def mean_error(normals: torch.Tensor, capture: Capture) -> float:
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    m = torch.from_numpy(np.asarray(capture.mask, dtype=bool)) & torch.isfinite(gt).all(-1) & torch.isfinite(normals).all(-1)
    return float(angular_error_deg(normals.double()[m], gt[m]).mean())


def run_polarshape(capture: Capture, model: str, label: str | None = None, **options: object) -> dict:
    t0 = time.perf_counter()
    pre = {k: options.pop(k) for k in ("demosaic", "sample_at") if k in options}
    result = recover_capture(capture, RecoveryOptions(model=model, **options), **pre)
    wall = time.perf_counter() - t0
    out = {"method": label or ("polarshape" if model == "fmbrdf" else "lambertian"), "seconds": wall,
           "normal_error_deg": mean_error(result.normals, capture), "timings": result.timings, "skipped": result.skipped}
    if model == "fmbrdf":
        out["params"] = result.params
        out["param_error"] = {k: abs(result.params[k] - v) for k, v in TRUTH.items() if k in result.params}
        out["history"] = [{"seconds": h["seconds"], "loss": h["loss"], "stage": h["stage"]} for h in result.history]
    return out


def run_adam(capture: Capture, steps: int, alternations: int, budget_s: float, lr: float = 1e-2) -> dict:
    """Adam on the full model (global params, then normals, alternating), error after each stage."""
    inp = preprocess_capture(capture)
    m = inp.mask
    obs = flatten_observations(inp, m)  # the same observations and start as polarshape's
    n0 = initial_normals(inp).normals
    raw_n = n0[m].clone().requires_grad_(True)  # (P, 3), normalised in the model
    u = {"ior": torch.tensor(1.5, dtype=torch.float64, requires_grad=True),
         "log_alpha": torch.tensor(math.log(0.5), dtype=torch.float64, requires_grad=True),
         "log_beta": torch.tensor(math.log(2.0), dtype=torch.float64, requires_grad=True),
         "log_ks": torch.tensor(0.0, dtype=torch.float64, requires_grad=True),
         "log_rk": torch.tensor(math.log(0.5), dtype=torch.float64, requires_grad=True)}
    w = obs.weight.unsqueeze(-1) * torch.tensor([1.0, 0.5, 0.5])

    def loss_fn() -> torch.Tensor:
        tables = build_tables(ior=u["ior"].clamp(1.01, 3.0), alpha=u["log_alpha"].exp(), beta=u["log_beta"].exp(), kappa=0.0)
        n = raw_n / raw_n.norm(dim=-1, keepdim=True)
        surf, body = render_parts(tables, n, obs)
        ks = u["log_ks"].exp()
        model = ks * surf + ks * u["log_rk"].exp() * body
        return (w * (obs.stokes - model) ** 2).sum() / w.sum()

    t0 = time.perf_counter()
    history = []
    opt_g = torch.optim.Adam(list(u.values()), lr=lr)
    opt_n = torch.optim.Adam([raw_n], lr=lr * 0.1)
    for alt in range(alternations):
        for stage, opt in (("global", opt_g), ("normals", opt_n)):
            for _ in range(steps):
                opt.zero_grad()
                loss = loss_fn()
                loss.backward()
                opt.step()
                if time.perf_counter() - t0 > budget_s:
                    break
            normals = torch.full((*m.shape, 3), math.nan, dtype=torch.float64)
            normals[m] = (raw_n / raw_n.norm(dim=-1, keepdim=True)).detach().double()
            history.append({"alternation": alt, "stage": stage, "seconds": time.perf_counter() - t0,
                            "loss": float(loss.detach()), "normal_error_deg": mean_error(normals, capture)})
            if time.perf_counter() - t0 > budget_s:
                break
        if time.perf_counter() - t0 > budget_s:
            break
    return {"method": "adam", "seconds": time.perf_counter() - t0, "normal_error_deg": history[-1]["normal_error_deg"],
            "params": {"ior": float(u["ior"].detach().clamp(1.01, 3.0)), "alpha": float(u["log_alpha"].detach().exp()), "beta": float(u["log_beta"].detach().exp())},
            "history": history, "steps_per_stage": steps, "budget_s": budget_s}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="super-pixels across (128–1024)")
    ap.add_argument("--lights", type=int, nargs="+", default=[12], help="numbers of lights (4–24)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--adam-steps", type=int, default=200, help="Adam steps per stage (paper: 10000)")
    ap.add_argument("--adam-alternations", type=int, default=100)
    ap.add_argument("--adam-budget", type=float, default=60.0, help="seconds per Adam run (0 = skip Adam)")
    ap.add_argument("--shared", action="store_true", help="also run the captures in ../shared/data")
    ap.add_argument("--out", type=Path, default=None, help="write all results as JSON here")
    ap.add_argument("--solvers", nargs="+", choices=["alternating", "joint"], default=None,
                    help="recovery.solver of the polarshape rows, each in turn (default: the default solver)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(f"# Recovery benchmark — {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads\n")
    print("| capture | K | method | wall (s) | mean normal error (°) | μ | α | β | stages (s) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---|")
    rows = []
    solvers: list[str | None] = list(args.solvers or [None])

    def fmbrdf_runs(capture: Capture, label: str | None, **options: object) -> list[dict]:
        """The polarshape rows of ``capture``: one per solver of ``--solvers`` (named in the label when given)."""
        out = []
        for solver in solvers:
            extra = {} if solver is None else {"solver": solver}
            name = label if solver is None else f"{label or 'polarshape'} ({solver})"
            out.append(run_polarshape(capture, "fmbrdf", name, **options, **extra))
        return out

    def report(name: str, k: int, r: dict) -> None:
        p = r.get("params", {})
        fmt = lambda key: f"{p[key]:.3f}" if key in p else "–"  # noqa: E731
        t = r.get("timings", {})
        stages = " · ".join(f"{key} {t[key]:.1f}" for key in ("preprocess", "init_lambertian", "global_params", "normals",
                                                              "kappa_test", "smoothing") if key in t)
        if r["method"] == "adam":
            stages = f"{len(r['history'])} stages of ≤ {r['steps_per_stage']} steps"
        print(f"| {name} | {k} | {r['method']} | {r['seconds']:.2f} | {r['normal_error_deg']:.3f} | "
              f"{fmt('ior')} | {fmt('alpha')} | {fmt('beta')} | {stages} |", flush=True)
        rows.append({"capture": name, "lights": k, **r})

    for size in args.sizes:
        for k in args.lights:
            capture = simulate(size, k)
            name = f"sphere {size}²"
            if k < 3:
                print(f"| {name} | {k} | – | – | fewer than 3 lights: refused | | | | |")
                continue
            report(name, k, run_polarshape(capture, "lambertian"))
            for r in fmbrdf_runs(capture, None):
                report(name, k, r)
            if args.adam_budget > 0:
                report(name, k, run_adam(capture, args.adam_steps, args.adam_alternations, args.adam_budget))
    if args.shared:
        for folder in ("official_sphere128", "mitsuba_sphere_a020"):
            path = REPO / ".." / "shared" / "data" / folder
            if not path.is_dir():
                print(f"| {folder} | | skipped: {path} not found | | | | | | |")
                continue
            capture = load_capture(path)
            if folder == "official_sphere128":
                # its ground truth is at each block's 90° site (top left): estimate there too
                variants = [("lambertian", "lambertian (90° site)", {"sample_at": "top_left"}),
                            ("fmbrdf", "polarshape, super-pixel Stokes (block centre)", {"demosaic": "superpixel"}),
                            ("fmbrdf", "polarshape (90° site)", {"sample_at": "top_left"}),
                            ("fmbrdf", "polarshape (90° site), smoothness 0.5", {"sample_at": "top_left", "smoothness": 0.5})]
            else:
                variants = [("lambertian", None, {}), ("fmbrdf", None, {}), ("fmbrdf", "polarshape, smoothness 0.5", {"smoothness": 0.5})]
            for model, label, options in variants:
                runs = fmbrdf_runs(capture, label, **options) if model == "fmbrdf" else [
                    run_polarshape(capture, model, label, **options)]
                for r in runs:
                    report(folder, capture.num_lights, r)
    if args.out is not None:
        atomic_write_bytes(args.out, json.dumps(rows, indent=1, default=str).encode(), overwrite=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
