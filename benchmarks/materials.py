"""Benchmark of objects of several materials (issue 15, part 2): time against error, beside today's
single-material fit on the same captures.

Simulated captures (12-bit, shot + read noise, cast shadows), N × N super-pixels:

- ``two_materials``: configs/scenes/two_materials_blob.yaml (perspective, 12 lights), the bumpy
  blob split by a plane into a glossy half (α 0.08, μ 1.6) and a rough half (α 0.45, μ 1.45),
  exposed at 2.5 ms (the glossy lobe does not clip);
- ``one_material``: configs/scenes/blob.yaml as it is (α 0.3, μ 1.5, κ 20);
- ``one_material_sphere``: configs/scenes/sphere.yaml as it is (orthographic, 9 lights, α 0.25);
- ``mismatch_baek_sphere`` / ``mismatch_baek_ggx_sphere`` / ``mismatch_baek_blob``: the sphere
  (blob) rendered with Baek's pBRDF (Beckmann α 0.25 / GGX α 0.25 / Beckmann α 0.3, μ 1.5): one
  material that the FMBRDF does not explain exactly (``--cases`` to run them).

Each is recovered with ``recovery.materials: 1`` (today's single-material fit) and ``auto`` in one
process, ``--repeat`` times (the order alternating between repeats; times are then the medians and
the ratio the median of the per-repeat ratios: a loaded machine moves whole runs). Per run: the
number of materials found, the model choice's decision statistics (each split tried: the early
test's part sizes, the in-sample and held-out-light relative gains, what decided), the assignment
accuracy away from the material edge (super-pixels whose 8 neighbours all carry their true
material, each found material matched to the true one of nearest α), α and μ of each true material
against the fit, the mean normal error over the mask (and over the pixels lit by ≥ K − 3 lights,
as tests/test_normals.py measures), wall time, and the ratio of each to the single-material run's.

``--solver`` sets ``recovery.solver`` of both runs (default: the default solver).

Usage:  python benchmarks/materials.py [--size 80] [--repeat 3] [--cases one_material,...] [--solver joint]
                                      [--out materials.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.atomic import atomic_write_text
from polarshape.io.capture import Capture
from polarshape.metrics import angular_error_deg
from polarshape.normals import NormalsResult, recover_capture
from polarshape.recover.materials import boundary_pixels
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
logger = logging.getLogger("benchmarks.materials")

def _baek(alpha: float, distribution: str) -> dict[str, Any]:
    return {"model": "baek", "ior": 1.5, "k_s": 1.0, "k_d": 0.5, "alpha": alpha, "distribution": distribution}


#: (scene file, exposure µs or None for the scene's own, material replacing the scene's or None).
CASES: dict[str, tuple[str, float | None, dict[str, Any] | None]] = {
    "two_materials": ("two_materials_blob", None, None),
    "one_material": ("blob", None, None),
    "one_material_sphere": ("sphere", None, None),
    "mismatch_baek_sphere": ("sphere", None, _baek(0.25, "beckmann")),
    "mismatch_baek_ggx_sphere": ("sphere", None, _baek(0.25, "ggx")),
    "mismatch_baek_blob": ("blob", None, _baek(0.3, "beckmann")),
}
DEFAULT_CASES = ("two_materials", "one_material", "one_material_sphere")


def simulate(scene: str, size: int, exposure_us: float | None, material: dict[str, Any] | None = None
             ) -> tuple[Capture, list[dict[str, float]]]:
    """The capture of configs/scenes/<scene>.yaml at size × size super-pixels (the same field of
    view), its object's material replaced by ``material`` if given, and its true materials (in the
    numbering of the ground truth's material map)."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / f"{scene}.yaml").read_text())
    raw = 2 * size
    if d["camera"].get("projection") == "perspective":
        f = d["camera"]["intrinsics"]["fx"] * raw / d["camera"]["width"]
        d["camera"]["intrinsics"] = {"fx": f, "fy": f, "cx": (raw - 1) / 2, "cy": (raw - 1) / 2}
    else:
        d["camera"]["pixel_size_m"] = d["camera"]["pixel_size_m"] * d["camera"]["width"] / raw
    d["camera"]["width"] = d["camera"]["height"] = raw
    if exposure_us is not None:
        d["camera"]["exposure_us"] = exposure_us
    obj = d["objects"][0]
    if material is not None:
        obj["material"] = material
    truth = [obj["material"]] + ([obj["split"]["material"]] if "split" in obj else [])
    capture = SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)
    return capture, [{k: float(v) for k, v in m.items() if k in ("ior", "alpha", "beta", "kappa") and k in m}
                     for m in truth]


