"""How ``polarshape run`` scales: time per stage against pixels and against lights, peak memory (issue 13).

Two sweeps of ``run_pipeline`` on simulated captures of the sphere scene (configs/scenes/sphere.yaml, the
sphere 93 % of the frame height across, directional lights on a spiral: zenith 15–55°, golden-angle
azimuths — :func:`benchmarks.memory.full_frame_scene`):

- pixels: N×N super-pixels for each ``--sizes`` entry (``full`` = the full TRI050S-PC frame, 2448×2048
  raw = 1224×1024 super-pixels) under ``--size-lights`` lights (default 12);
- lights: each ``--lights`` entry at ``--light-size``² super-pixels (default 256²).

Each case renders its capture once (``polarshape simulate`` in a subprocess, cached in ``--work``), then
runs ``polarshape run`` on it from the capture folder in a fresh subprocess, which reports the run's own
stage timings (params.json ``timings_s``; robust PS from ``recovery_timings_s``) and its peak resident
set size (``getrusage``: the run alone, the render is another process; with ``--device cuda`` also the
peak CUDA memory). The run is the default configuration except: float32 (the default), ``report.enabled:
false`` and ``validation.holdout: none`` (held-out validation and the report are checks of a run, not
part of its measured path), ``progress: false``; ``--model`` and ``--max-outer-iterations`` when given.
Stage columns: load (read the capture), preprocess, robust PS (the initial normals), recovery (the rest
of ``recover_normals``: material and normals), other (near-field, interreflection, validation, self-checks),
integration, mesh, outputs (maps written, evaluation against the simulator's ground truth, report).

For each sweep the total and every stage are fitted as ``t = a + c · (object pixels × lights)`` (least
squares): ``c`` is the constant (µs per pixel·light), ``a`` the fixed cost; "exponent" is the slope of
log t against log(pixels × lights) over the larger half of the cases (1 = linear at scale; the fixed cost
bends the small cases). "Linear" = R² ≥ 0.98 and exponent 0.8–1.2.

Usage:
    python benchmarks/scaling.py [--sizes 128 256 512 1024 full] [--lights 4 8 12 24 48]
        [--size-lights 12] [--light-size 256] [--device cpu|cuda|auto] [--model auto|fmbrdf|lambertian]
        [--max-outer-iterations N] [--work DIR] [--md FILE] [--reuse]

    # peak RSS of one case, as the issue asks (render it first so time -v sees the run only):
    python benchmarks/scaling.py --render-only --sizes full --work /tmp/scaling
    /usr/bin/time -v python benchmarks/scaling.py --case full-frame --work /tmp/scaling

``--case`` runs one case in this process (``full-frame`` or ``N`` for N² super-pixels, ``@L`` for L lights,
e.g. ``256@48``; default 12 lights) and prints its row; the sweeps run every case that way. ``--reuse``
keeps the results of cases already measured in ``--work`` (resume a sweep). BLAS threads oversubscribe a
busy box: set OMP_NUM_THREADS (and say which).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from memory import full_frame_scene  # noqa: E402 (benchmarks/ is a folder of scripts)

FULL_FRAME = (1224, 1024)  # TRI050S-PC super-pixels (2448×2048 raw)
COLUMNS = ("load", "preprocess", "robust PS", "recovery", "other", "integration", "mesh", "outputs")
OTHER = ("nearfield", "interreflection", "validation", "checks")
OUTPUTS = ("export", "evaluation", "report")


def parse_case(spec: str) -> tuple[int, int, int]:
    """``full-frame``/``full``, ``N``, ``N@L`` or ``WxH@L`` → (width, height, lights) in super-pixels."""
    size, _, lights = spec.partition("@")
    if size in ("full", "full-frame"):
        width, height = FULL_FRAME
    elif "x" in size:
        width, height = (int(v) for v in size.split("x"))
    else:
        width = height = int(size)
    return width, height, int(lights) if lights else 12


def case_name(width: int, height: int, lights: int) -> str:
    return f"{width}x{height}@{lights}"


def capture_folder(work: Path, width: int, height: int, lights: int) -> Path:
    return work / f"capture_{case_name(width, height, lights)}"


def render(work: Path, width: int, height: int, lights: int, device: str) -> Path:
    """The simulated capture of a case (rendered in a subprocess unless ``work`` has it)."""
    capture = capture_folder(work, width, height, lights)
    if (capture / "capture.yaml").exists():
        return capture
    scene = full_frame_scene(2 * width, 2 * height, lights, work / f"scene_{case_name(width, height, lights)}.yaml")
    return simulate(scene, capture, device)


def simulate(scene: Path, capture: Path, device: str) -> Path:
    """``polarshape simulate`` of a scene file into ``capture`` (in a subprocess)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "polarshape.cli", "simulate", str(scene), "--out", str(capture),
                    "--overwrite", "--quiet", "--device", "cuda" if device == "cuda" else "cpu"], check=True, stdout=sys.stderr)
    print(f"rendered {capture.name} in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return capture


def run_case(capture: Path, out: Path, device: str, model: str | None, max_outer: int | None,
             recovery_options: dict | None = None) -> dict:
    """``run_pipeline`` of one capture in this process: stage seconds, pixels, peak memory
    (``recovery_options``: more keys of the run's ``recovery`` section, e.g. ``solver``)."""
    import torch

    from polarshape.config import parse_run_config
    from polarshape.pipeline import run_pipeline

    recovery: dict = {} if model is None else {"model": model}
    recovery.update(recovery_options or {})
    if max_outer is not None:
        recovery["max_outer_iterations"] = max_outer
    config = parse_run_config({
        "format": "polarshape-run/1", "input": {"type": "capture", "path": str(capture.absolute())},
        "device": device, "dtype": "float32", "progress": False, "recovery": recovery,
        "validation": {"holdout": "none"}, "report": {"enabled": False},
    }, "scaling benchmark")
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    import polarshape.pipeline as pipeline_module

    recover_cpu = [0.0]  # CPU seconds inside recover_normals (robust PS included): a fair clock on a busy box
    recover = pipeline_module.recover_normals

    def timed_recover(*args, **kwargs):
        t0 = time.process_time()
        try:
            return recover(*args, **kwargs)
        finally:
            recover_cpu[0] += time.process_time() - t0

    pipeline_module.recover_normals = timed_recover
    try:
        params = run_pipeline(config, out, overwrite=True).params
    finally:
        pipeline_module.recover_normals = recover
    t = params["timings_s"]
    robust = float(params["recovery_timings_s"].get("init_lambertian", 0.0))
    stages = {
        "load": t["input"], "preprocess": t["preprocess"], "robust PS": robust,
        "recovery": t["recovery"] - robust, "other": sum(t.get(s, 0.0) for s in OTHER),
        "integration": t["integration"], "mesh": t["mesh"], "outputs": sum(t.get(s, 0.0) for s in OUTPUTS),
    }
    return {
        "superpixels_hw": params["capture"]["superpixels_hw"], "lights": params["capture"]["lights"],
        "mask_px": params["capture"]["mask_pixels"], "model": params["model"], "device": params["device"],
        "stages": stages, "total": t["total"],
        "mean_err_deg": params["metrics"].get("normals", {}).get("mean_deg", math.nan),
        "median_err_deg": params["metrics"].get("normals", {}).get("median_deg", math.nan),
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,  # KiB on Linux
        # the process's CPU seconds (imports and the run; on a shared box a fairer clock than the wall)
        "recovery_cpu_s": recover_cpu[0],
        "cpu_s": resource.getrusage(resource.RUSAGE_SELF).ru_utime + resource.getrusage(resource.RUSAGE_SELF).ru_stime,
        "cuda_peak_mb": torch.cuda.max_memory_allocated() / 2**20 if params["device"].startswith("cuda") else None,
        "threads": torch.get_num_threads(),
    }


def measure(args: argparse.Namespace, work: Path, width: int, height: int, lights: int) -> dict:
    """One case in a fresh process (its own peak RSS), cached as JSON in ``work``."""
    record = work / f"result_{args.device}_{case_name(width, height, lights)}.json"
    if args.reuse and record.exists():
        return json.loads(record.read_text())
    capture = render(work, width, height, lights, args.device)
    argv = [sys.executable, __file__, "--case", case_name(width, height, lights), "--work", str(work),
            "--device", args.device, "--json", str(record)]
    if args.model:
        argv += ["--model", args.model]
    if args.max_outer_iterations:
        argv += ["--max-outer-iterations", str(args.max_outer_iterations)]
    assert capture.exists()
    proc = subprocess.run(argv, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-4000:])
        return {"failed": proc.returncode, "superpixels_hw": [height, width], "lights": lights}
    return json.loads(record.read_text())


