"""``polarshape run`` over a grid of materials and cameras: 256² × 13 lights ≤ 8 s for every one (issue 13).

Cases: α ∈ ``--alphas`` × κ ∈ ``--kappas`` × camera ∈ ``--cameras`` (default 0.03 0.1 0.3 0.8 × 0 50 ×
orthographic perspective: 16 cases). Each is the sphere scene of :mod:`benchmarks.scaling`
(configs/scenes/sphere.yaml through :func:`benchmarks.memory.full_frame_scene`: the sphere 93 % of the frame
height across, ``--lights`` directional lights on a spiral, zenith 15–55°) at ``--size``² super-pixels with
the sphere's α and κ replaced (μ 1.5, β 2, k_s 1, k_b 0.5 kept); ``perspective`` puts a pinhole at the origin
and the sphere (radius 0.1 m) 0.5 m away, its outline the same size in the image (a strong perspective:
the rays spread ±11.5°). Every case is rendered once (``polarshape simulate`` in a subprocess, cached in
``--work``) and run in a fresh process with :func:`benchmarks.scaling.run_case` (the scaling benchmark's
run: float32, ``report.enabled: false``, ``validation.holdout: none``; ``--solver`` sets ``recovery.solver``
when given, else the default).

Columns, from the run's params.json: total (s, the run's own ``timings_s``); the recovery's steps
(``recovery_timings_s``): material = the coarsest level's material steps (``global_params`` + ``joint``
without its κ test), κ test (``kappa_test``), normals (every level's per-pixel normals), rest = total minus
those three (preprocess, robust PS, pyramid, final render, the stages after the recovery); outer
iterations of the coarsest level (alternating: material/normal rounds; joint: LM iterations); converged
(alternating: the loss changed by ≤ 0.1 % over the last two outer iterations, the solver's own test; joint:
the solver's verdict); the relative loss change at the end (alternating: between the last two outer
iterations; joint: its last iteration's); κ and α found; the mean normal error (° against the simulator's
ground truth); the model the run chose (``recovery.model: auto``: a lobe too broad to tell from
Lambertian runs the Lambertian path, no material solve). CPU (s): the run's process, imports included (a fairer clock than the wall on a
busy box). Then the median total and max/median (the issue: no case slower than 2× the median).

Usage:
    python benchmarks/material_grid.py [--alphas 0.03 0.1 0.3 0.8] [--kappas 0 50]
        [--cameras orthographic perspective] [--size 256] [--lights 13] [--exposure-us US]
        [--solver alternating|joint]
        [--work DIR] [--tag NAME] [--json FILE] [--md FILE] [--reuse] [--compare TAG]

    # before/after: each checkout's grid on the same captures, then both side by side
    PYTHONPATH=<main> python benchmarks/material_grid.py --work DIR --tag main
    PYTHONPATH=<branch> python benchmarks/material_grid.py --work DIR --tag branch --reuse --compare main

Set OMP_NUM_THREADS (and say which); compare two checkouts with PYTHONPATH=<checkout> and the same
``--work`` (the captures are shared; the results are kept per checkout with ``--tag``; ``--compare TAG``
prints another tag's results beside these).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from memory import full_frame_scene  # noqa: E402 (benchmarks/ is a folder of scripts)
from scaling import machine_line, run_case, simulate  # noqa: E402

ALPHAS = (0.03, 0.1, 0.3, 0.8)
KAPPAS = (0.0, 50.0)
CAMERAS = ("orthographic", "perspective")
#: perspective: the sphere's distance and radius (m); the focal length puts its outline where the
#: orthographic camera has it (93 % of the frame height)
PERSPECTIVE_DISTANCE_M, PERSPECTIVE_RADIUS_M = 0.5, 0.1


def case_name(alpha: float, kappa: float, camera: str, size: int, lights: int, exposure_us: float | None = None) -> str:
    """``a0.03_k50_perspective_256@13``: one case's name (files in ``--work``); ``_e300us`` appended for an
    exposure other than the scene's."""
    return f"a{alpha:g}_k{kappa:g}_{camera}_{size}@{lights}" + ("" if exposure_us is None else f"_e{exposure_us:g}us")


