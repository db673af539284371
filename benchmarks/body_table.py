"""Benchmark of the body-table build at κ > 0 (issue 13): this checkout against a reference one.

For each (κ, α) it times :func:`polarshape.brdf.body_fast.build_body_table` (float64, μ 1.5, β 2,
empty facet cache) of this checkout and of ``--ref`` (another checkout's ``body_fast.py``, loaded
beside it in the same process, runs alternated), without autograd and with ``requires_grad`` on κ
(build + backward of the table's sum), and a finite-difference build (α moved by 1e-4 on the frozen
layout of a build just before: the facet side comes from the cache, as in the fits' Jacobians), and
reports the ratios. Times are CPU seconds of this process
(``time.process_time``, one torch thread): on a shared box they move far less than wall time.
It also checks that both give the same table: the largest relative difference of ``values``
(|a − b| / max(|b|, 1) per element; the three channels are O(1)) and of the gradients of a fixed
random positive projection of ``values`` wrt μ, α, β, κ.

Usage:  python benchmarks/body_table.py [--ref /work/main] [--kappas 5 20 50 100]
                                        [--alphas 0.03 0.3 0.8] [--n-grid 65] [--repeats 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import math
import sys
import time
from pathlib import Path
from types import ModuleType

import torch

from polarshape.brdf import body_fast
from polarshape.brdf.distribution import d_normalisation

log = logging.getLogger("body_table")


def load_reference(checkout: Path) -> ModuleType:
    """``polarshape/brdf/body_fast.py`` of another checkout as a module of its own (its imports
    resolve to this checkout's other modules)."""
    spec = importlib.util.spec_from_file_location("body_fast_ref", checkout / "polarshape" / "brdf" / "body_fast.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _inputs(kappa: float, alpha: float, grad: bool) -> tuple[torch.Tensor, ...]:
    mu, a, b, k = (torch.tensor(v, dtype=torch.float64, requires_grad=grad) for v in (1.5, alpha, 2.0, kappa))
    return mu, a, b, k, d_normalisation(a, b)


def _build(module: ModuleType, kappa: float, alpha: float, n_grid: int, grad: str) -> torch.Tensor:
    """One build from an empty facet cache; grad: "none", "kappa" (κ requires grad, backward of the
    sum) or "all" (μ, α, β, κ require grad; returns their gradients of a fixed projection)."""
    module.clear_facet_cache()
    if grad == "fd":  # the cache filled by the build at the layout, then the timed one at α + 1e-4 α
        mu, a, b, k, c = _inputs(kappa, alpha, False)
        module.build_body_table(mu, a, b, k, c, n_grid=n_grid, layout=(alpha, 2.0, kappa))
        mu, a, b, k, c = _inputs(kappa, alpha * (1.0 + 1e-4), False)
        t0 = time.process_time()
        module.build_body_table(mu, a, b, k, c, n_grid=n_grid, layout=(alpha, 2.0, kappa))
        return torch.tensor(time.process_time() - t0)
    mu, a, b, k, c = _inputs(kappa, alpha, grad == "all")
    if grad == "kappa":
        k.requires_grad_(True)
    table = module.build_body_table(mu, a, b, k, c, n_grid=n_grid)
    if grad == "none":
        return table.values
    if grad == "kappa":
        table.values.sum().backward()
        return k.grad
    # positive weights: a signed projection's gradient cancels to ~1e-3 of its terms and reads their
    # rounding as a 1e-13..1e-12 relative change
    weights = torch.rand(table.values.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return torch.stack(torch.autograd.grad((table.values * weights).sum(), (mu, a, b, k)))


def _rel(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((x - ref).abs() / ref.abs().clamp_min(1.0)).max())


def _timed(fn, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", type=Path, default=Path("/work/main"), help="checkout to compare against")
    ap.add_argument("--kappas", type=float, nargs="+", default=[5.0, 20.0, 50.0, 100.0])
    ap.add_argument("--alphas", type=float, nargs="+", default=[0.03, 0.3, 0.8])
    ap.add_argument("--n-grid", type=int, default=65)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    ref = load_reference(args.ref)
    log.info("torch %s, 1 thread, CPU s, n_grid %d, best of %d; ref = %s",
             torch.__version__, args.n_grid, args.repeats, args.ref)
    log.info("| κ | α | modes | ref (s) | this (s) | ratio | ref +∂κ (s) | this +∂κ (s) | ratio | ref FD (s) | this FD (s) "
             "| ratio | Δvalues rel | Δgrad rel |")
    log.info("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for kappa in args.kappas:
        for alpha in args.alphas:
            n_modes = body_fast.n_fourier_modes(kappa, alpha, 2.0)
            times = {}
            for grad in ("none", "kappa", "fd"):
                t_ref = t_new = math.inf
                for _ in range(args.repeats):  # alternated: the box is shared
                    if grad == "fd":
                        t_ref = min(t_ref, float(_build(ref, kappa, alpha, args.n_grid, grad)))
                        t_new = min(t_new, float(_build(body_fast, kappa, alpha, args.n_grid, grad)))
                        continue
                    t_ref = min(t_ref, _timed(lambda: _build(ref, kappa, alpha, args.n_grid, grad), 1))
                    t_new = min(t_new, _timed(lambda: _build(body_fast, kappa, alpha, args.n_grid, grad), 1))
                times[grad] = (t_ref, t_new)
            new_values = _build(body_fast, kappa, alpha, args.n_grid, "none")
            dv = _rel(new_values, _build(ref, kappa, alpha, args.n_grid, "none"))
            g_ref = _build(ref, kappa, alpha, args.n_grid, "all")
            dg = float(((_build(body_fast, kappa, alpha, args.n_grid, "all") - g_ref).abs() / g_ref.abs()).max())
            (r0, n0), (r1, n1), (r2, n2) = times["none"], times["kappa"], times["fd"]
            log.info("| %g | %g | %d | %.3f | %.3f | %.2f | %.3f | %.3f | %.2f | %.3f | %.3f | %.2f | %.1e | %.1e |",
                     kappa, alpha, n_modes, r0, n0, r0 / n0, r1, n1, r1 / n1, r2, n2, r2 / n2, dv, dg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