def _match(found: list[dict[str, float]], truth: list[dict[str, float]]) -> list[int]:
    """For each found material, the true one of nearest α (log scale)."""
    return [min(range(len(truth)), key=lambda t: abs(math.log(f["alpha"] / truth[t]["alpha"]))) for f in found]


def evaluate(result: NormalsResult, capture: Capture, truth: list[dict[str, float]], seconds: float
             ) -> dict[str, Any]:
    """The benchmark's figures of one run."""
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    valid = preprocess_capture(capture).valid
    lit = valid.sum(0) >= valid.shape[0] - 3
    m = result.mask & torch.isfinite(gt).all(-1) & torch.isfinite(result.normals).all(-1)
    err = angular_error_deg(result.normals.double()[m], gt[m])
    found = result.material_params or [result.params]
    match = _match(found, truth)
    out: dict[str, Any] = {
        "seconds": seconds, "materials_found": len(found),
        "mean_error_deg": float(err.mean()), "median_error_deg": float(err.median()),
        "mean_error_lit_deg": float(angular_error_deg(result.normals.double()[m & lit], gt[m & lit]).mean()),
        "recovery_timings_s": {k: float(v) for k, v in result.timings.items()},
        "materials": [{"matched_truth": t, **{k: f.get(k) for k in ("ior", "alpha", "beta", "kappa", "k_s")}}
                      for f, t in zip(found, match)],
        "selection": [{k: r.get(k) for k in ("materials", "decided", "early_sizes", "sizes", "relative_gain",
                                             "held_out_gain", "at_bounds", "kept")}
                      for r in result.material_selection],
    }
    per_truth = []
    for t, tm in enumerate(truth):
        mine = [found[i] for i in range(len(found)) if match[i] == t]
        best = min(mine, key=lambda f: abs(math.log(f["alpha"] / tm["alpha"]))) if mine else found[0]
        per_truth.append({"true_alpha": tm["alpha"], "alpha": best["alpha"],
                          "alpha_rel_error": best["alpha"] / tm["alpha"] - 1.0,
                          "true_ior": tm["ior"], "ior": best["ior"], "ior_error": best["ior"] - tm["ior"]})
    out["per_true_material"] = per_truth
    if "materials" in capture.ground_truth and result.materials is not None:
        g = torch.from_numpy(capture.ground_truth["materials"].astype(np.int64))
        labels = result.materials.cpu()
        inner = (g >= 0) & ~boundary_pixels(torch.where(g >= 0, g, 0), g != -1) & (labels >= 0)
        predicted = torch.tensor(match)[labels.clamp_min(0)]
        out["assignment_accuracy_inner"] = float((predicted[inner] == g[inner]).double().mean())
        out["mixed_pixels"] = int(result.mixed.sum()) if result.mixed is not None else 0
    return out