def parse_case(name: str) -> tuple[float, float, str, int, int]:
    """The inverse of :func:`case_name` but for the exposure (:func:`parse_exposure`)."""
    a, k, camera, rest = name.split("_", 3)
    size, lights = rest.split("_e")[0].split("@")
    return float(a[1:]), float(k[1:]), camera, int(size), int(lights)


def parse_exposure(name: str) -> float | None:
    """The exposure (µs) a :func:`case_name` carries, None for the scene's own."""
    tail = name.split("@", 1)[1]
    return float(tail.split("_e", 1)[1].removesuffix("us")) if "_e" in tail else None


def scene_file(alpha: float, kappa: float, camera: str, size: int, lights: int, path: Path,
               exposure_us: float | None = None) -> Path:
    """The scene of one case (module docstring) written to ``path``; ``exposure_us``: the camera's exposure
    instead of the scene's (configs/scenes/sphere.yaml: 10 ms, which clips the lobe's core at α ≤ 0.1)."""
    import yaml

    raw = 2 * size
    full_frame_scene(raw, raw, lights, path)
    scene = yaml.safe_load(path.read_text())
    scene["objects"][0]["material"].update(alpha=float(alpha), kappa=float(kappa))
    if exposure_us is not None:
        scene["camera"]["exposure_us"] = float(exposure_us)
    if camera == "perspective":
        cam = scene["camera"]
        cam["projection"] = "perspective"
        cam.pop("pixel_size_m", None)
        cam.pop("principal_point", None)
        half_angle = math.asin(PERSPECTIVE_RADIUS_M / PERSPECTIVE_DISTANCE_M)
        f = 0.465 * raw / math.tan(half_angle)  # the outline's radius 0.465 · raw pixels
        cam["intrinsics"] = {"fx": f, "fy": f, "cx": (raw - 1) / 2, "cy": (raw - 1) / 2}
        sphere = scene["objects"][0]["shape"]
        sphere.update(center=[0.0, 0.0, PERSPECTIVE_DISTANCE_M], radius=PERSPECTIVE_RADIUS_M)
    elif camera != "orthographic":
        raise ValueError(f"--cameras: {camera!r} is neither orthographic nor perspective")
    path.write_text(yaml.safe_dump(scene, sort_keys=False))
    return path


def render(work: Path, name: str, device: str) -> Path:
    """The capture of case ``name`` (rendered unless ``work`` has it)."""
    capture = work / f"capture_{name}"
    if not (capture / "capture.yaml").exists():
        simulate(scene_file(*parse_case(name), work / f"scene_{name}.yaml", parse_exposure(name)), capture, device)
    return capture


def convergence(params: dict, max_outer: int) -> dict:
    """Outer iterations, converged?, relative loss change at the end, from params.json's loss history
    (the coarsest level: the one whose records carry the material steps)."""
    history = [h for h in params["losses"]["history"] if h.get("stage", "").startswith("level")]
    if not history:  # no FMBRDF solve (model lambertian: one least-squares fit)
        return {"outer": 0, "converged": None, "rel_change": math.nan}
    coarsest = max(int(h["stage"].removeprefix("level")) for h in history)
    level = [h for h in history if h["stage"] == f"level{coarsest}"]
    joint = [h for h in level if h.get("solver") == "joint"]
    if joint:  # the joint solve's own iterations and verdict
        converged = not any(s.startswith("recovery: joint: not converged") for s in params.get("skipped", []))
        return {"outer": len(joint), "converged": converged, "rel_change": abs(float(joint[-1]["rel_change"]))}
    rounds = [float(h["loss"]) for h in level if "solver" not in h]  # one record per outer iteration
    rel = abs(rounds[-2] - rounds[-1]) / max(abs(rounds[-2]), 1e-300) if len(rounds) >= 2 else math.nan
    converged = len(rounds) >= 3 and (len(rounds) < max_outer or abs(rounds[-3] - rounds[-1]) <= 1e-3 * abs(rounds[-3]))
    return {"outer": len(rounds), "converged": converged, "rel_change": rel}


