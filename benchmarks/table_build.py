"""Cost of the fast evaluator's table build at κ = 0, as a material fit makes them (issue 13).

A Levenberg–Marquardt step of :func:`polarshape.recover.reflectometry.fit_reflectance` builds the tables
(:func:`polarshape.brdf.build_tables`) for forward differences on a frozen layout and for a trial point
on its own layout. Three kinds of build, timed per α (β = 2, κ = 0), each with fresh values every call:

- ``trial``: a new point — new μ, α, β, and the layout of that point (every cache misses);
- ``mu``: a new μ on a frozen layout (the μ difference: the facet side changes, its geometry does not);
- ``ab``: a new α or β on a frozen layout at a fixed μ (the α, β differences).

Reports the median time per build (ms) of ``--repeats`` rounds of ``--builds`` builds: process CPU time
(what a loaded, shared box distorts least) and, in brackets, wall-clock time. Before/after: run
the same script with PYTHONPATH pointing at each checkout, alternating, and compare the medians;
``--save FILE`` stores every table built (values, Smith table, c) and ``--compare A B`` reports the
largest differences of two saved runs, relative to each table's scale (and elementwise).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/table_build.py [--alphas 0.03 0.1 0.3 0.8] [--builds 20]
        [--repeats 3] [--n-grid 65] [--device cpu] [--grad] [--save FILE]
    python benchmarks/table_build.py --compare before.pt after.pt
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import polarshape
from polarshape.brdf import build_tables
from polarshape.brdf.body_fast import clear_facet_cache

try:
    from polarshape.brdf.smith import clear_smith_cache
except ImportError:  # a checkout before the Smith table's layout cache
    def clear_smith_cache() -> int:
        return 0


def _values(kind: str, alpha: float, i: int) -> tuple[dict[str, float], tuple[float, float, float]]:
    """The parameters and layout of the i-th build of one kind (all distinct, near μ 1.5, α, β 2)."""
    mu = 1.5 + 1e-3 * i
    if kind == "trial":
        a, b = alpha * (1.0 + 1e-3 * i), 2.0 + 1e-3 * i
        return dict(ior=mu, alpha=a, beta=b, kappa=0.0), (a, b, 0.0)
    if kind == "mu":
        return dict(ior=mu, alpha=alpha, beta=2.0, kappa=0.0), (alpha, 2.0, 0.0)
    if i % 2:
        return dict(ior=1.5, alpha=alpha * (1.0 + 1e-3 * i), beta=2.0, kappa=0.0), (alpha, 2.0, 0.0)
    return dict(ior=1.5, alpha=alpha, beta=2.0 + 1e-3 * i, kappa=0.0), (alpha, 2.0, 0.0)


def run(alphas: list[float], builds: int, repeats: int, n_grid: int, device: str, grad: bool,
        save: str | None) -> None:
    torch.manual_seed(0)
    kinds = ("trial", "mu", "ab")
    print(f"polarshape {polarshape.__file__}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"device {device}, n_grid {n_grid}, grad {grad}")
    print("| α | " + " | ".join(f"{k}: CPU (wall) ms" for k in kinds) + " |")
    print("|---:|" + "---:|" * len(kinds))
    saved: dict[str, dict[str, torch.Tensor]] = {}
    for alpha in alphas:
        clear_facet_cache()
        clear_smith_cache()
        row = []
        for kind in kinds:
            times = []
            for rep in range(repeats + 1):  # the first round warms up (and fills the caches once)
                t0, c0 = time.perf_counter(), time.process_time()
                for i in range(builds):
                    vals, layout = _values(kind, alpha, rep * builds + i)
                    if grad:
                        mu = torch.tensor(vals.pop("ior"), dtype=torch.float64, requires_grad=True)
                        tab = build_tables(ior=mu, **vals, device=device, n_grid=n_grid, layout=layout)
                        (tab.body.values.sum() + tab.smith.excess.sum()).backward()
                    else:
                        tab = build_tables(**vals, device=device, n_grid=n_grid, layout=layout)
                    if save and rep == repeats:
                        saved[f"{alpha}/{kind}/{i}"] = {
                            "body": tab.body.values.detach().cpu(), "smith": tab.smith.excess.detach().cpu(),
                            "c": tab.c.detach().cpu(), **({"grad": mu.grad.cpu()} if grad else {}),
                        }
                if torch.cuda.is_available() and device != "cpu":
                    torch.cuda.synchronize()
                if rep:
                    times.append(((time.process_time() - c0) / builds, (time.perf_counter() - t0) / builds))
            row.append((statistics.median(t[0] for t in times), statistics.median(t[1] for t in times)))
        print(f"| {alpha} | " + " | ".join(f"{1e3 * c:.2f} ({1e3 * w:.2f})" for c, w in row) + " |", flush=True)
    if save:
        torch.save(saved, save)
        print(f"saved {len(saved)} table sets to {save}")


def compare(a_path: str, b_path: str) -> None:
    """Largest difference of each part over all saved builds: relative to the largest |value| of that
    part in that build, and elementwise relative (over elements above 1e-9 of that scale)."""
    a, b = torch.load(a_path), torch.load(b_path)
    assert a.keys() == b.keys(), "the two runs built different tables"
    worst: dict[str, list[float]] = {}
    for key in a:
        for part, x in a[key].items():
            y = b[key][part]
            if part == "body":  # (log W0, WQ/W0, WU/W0): each channel on its own scale
                pieces = [(f"body ch{c}", x[..., c], y[..., c]) for c in range(x.shape[-1])]
            else:
                pieces = [(part, x, y)]
            for name, u, v in pieces:
                scale = float(u.abs().max().clamp_min(1e-300))
                d = (u - v).abs()
                big = u.abs() > 1e-9 * scale
                elem = float((d[big] / u.abs()[big]).max()) if bool(big.any()) else 0.0
                w = worst.setdefault(name, [0.0, 0.0, 0])
                w[0], w[1], w[2] = max(w[0], float(d.max()) / scale), max(w[1], elem), w[2] + int(torch.equal(u, v))
    n = len(a)
    print(f"{n} table sets compared")
    print("| part | max |Δ| / scale | max elementwise rel | bitwise equal |")
    print("|---|---:|---:|---:|")
    for name, (rel, elem, eq) in worst.items():
        print(f"| {name} | {rel:.2e} | {elem:.2e} | {eq}/{n} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.03, 0.1, 0.3, 0.8])
    ap.add_argument("--builds", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--n-grid", type=int, default=65)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grad", action="store_true", help="μ requires grad; time the build and its backward")
    ap.add_argument("--save", default=None)
    ap.add_argument("--compare", nargs=2, default=None)
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    run(args.alphas, args.builds, args.repeats, args.n_grid, args.device, args.grad, args.save)


if __name__ == "__main__":
    main()
