"""Issue 13: the joint solve against the alternation, in the same run, with its convergence table.

    python benchmarks/joint_solve.py --size 40             # 40² super-pixels, all cases
    python benchmarks/joint_solve.py --size 64 --alphas 0.1 0.3 --kappas 0 --kinds sphere
    python benchmarks/joint_solve.py --size 40 --kinds sphere --alphas 0.03 --kappas 0 --solvers joint --trace

Captures: the tests' simulated scenes (``tests/test_normals.py::_simulate``: ``sphere`` —
orthographic camera; ``blob`` — perspective pinhole), 12-bit with shot and read noise, 12 lights,
the material's α and κ as given (μ 1.5, β 2, k_b 0.5), exposure 1 ms for α < 0.1 (the shiny lobe
would saturate at the scenes' 10 ms). Each capture is recovered end to end (``recover_capture``,
model fmbrdf, κ decided by the recovery) with ``recovery.solver`` ``alternating`` then ``joint``.

Columns: case; for ``joint``: the κ = 0 solve's iterations on the coarsest level, its final relative
loss change and whether it is below 1e-5 (``conv``), the nested κ test's iterations (it stops at 1e-3:
a test, not a fit) and, where κ gained enough to be polished, the polish's iterations, relative change
and convergence (``p_*``); for ``alternating``: its outer iterations; the seconds of each solver
(whole recovery) and their ratio; |α − α_true|/α_true, |μ − μ_true|, |β − β_true| and κ found; the
mean normal error (degrees) over mask pixels lit by ≥ K − 3 lights. Times are of this machine (printed).
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


def _solves(result: object, solver: str) -> list[list[dict]]:
    """The recovery's joint solves of one kind (``joint``: the κ = 0 solve; ``joint_kappa``: the nested κ
    test, then its polish when κ gained), each as its history rows (a solve restarts at iteration 1)."""
    out: list[list[dict]] = []
    for h in result.history:
        if h.get("solver") == solver:
            if h.get("iteration") == 1 or not out:
                out.append([])
            out[-1].append(h)
    return out


def _convergence(rows: list[dict]) -> tuple[int, float]:
    """Iterations and the last relative loss change of one solve ((0, nan) when there is none)."""
    return (len(rows), float(rows[-1].get("rel_change", float("nan")))) if rows else (0, float("nan"))


def _trace(result: object) -> None:
    """Every joint iteration: loss, relative change, λ, damping tries and their gain ratios ρ, the share of
    pixels that kept their normal step, highlight jumps, globals held at a bound, the globals' step."""
    for stage in ("joint", "joint_kappa"):
        for rows in _solves(result, stage):
            for h in rows:
                step = " ".join(f"{v:+.2e}" for v in h.get("step", []))
                rho = ",".join("-" if r is None else f"{r:.2f}" for r in h.get("rho", []))
                print(f"    {stage:<11} {h['iteration']:>3} loss {h['loss']:.6e} rel {h['rel_change']:.1e} "
                      f"λ {h.get('lambda', float('nan')):.1e} tries {h.get('attempts', '?')} ρ [{rho}] "
                      f"moved {h.get('moved', float('nan')):.2f} jumped {h.get('jumped', '?')} "
                      f"pinned {h.get('pinned', [])} step [{step}] α {h.get('alpha', 0):.4g} "
                      f"β {h.get('beta', 0):.3g} μ {h.get('ior', 0):.4g} κ {h.get('kappa', 0):.3g}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--alphas", type=float, nargs="+", default=[0.03, 0.1, 0.3, 0.8])
    parser.add_argument("--kappas", type=float, nargs="+", default=[0.0, 50.0])
    parser.add_argument("--kinds", nargs="+", default=["sphere", "blob"])
    parser.add_argument("--solvers", nargs="+", default=["alternating", "joint"])
    parser.add_argument("--trace", action="store_true", help="print every joint iteration (loss, λ, steps)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    print(f"machine: {platform.machine()} {platform.processor() or ''}, torch threads 1; size {args.size}², "
          "the scenes' 12 lights")
    head = (f"{'case':<28} {'solver':<11} {'iters':>5} {'rel_chg':>8} {'conv':>4} {'κ test':>6} {'polish':>6} "
            f"{'p_rel':>8} {'p_conv':>6} {'time_s':>7} {'ratio':>6} "
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
                    base = seconds if base is None else base
                    if solver == "joint":
                        # the κ = 0 solve (to 1e-5), the nested κ test (to 1e-3) and its polish (to 1e-5)
                        iters, rel = _convergence((_solves(result, "joint") or [[]])[0])
                        kappa_solves = _solves(result, "joint_kappa")
                        k_iters = len(kappa_solves[0]) if kappa_solves else 0
                        p_iters, p_rel = _convergence(kappa_solves[1] if len(kappa_solves) > 1 else [])
                    else:
                        iters = sum(1 for h in result.history if str(h.get("stage", "")).startswith("level")
                                    and h.get("lm_iterations") is not None and h.get("solver") is None)
                        rel, k_iters, p_iters, p_rel = float("nan"), 0, 0, float("nan")
                    conv = "yes" if rel < 1e-5 else ("-" if rel != rel else "no")
                    p_conv = "yes" if p_rel < 1e-5 else ("-" if p_rel != p_rel else "no")
                    p_col = f"{p_iters:>6}" if p_iters else f"{'-':>6}"
                    print(f"{case:<28} {solver:<11} {iters:>5} {rel:>8.1e} {conv:>4} {k_iters:>6} {p_col} "
                          f"{p_rel:>8.1e} {p_conv:>6} {seconds:>7.1f} "
                          f"{seconds / base:>6.2f} {abs(p['alpha'] - alpha) / alpha:>7.3f} {abs(p['ior'] - 1.5):>7.3f} "
                          f"{abs(p['beta'] - 2.0):>6.2f} {p['kappa']:>6.1f} {err:>6.2f}", flush=True)
                    if args.trace and solver == "joint":
                        _trace(result)

if __name__ == "__main__":
    main()