def summarise(case: dict, params: dict, max_outer: int) -> dict:
    """One row's figures from :func:`benchmarks.scaling.run_case`'s record and the run's params.json."""
    rt = params.get("recovery_timings_s", {})
    kappa_test = float(rt.get("kappa_test", 0.0))
    joint = float(rt.get("joint", 0.0))
    material = float(rt.get("global_params", 0.0)) + (joint - kappa_test if joint > 0 else 0.0)
    normals = float(rt.get("normals", 0.0))
    total = float(case["total"])
    return {
        "total": total, "material": material, "kappa_test": kappa_test, "normals": normals,
        "rest": total - material - kappa_test - normals, **convergence(params, max_outer),
        "kappa": float(params["params"].get("kappa", math.nan)), "alpha": float(params["params"].get("alpha", math.nan)),
        "model": params["model"], "mean_err_deg": case["mean_err_deg"], "mask_px": case["mask_px"],
        "cpu_s": case["cpu_s"], "threads": case["threads"],
    }


def measure(args: argparse.Namespace, work: Path, name: str) -> dict:
    """One case in a fresh process (``--case``), cached as JSON in ``work``."""
    record = work / f"result_{args.tag}_{name}.json"
    if args.reuse and record.exists():
        return json.loads(record.read_text())
    render(work, name, args.device)
    argv = [sys.executable, __file__, "--case", name, "--work", str(work), "--device", args.device,
            "--case-json", str(record), "--tag", args.tag]
    if args.solver:
        argv += ["--solver", args.solver]
    proc = subprocess.run(argv, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-4000:])
        return {"failed": proc.returncode}
    return json.loads(record.read_text())


def run_one(args: argparse.Namespace, work: Path, name: str) -> dict:
    """Case ``name`` in this process."""
    from polarshape.recover.options import RecoveryOptions

    capture = render(work, name, args.device)
    out = work / f"run_{args.tag}_{name}"
    case = run_case(capture, out, args.device, None, None, {"solver": args.solver} if args.solver else None)
    params = json.loads((out / "params.json").read_text())
    return summarise(case, params, RecoveryOptions().max_outer_iterations)


def table(names: list[str], results: list[dict]) -> list[str]:
    """The Markdown table of the cases and the median, max/median line."""
    lines = ["| α | κ | camera | total (s) | CPU (s) | material | κ test | normals | rest | outer it. | converged | "
             "rel. Δloss | model | κ found | α found | mean err (°) |",
             "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---|---:|---:|---:|"]
    for name, r in zip(names, results):
        a, k, camera, _, _ = parse_case(name)
        if "failed" in r:
            lines.append(f"| {a:g} | {k:g} | {camera} | failed (exit {r['failed']}) |" + " |" * 12)
            continue
        conv = {True: "yes", False: "**no**", None: "—"}[r["converged"]]
        lines.append(
            f"| {a:g} | {k:g} | {camera} | **{r['total']:.1f}** | {r['cpu_s']:.1f} | {r['material']:.2f} | {r['kappa_test']:.2f} | "
            f"{r['normals']:.2f} | {r['rest']:.2f} | {r['outer']} | {conv} | {r['rel_change']:.1e} | "
            f"{r['model']} | {r['kappa']:.3g} | {r['alpha']:.3g} | {r['mean_err_deg']:.3f} |")
    totals = [r["total"] for r in results if "failed" not in r]
    if totals:
        med = statistics.median(totals)
        lines += ["", f"median {med:.1f} s, max {max(totals):.1f} s, max/median {max(totals) / med:.2f}; "
                  f"{sum(t <= 8.0 for t in totals)}/{len(totals)} cases ≤ 8 s"]
    return lines


