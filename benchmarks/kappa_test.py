"""Issue 13: the κ test's cost per decision — table builds, joint-solve iterations, CPU seconds — replayed
from saved inputs, so that two checkouts decide on exactly the same κ = 0 optimum.

    # 1. save the κ test's inputs of grid cases (each run stops at its κ test; any checkout)
    python benchmarks/kappa_test.py save /tmp/grid/capture_a0.8_k50_orthographic_256@13 ... --out DIR
    # 2. replay them on a checkout (PYTHONPATH=<checkout>), then compare two checkouts' JSON
    PYTHONPATH=<main> python benchmarks/kappa_test.py replay DIR/*.pt --json main.json
    PYTHONPATH=<branch> python benchmarks/kappa_test.py replay DIR/*.pt --json branch.json --compare main.json

``save`` runs a capture of ``benchmarks/material_grid.py`` the way that benchmark does
(:func:`benchmarks.scaling.run_case`) and, at the alternation's κ decision
(``polarshape.recover.coarse_to_fine._decide_kappa``), writes its arguments (the subsample's normals and
observations, the κ = 0 optimum, the start of the first outer iteration, δ, the options it reads) to
``DIR/<case>.pt`` and ends the process (cases whose alternation never reaches the test write nothing).
``replay`` calls ``_decide_kappa`` on each and prints: κ kept, κ and α found, table builds
(``polarshape.recover.joint_solve.build_tables`` calls, by body grid and κ > 0), the joint solves'
iterations, wall and CPU seconds; ``--compare`` adds another replay's builds and CPU seconds and whether the
result (decision, κ, α, skip message, subsample normals) is identical.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def save(captures: list[Path], out: Path) -> None:
    """Save each capture's κ-test inputs to ``out/<case>.pt`` (one subprocess per capture)."""
    import subprocess

    out.mkdir(parents=True, exist_ok=True)
    for capture in captures:
        target = out / (capture.name.removeprefix("capture_") + ".pt")
        subprocess.run([sys.executable, __file__, "_save_one", str(capture), str(target)], check=True)
        print(("saved " if target.exists() else "no κ test: ") + str(target), flush=True)


def _save_one(capture: Path, target: Path) -> None:
    import tempfile

    import polarshape.recover.coarse_to_fine as c2f
    from scaling import run_case

    def hook(lv, sub_idx, start, options, polarised, *, level, log):  # noqa: ANN001, ANN202, ARG001
        torch.save({"n_sub": lv.n[sub_idx].clone(), "obs_sub": dataclasses.asdict(lv.obs.select(sub_idx)),
                    "params": dataclasses.asdict(lv.params), "delta": lv.delta, "start_n": start[0],
                    "start_params": dataclasses.asdict(start[1]), "per_pixel_albedo": options.per_pixel_albedo,
                    "max_outer": options.max_outer_iterations, "polarised": polarised, "level": level}, target)
        os._exit(0)  # the rest of the run is not needed

    c2f._decide_kappa = hook
    with tempfile.TemporaryDirectory() as tmp:
        run_case(capture, Path(tmp), "cpu", None, None)


def replay(inputs: list[Path]) -> dict[str, dict]:
    """``_decide_kappa`` on each saved input: its decision, material, builds, iterations and seconds."""
    import polarshape.recover.coarse_to_fine as c2f
    import polarshape.recover.joint_solve as js
    from polarshape.brdf.params import FMBRDFParams
    from polarshape.recover.observations import Observations
    from polarshape.recover.options import RecoveryOptions

    builds: collections.Counter[str] = collections.Counter()
    build_tables, joint_solve = js.build_tables, js.joint_solve
    iterations: list[int] = []

    def counted_build(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        builds[f"{kwargs.get('n_grid')}{'k' if kwargs.get('kappa', 0.0) > 0 else ''}"] += 1
        return build_tables(*args, **kwargs)

    def counted_solve(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        fit = joint_solve(*args, **kwargs)
        iterations.append(fit.iterations)
        return fit

    js.build_tables, js.joint_solve, c2f.joint_solve = counted_build, counted_solve, counted_solve
    out = {}
    for path in inputs:
        d = torch.load(path, weights_only=False)
        obs = Observations(**d["obs_sub"])
        p = obs.num_pixels
        n = d["n_sub"].clone()
        lv = c2f._Level(torch.ones(p, dtype=torch.bool), obs, n, torch.zeros(p, dtype=n.dtype),
                        FMBRDFParams(**d["params"]), d["delta"], None)
        options = RecoveryOptions(per_pixel_albedo=d["per_pixel_albedo"], max_outer_iterations=d["max_outer"])
        log = c2f.SolveLog()
        builds.clear()
        iterations.clear()
        t0, c0 = time.perf_counter(), time.process_time()
        kept = c2f._decide_kappa(lv, torch.arange(p), (d["start_n"], FMBRDFParams(**d["start_params"])), options,
                                 d["polarised"], level=d["level"], log=log)
        row = {"kept": kept, "kappa": lv.params.kappa, "alpha": lv.params.alpha, "wall_s": time.perf_counter() - t0,
               "cpu_s": time.process_time() - c0, "builds": sum(builds.values()), "by_grid": dict(builds),
               "iterations": iterations[1:], "skipped": log.skipped, "normals_sum": float(lv.n.double().sum())}
        out[path.stem] = row
        print(f"{path.stem:32s} kept {kept!s:5} κ {row['kappa']:.2f} α {row['alpha']:.4f} builds {row['builds']:3d} "
              f"{row['by_grid']} iterations {'+'.join(map(str, row['iterations']))} wall {row['wall_s']:.2f} s "
              f"CPU {row['cpu_s']:.2f} s", flush=True)
    return out


def compare(new: dict[str, dict], old: dict[str, dict]) -> None:
    """Markdown: each case's builds and CPU seconds old → new and whether the result is identical."""
    print("\n| case | κ kept | builds | iterations | CPU (s) | κ found | α found | result |")
    print("|---|---|---:|---|---:|---:|---:|---|")
    for name, b in new.items():
        a = old.get(name)
        if a is None:
            continue
        keys = ("kept", "kappa", "alpha", "skipped")
        same = "identical" if all(a[k] == b[k] for k in (*keys, "normals_sum")) else (
            "same κ, α, message" if all(a[k] == b[k] if k != "kappa" else round(a[k], 2) == round(b[k], 2)
                                        for k in keys) else "**differs**")
        its = ["+".join(map(str, r["iterations"])) for r in (a, b)]
        print(f"| {name} | {'yes' if b['kept'] else 'no'} | {a['builds']} → {b['builds']} | {its[0]} → {its[1]} | "
              f"{a['cpu_s']:.2f} → {b['cpu_s']:.2f} | {b['kappa']:.2f} | {b['alpha']:.4f} | {same} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("save")
    s.add_argument("captures", type=Path, nargs="+")
    s.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("replay")
    r.add_argument("inputs", type=Path, nargs="+")
    r.add_argument("--json", type=Path)
    r.add_argument("--compare", type=Path, help="another replay's --json: builds and CPU s side by side")
    one = sub.add_parser("_save_one")
    one.add_argument("capture", type=Path)
    one.add_argument("target", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    if args.command == "save":
        save(args.captures, args.out)
    elif args.command == "_save_one":
        _save_one(args.capture, args.target)
    else:
        out = replay(args.inputs)
        if args.json:
            args.json.write_text(json.dumps(out, indent=1))
        if args.compare:
            compare(out, json.loads(args.compare.read_text()))


if __name__ == "__main__":
    main()