def row(case: dict) -> str:
    h, w = case["superpixels_hw"]
    if "failed" in case:
        return f"| {w}×{h} | {case['lights']} | failed (exit {case['failed']}) |" + " |" * (len(COLUMNS) + 5)
    per = case["total"] / (case["mask_px"] * case["lights"]) * 1e6
    cuda = "" if case.get("cuda_peak_mb") is None else f" (CUDA {case['cuda_peak_mb']:.0f})"
    stages = " | ".join(f"{case['stages'][c]:.2f}" for c in COLUMNS)
    return (f"| {w}×{h} | {case['lights']} | {case['mask_px']:,} | {case['device']} | {stages} | "
            f"**{case['total']:.1f}** | {per:.2f} | {case['max_rss_mb']:.0f}{cuda} | {case['mean_err_deg']:.2f} |")


def header() -> list[str]:
    return ["| super-pixels | lights | object px | device | " + " | ".join(COLUMNS)
            + " | total (s) | µs / (px·light) | peak RSS (MB) | mean err (°) |",
            "|---|---:|---:|---|" + "---:|" * (len(COLUMNS) + 4)]


def linear_fit(x: list[float], y: list[float]) -> tuple[float, float, float, float]:
    """``y ≈ a + c·x`` by least squares: (a, c, R², exponent of y against x over the upper half of the distinct
    x, at least the two largest; nan with fewer than two distinct x)."""
    n = len(x)
    mx, my = sum(x) / n, sum(y) / n
    sxx = sum((v - mx) ** 2 for v in x)
    c = sum((u - mx) * (v - my) for u, v in zip(x, y)) / sxx if sxx > 0 else math.nan
    a = my - c * mx
    ss = sum((v - my) ** 2 for v in y)
    r2 = 1 - sum((v - a - c * u) ** 2 for u, v in zip(x, y)) / ss if ss > 0 else math.nan
    # the marginal exponent: log-log slope over the upper half of the cases (a fixed cost bends the lower half),
    # of the distinct sizes, so that it spans two at least (1024² and the full frame hold the same sphere)
    sizes = sorted(set(x))
    top = sizes[max(min((len(sizes) - 1) // 2, len(sizes) - 2), 0)]
    pts = [(math.log(u), math.log(v)) for u, v in zip(x, y) if u >= top and u > 0 and v > 0]
    lx = sum(p[0] for p in pts) / max(len(pts), 1)
    sxx_l = sum((p[0] - lx) ** 2 for p in pts)
    ly = sum(p[1] for p in pts) / max(len(pts), 1)
    exponent = sum((p[0] - lx) * (p[1] - ly) for p in pts) / sxx_l if len(pts) >= 2 and sxx_l > 0 else math.nan
    return a, c, r2, exponent


def fit_lines(name: str, cases: list[dict]) -> list[str]:
    done = [c for c in cases if "failed" not in c]
    if len(done) < 2:
        return [f"{name}: fewer than 2 cases measured, no fit"]
    x = [c["mask_px"] * c["lights"] for c in done]
    lines = [f"**Fit over the {name} sweep** (t = a + c · pixels·lights, {len(done)} cases):", "",
             "| stage | c (µs per px·light) | a (s) | R² | exponent |", "|---|---:|---:|---:|---:|"]
    for stage in (*COLUMNS, "total"):
        y = [c["total"] if stage == "total" else c["stages"][stage] for c in done]
        a, c, r2, exponent = linear_fit(x, y)
        bold = "**" if stage == "total" else ""
        lines.append(f"| {bold}{stage}{bold} | {c * 1e6:.3f} | {a:.2f} | {r2:.3f} | {exponent:.2f} |")
    a, c, r2, exponent = linear_fit(x, [c["total"] for c in done])
    verdict = "linear (plus a fixed cost)" if r2 >= 0.98 and 0.8 <= exponent <= 1.2 else "NOT linear"
    lines += ["", f"{name}: total {verdict} in pixels × lights (R² {r2:.3f}, exponent {exponent:.2f}; "
              f"exponent over the larger half of the cases; linear = R² ≥ 0.98 and exponent 0.8–1.2); constant {c * 1e6:.3f} µs per pixel·light, fixed cost {a:.1f} s"]
    return lines


def machine_line() -> str:
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    return (f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
            f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')} (torch threads {torch.get_num_threads()}), "
            f"cuda: {gpu}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="*", default=["128", "256", "512", "1024", "full"],
                        help="pixel sweep: N (N×N super-pixels) or 'full' (1224×1024)")
    parser.add_argument("--lights", nargs="*", type=int, default=[4, 8, 12, 24, 48], help="light sweep: light counts")
    parser.add_argument("--size-lights", type=int, default=12, help="lights of the pixel sweep")
    parser.add_argument("--light-size", type=int, default=256, help="N×N super-pixels of the light sweep")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="cpu")
    parser.add_argument("--model", choices=["auto", "fmbrdf", "lambertian"], default=None,
                        help="recovery.model (default: the configuration default, auto)")
    parser.add_argument("--max-outer-iterations", type=int, default=None, help="recovery.max_outer_iterations")
    parser.add_argument("--work", type=Path, default=None, help="captures and results (default: a temporary folder)")
    parser.add_argument("--md", type=Path, default=None, help="also write the tables to this Markdown file")
    parser.add_argument("--reuse", action="store_true", help="keep results of cases already measured in --work")
    parser.add_argument("--render-only", action="store_true", help="render the captures of the sweeps and stop")
    parser.add_argument("--case", help="run one case in this process: full-frame, N or N@L (e.g. 256@48)")
    parser.add_argument("--json", type=Path, help=argparse.SUPPRESS)  # where --case writes its result
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        work = (args.work or Path(tmp)).absolute()
        work.mkdir(parents=True, exist_ok=True)
        if args.case:
            width, height, lights = parse_case(args.case)
            capture = capture_folder(work, width, height, lights)
            if not (capture / "capture.yaml").exists():
                print("note: rendering the capture first; /usr/bin/time -v then also sees the render's memory "
                      "(run --render-only first)", file=sys.stderr)
                capture = render(work, width, height, lights, args.device)
            case = run_case(capture, work / f"run_{args.device}_{case_name(width, height, lights)}", args.device,
                            args.model, args.max_outer_iterations)
            if args.json:
                args.json.write_text(json.dumps(case))
            print(machine_line())
            print("\n".join([*header(), row(case)]))
            return
        size_cases = [(*parse_case(s)[:2], args.size_lights) for s in args.sizes]
        light_cases = [(args.light_size, args.light_size, n) for n in args.lights]
        if args.render_only:
            for width, height, lights in dict.fromkeys(size_cases + light_cases):
                render(work, width, height, lights, args.device)
            return
        out = [machine_line(), ""]
        print(out[0], flush=True)
        for name, cases in (("pixels", size_cases), ("lights", light_cases)):
            if not cases:
                continue
            lines = [f"**Against {name}** ({'%d lights' % args.size_lights if name == 'pixels' else f'{args.light_size}² super-pixels'}):",
                     "", *header()]
            print("\n".join(lines), flush=True)
            measured = []
            for width, height, lights in cases:
                measured.append(measure(args, work, width, height, lights))
                lines.append(row(measured[-1]))
                print(lines[-1], flush=True)
            fit = fit_lines(name, measured)
            print("\n" + "\n".join(fit) + "\n", flush=True)
            out += [*lines, "", *fit, ""]
        if args.md:
            args.md.write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