def comparison(names: list[str], before: list[dict | None], after: list[dict], tags: tuple[str, str]) -> list[str]:
    """Before/after side by side (``before``: another checkout's results of the same cases in ``--work``)."""
    lines = [f"| α | κ | camera | total (s) {tags[0]} → {tags[1]} | CPU (s) | material | normals | outer it. | "
             "α found | mean err (°) |", "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    pairs = []
    for name, b, a in zip(names, before, after):
        al, k, camera, _, _ = parse_case(name)
        if b is None or "failed" in b or "failed" in a:
            lines.append(f"| {al:g} | {k:g} | {camera} | not measured by both |" + " |" * 6)
            continue
        pairs.append((b, a))

        def arrow(key: str, fmt: str) -> str:
            return f"{format(b[key], fmt)} → {format(a[key], fmt)}"

        lines.append(f"| {al:g} | {k:g} | {camera} | {arrow('total', '.1f')} | **{arrow('cpu_s', '.1f')}** | "
                     f"{arrow('material', '.2f')} | {arrow('normals', '.2f')} | {arrow('outer', 'd')} | "
                     f"{arrow('alpha', '.3g')} | {arrow('mean_err_deg', '.3f')} |")
    if pairs:
        lines.append("")
        for key, label in (("total", "total"), ("cpu_s", "CPU")):
            b, a = [r[key] for r, _ in pairs], [r[key] for _, r in pairs]
            lines.append(f"{label}: median {statistics.median(b):.1f} → {statistics.median(a):.1f} s, max "
                         f"{max(b):.1f} → {max(a):.1f} s, max/median {max(b) / statistics.median(b):.2f} → "
                         f"{max(a) / statistics.median(a):.2f}; sum {sum(b):.1f} → {sum(a):.1f} s "
                         f"(ratio {sum(a) / sum(b):.2f})")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--alphas", nargs="*", type=float, default=list(ALPHAS))
    parser.add_argument("--kappas", nargs="*", type=float, default=list(KAPPAS))
    parser.add_argument("--cameras", nargs="*", choices=CAMERAS, default=list(CAMERAS))
    parser.add_argument("--size", type=int, default=256, help="N×N super-pixels")
    parser.add_argument("--lights", type=int, default=13)
    parser.add_argument("--exposure-us", type=float, default=None,
                        help="camera exposure of every case (default: the scene's 10 ms, which clips the lobe's core "
                        "at alpha <= 0.1); the case names get _e<µs>us")
    parser.add_argument("--solver", choices=["alternating", "joint"], default=None,
                        help="recovery.solver (default: the configuration's)")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("--work", type=Path, default=None, help="captures and results (default: a temporary folder)")
    parser.add_argument("--tag", default="run", help="names this checkout's results in --work (e.g. main, branch)")
    parser.add_argument("--reuse", action="store_true", help="keep results of cases already measured in --work")
    parser.add_argument("--json", type=Path, default=None, help="write every case's figures to this JSON file")
    parser.add_argument("--md", type=Path, default=None, help="also write the table to this Markdown file")
    parser.add_argument("--compare", metavar="TAG", default=None,
                        help="also print this tag's results of the same cases in --work beside these (before → after)")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # one case in this process (what the grid runs)
    parser.add_argument("--case-json", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.exposure_us is not None and not args.exposure_us > 0:
        parser.error(f"--exposure-us must be a positive number of microseconds; got {args.exposure_us:g}")

    with tempfile.TemporaryDirectory() as tmp:
        work = (args.work or Path(tmp)).absolute()
        work.mkdir(parents=True, exist_ok=True)
        if args.case:
            result = run_one(args, work, args.case)
            if args.case_json:
                args.case_json.write_text(json.dumps(result))
            print("\n".join(table([args.case], [result])))
            return
        names = [case_name(a, k, c, args.size, args.lights, args.exposure_us) for c in args.cameras
                 for k in args.kappas for a in args.alphas]
        head = [machine_line(), f"{args.size}² super-pixels, {args.lights} lights, solver "
                f"{args.solver or 'default'}", ""]
        print("\n".join(head), flush=True)
        results = []
        for name in names:
            results.append(measure(args, work, name))
            print("\n".join(table([name], [results[-1]])[2:3]), flush=True)
        lines = [*head, *table(names, results)]
        if args.compare:
            before = [json.loads(f.read_text()) if (f := work / f"result_{args.compare}_{name}.json").exists()
                      else None for name in names]
            lines += ["", *comparison(names, before, results, (args.compare, args.tag))]
        print("\n".join(lines[len(head):]), flush=True)
        if args.json:
            args.json.write_text(json.dumps(dict(zip(names, results)), indent=1))
        if args.md:
            args.md.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
