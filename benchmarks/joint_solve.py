"""Issue 13: the joint solve against the alternation, in the same run, with its convergence table.

    python benchmarks/joint_solve.py --size 40             # 40² super-pixels, all cases
    python benchmarks/joint_solve.py --size 64 --alphas 0.1 0.3 --kappas 0 --kinds sphere

Captures: the tests' simulated scenes (``tests/test_normals.py::_simulate``: ``sphere`` —
orthographic camera; ``blob`` — perspective pinhole), 12-bit with shot and read noise, 12 lights,
the material's α and κ as given (μ 1.5, β 2, k_b 0.5), exposure 1 ms for α < 0.1 (the shiny lobe
would saturate at the scenes' 10 ms). Each capture is recovered end to end (``recover_capture``,
model fmbrdf, κ decided by the recovery) with ``recovery.solver`` ``alternating`` then ``joint``.

Columns: case; the joint solve's iterations on the coarsest level, the final relative loss change
and whether it is below 1e-5 (``converged``); the seconds of each solver (whole recovery) and their
ratio; |α − α_true|/α_true, |μ − μ_true|, |β − β_true| and κ found; the mean normal error
(degrees) over mask pixels lit by ≥ K − 3 lights. Times are of this machine (printed).
"""

from __future__ import annotations

import argparse
import logging
import platform
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from test_normals import _errors, _recover, _simulate  # noqa: E402  (the tests' scenes)


def _run(capture: object, solver: str) -> tuple[object, float]:
    t0 = time.perf_counter()
    result = _recover(capture, solver=solver)
    return result, time.perf_counter() - t0


def _joint_convergence(result: object) -> tuple[int, float]:
    rows = [h for h in result.history if h.get("solver") == "joint"]
    kappa_rows = [h for h in result.history if h.get("solver") == "joint_kappa"]
    last = (kappa_rows or rows)[-1] if rows else {}
    return len(rows) + len(kappa_rows), float(last.get("rel_change", float("nan")))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.03, 0.1, 0.3, 0.8])
    parser.add_argument("--kappas", type=float, nargs="+", default=[0.0, 50.0])
    parser.add_argument("--kinds", nargs="+", default=["sphere", "blob"])
    parser.add_argument("--solvers", nargs="+", default=["alternating", "joint"])
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    print(f"machine: {platform.machine()} {platform.processor() or ''}, torch threads 1; size {args.size}², "
          "the scenes' 12 lights")
    head = (f"{'case':<28} {'solver':<11} {'iters':>5} {'rel_chg':>8} {'conv':>4} {'time_s':>7} {'ratio':>6} "
            f"{'dα/α':>7} {'dμ':>7} {'dβ':>6} {'κ':>6} {'err°':>6}")
    print(head)
    for kind in args.kinds:
        for kappa in args.kappas:
            for alpha in args.alphas:
                capture = _simulate(kind, args.size, alpha, kappa=kappa, exposure_us=1000.0 if alpha < 0.1 else None)
                case = f"{kind}{' (persp)' if kind == 'blob' else ' (ortho)'} α{alpha:g} κ{kappa:g}"
                base = None
                for solver in args.solvers:
                    result, seconds = _run(capture, solver)
                    err, _ = _errors(result, capture)
                    p = result.params
                    iters, rel = _joint_convergence(result) if solver == "joint" else (
                        sum(1 for h in result.history if str(h.get("stage", "")).startswith("level")
                            and h.get("lm_iterations") is not None and h.get("solver") is None), float("nan"))
                    base = seconds if base is None else base
                    conv = "yes" if rel < 1e-5 else ("-" if rel != rel else "no")
                    print(f"{case:<28} {solver:<11} {iters:>5} {rel:>8.1e} {conv:>4} {seconds:>7.1f} "
                          f"{seconds / base:>6.2f} {abs(p['alpha'] - alpha) / alpha:>7.3f} {abs(p['ior'] - 1.5):>7.3f} "
                          f"{abs(p['beta'] - 2.0):>6.2f} {p['kappa']:>6.1f} {err:>6.2f}", flush=True)


if __name__ == "__main__":
    main()
