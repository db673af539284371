"""The stages around the recovery of ``polarshape run`` at full frame: wall and CPU seconds each (issue 13).

Runs ``run_pipeline`` on a capture in this process, with the configuration of ``benchmarks/scaling.py``
(float32, ``validation.holdout: none``, ``report.enabled: false``; ``--model``), and prints per stage the wall
time (params.json ``timings_s``) and the CPU time of this process (``time.process_time``: on a box shared with
other jobs the wall time is mostly waiting, the CPU time much less so). Robust PS (the initial normals), the
material selection and the final FMBRDF render sit inside the ``recovery`` stage; they are timed on their own and
counted with the stages around the recovery: "around" = load + preprocess + robust PS + nearfield +
interreflection + validation + checks + integration + mesh + export + evaluation + report + materials selection
+ render (everything but the normal and material solve).

Usage:
    python benchmarks/scaling.py --render-only --sizes full --lights --work /tmp/ff   # the capture, once
    OMP_NUM_THREADS=1 python benchmarks/fullframe.py /tmp/ff/capture_1224x1024@12 --model lambertian
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

AROUND = ("input", "preprocess", "robust PS", "nearfield", "interreflection", "validation", "checks", "integration",
          "mesh", "export", "evaluation", "report", "materials selection", "render")


def _timed(name: str, cpu: dict[str, float], wall: dict[str, float], fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            cpu[name] = cpu.get(name, 0.0) + time.process_time() - c0
            wall[name] = wall.get(name, 0.0) + time.perf_counter() - w0
    return wrapper


def measure(capture: Path, model: str | None, out: Path) -> dict[str, Any]:
    """One ``run_pipeline`` of ``capture``: {"wall": {stage: s}, "cpu": {stage: s}, "params": params.json}."""
    import torch

    from polarshape import normals, pipeline
    from polarshape.config import parse_run_config
    from polarshape.recover import materials

    cpu: dict[str, float] = {}
    inner_wall: dict[str, float] = {}
    stage = pipeline._StageLog.stage

    @contextlib.contextmanager
    def cpu_stage(self: Any, name: str) -> Iterator[None]:
        c0 = time.process_time()
        with stage(self, name):
            yield
        cpu[name] = time.process_time() - c0

    patches = [(pipeline._StageLog, "stage", cpu_stage),
               (normals, "initial_normals", _timed("robust PS", cpu, inner_wall, normals.initial_normals)),
               (materials, "select_materials", _timed("materials selection", cpu, inner_wall,
                                                       materials.select_materials)),
               (normals, "_render_fmbrdf", _timed("render", cpu, inner_wall, normals._render_fmbrdf))]
    saved = [(obj, attr, getattr(obj, attr)) for obj, attr, _ in patches]
    for obj, attr, value in patches:
        setattr(obj, attr, value)
    try:
        recovery: dict[str, Any] = {} if model is None else {"model": model}
        config = parse_run_config({
            "format": "polarshape-run/1", "input": {"type": "capture", "path": str(capture.absolute())},
            "device": "cpu", "dtype": "float32", "progress": False, "recovery": recovery,
            "validation": {"holdout": "none"}, "report": {"enabled": False},
        }, "fullframe benchmark")
        params = pipeline.run_pipeline(config, out, overwrite=True).params
    finally:
        for obj, attr, value in saved:
            setattr(obj, attr, value)
    wall = {k: float(v) for k, v in params["timings_s"].items() if k != "total"}
    wall.update(inner_wall)
    for name in ("robust PS", "materials selection", "render"):  # inside the recovery stage
        wall["recovery"] -= wall.get(name, 0.0)
        cpu["recovery"] = cpu.get("recovery", 0.0) - cpu.get(name, 0.0)
    return {"wall": wall, "cpu": cpu, "params": params, "threads": torch.get_num_threads()}


def table(results: list[tuple[str, dict[str, Any]]]) -> str:
    """Markdown: one row per stage (wall / CPU seconds of each result), the sum of the stages around the recovery."""
    names = [s for s in (*AROUND[:3], "recovery", *AROUND[3:]) if any(s in r["wall"] for _, r in results)]
    lines = ["| stage | " + " | ".join(f"{label} wall | {label} CPU" for label, _ in results) + " |",
             "|---|" + "---:|---:|" * len(results)]
    for name in names:
        cells = " | ".join(f"{r['wall'].get(name, 0.0):.2f} | {r['cpu'].get(name, 0.0):.2f}" for _, r in results)
        lines.append(f"| {name} | {cells} |")
    around = " | ".join(f"**{sum(r['wall'].get(s, 0.0) for s in AROUND):.2f}** | "
                        f"**{sum(r['cpu'].get(s, 0.0) for s in AROUND):.2f}**" for _, r in results)
    lines.append(f"| **around the recovery** | {around} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("capture", type=Path, help="a capture folder (e.g. benchmarks/scaling.py --render-only's)")
    parser.add_argument("--model", choices=["auto", "fmbrdf", "lambertian"], default=None)
    parser.add_argument("--json", type=Path, help="also write the measurement here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(args.capture, args.model, Path(tmp) / "result")
    params = result.pop("params")
    result["mean_err_deg"] = params["metrics"].get("normals", {}).get("mean_deg")
    result["checks"] = params["checks"]
    result["mesh"] = {k: params["mesh"][k] for k in ("vertices", "faces")}
    if args.json:
        args.json.write_text(json.dumps(result, default=str))
    print(f"threads {result['threads']}, model {params['model']}, {params['capture']['mask_pixels']} px, "
          f"mean error {result['mean_err_deg']}")
    print(table([("", result)]))


if __name__ == "__main__":
    sys.exit(main())