def run(size: int, cases: tuple[str, ...] = DEFAULT_CASES, repeat: int = 1, solver: str | None = None) -> dict[str, Any]:
    solver_option = {} if solver is None else {"solver": solver}
    report: dict[str, Any] = {"machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads",
                              "size": size, "repeat": repeat, "solver": RecoveryOptions(**solver_option).solver,
                              "cases": {}}
    runs_of = (("single_material", 1), ("auto", "auto"))
    for name in cases:
        scene, exposure, material = CASES[name]
        capture, truth = simulate(scene, size, exposure, material)
        runs: dict[str, Any] = {}
        seconds: dict[str, list[float]] = {label: [] for label, _ in runs_of}
        for rep in range(repeat):
            for label, materials in (runs_of if rep % 2 == 0 else runs_of[::-1]):
                torch.manual_seed(0)
                t0 = time.perf_counter()
                options = RecoveryOptions(model="fmbrdf", materials=materials, **solver_option)
                result = recover_capture(capture, options)
                seconds[label].append(time.perf_counter() - t0)
                runs[label] = evaluate(result, capture, truth, seconds[label][-1])
                logger.info("%s %s (repeat %d): %s", name, label, rep, json.dumps(runs[label]))
        for label, _ in runs_of:
            runs[label]["seconds_each"] = seconds[label]
            runs[label]["seconds"] = float(np.median(seconds[label]))
        base, auto = runs["single_material"], runs["auto"]
        runs["ratios_auto_over_single"] = {
            "seconds": float(np.median([a / b for a, b in zip(seconds["auto"], seconds["single_material"])])),
            "seconds_each": [a / b for a, b in zip(seconds["auto"], seconds["single_material"])],
            "mean_error_deg": auto["mean_error_deg"] / base["mean_error_deg"],
        }
        report["cases"][name] = {"truth": truth, **runs}
    return report


def _table(report: dict[str, Any]) -> str:
    lines = [f"{'case':24s} {'run':16s} {'M':>2s} {'mean°':>6s} {'lit°':>6s} {'time s':>7s} {'assign':>7s}  "
             "α (fit/true), μ (fit/true) per true material"]
    for name, case in report["cases"].items():
        for label in ("single_material", "auto"):
            r = case[label]
            mats = "; ".join(f"α {p['alpha']:.3f}/{p['true_alpha']:.3f} μ {p['ior']:.3f}/{p['true_ior']:.3f}"
                             for p in r["per_true_material"])
            acc = r.get("assignment_accuracy_inner")
            lines.append(f"{name:24s} {label:16s} {r['materials_found']:2d} {r['mean_error_deg']:6.2f} "
                         f"{r['mean_error_lit_deg']:6.2f} {r['seconds']:7.1f} "
                         f"{'' if acc is None else f'{100 * acc:6.1f}%':>7s}  {mats}")
        ratio = case["ratios_auto_over_single"]
        lines.append(f"{name:24s} {'auto / single':16s}    {ratio['mean_error_deg']:6.2f}        "
                     f"{ratio['seconds']:7.2f}  (each repeat: {', '.join(f'{x:.3f}' for x in ratio['seconds_each'])})")
        for r in case["auto"]["selection"]:
            lines.append(f"{'':24s} split to {r['materials']}: decided {r['decided']}, early parts {r['early_sizes']}, "
                         f"in-sample gain {_num(r['relative_gain'])}, held-out gain {_num(r['held_out_gain'])}, "
                         f"parts {r['sizes']}, {'kept' if r['kept'] else 'not kept'}")
    return "\n".join(lines)


def _num(x: float | None) -> str:
    return "—" if x is None else f"{x:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=80, help="super-pixels across (default 80)")
    parser.add_argument("--repeat", type=int, default=1, help="recover each capture this many times (default 1)")
    parser.add_argument("--cases", default=",".join(DEFAULT_CASES),
                        help=f"comma-separated, of {', '.join(CASES)} (default {','.join(DEFAULT_CASES)})")
    parser.add_argument("--solver", choices=("alternating", "joint"), default=None,
                        help="recovery.solver of every run (default: the default solver)")
    parser.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = parser.parse_args()
    cases = tuple(c for c in args.cases.split(",") if c)
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        parser.error(f"--cases: unknown {unknown}; choose from {', '.join(CASES)}")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for noisy in ("polarshape.recover.coarse_to_fine", "polarshape.recover.normal_solver"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    report = run(args.size, cases, args.repeat, args.solver)
    if args.out is not None:
        atomic_write_text(args.out, json.dumps(report, indent=1) + "\n")
    logger.info("%s", _table(report))


if __name__ == "__main__":
    main()
