"""Benchmark of the FMBRDF forward model (issue 2).

Reports, in one run on this machine:
1. throughput of ``fmbrdf_stokes`` (fast evaluator) in pixel-light evaluations per second, forward
   and forward+backward (w.r.t. normals and k_b), for 1e5 and 1e6 evaluations with one material,
   against the paper's MLP surrogate cost (~8 µs per pixel-light forward on 2 CPU threads);
2. the cost of switching material: table build time (with and without autograd), per κ regime;
3. the error distribution of the fast evaluator against the exact reference over random samples
   of the full parameter box (α 0.01–2, β 0.5–4, μ 1.2–2.0, κ 0–100) and geometries incl. grazing.

Usage:  python benchmarks/brdf_eval.py [--device cpu|cuda] [--threads 2] [--n-error 24] [--quick]
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "brdf"))
from brdf_helpers import random_geometry  # noqa: E402

from polarshape.brdf import build_tables, fmbrdf_stokes  # noqa: E402
from polarshape.imaging.stokes import dolp  # noqa: E402

MLP_US_PER_EVAL = 8.0  # paper's networks, 2 CPU threads (issue 2)


def timed(fn, repeats: int = 3) -> float:
    fn()  # warm-up
    best = math.inf
    for _ in range(repeats):
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def throughput(device: str, dtype: torch.dtype) -> list[tuple]:
    rows = []
    rng = np.random.default_rng(0)
    mat = dict(ior=1.5, alpha=0.3, beta=2.0, kappa=30.0)
    tables = build_tables(**mat, device=device)
    for n in (100_000, 1_000_000):
        nrm, l, v = (x.to(device=device, dtype=dtype) for x in random_geometry(rng, n))
        kb = torch.full((n,), 0.5, device=device, dtype=dtype)

        def fwd():
            with torch.no_grad():
                fmbrdf_stokes(nrm, l, v, k_s=1.0, k_b=kb, **mat, tables=tables)

        def fwd_bwd():
            nn_ = nrm.clone().requires_grad_(True)
            kb_ = kb.clone().requires_grad_(True)
            fmbrdf_stokes(nn_, l, v, k_s=1.0, k_b=kb_, **mat, tables=tables).sum().backward()

        for name, fn in (("forward", fwd), ("forward+backward", fwd_bwd)):
            t = timed(fn)
            rows.append((name, n, str(dtype).replace("torch.", ""), t, n / t, MLP_US_PER_EVAL * 1e-6 * n / t))
    return rows


def build_costs(device: str) -> list[tuple]:
    rows = []
    for label, mat in (
        ("κ = 0 (separable)", dict(ior=1.5, alpha=0.3, beta=2.0, kappa=0.0)),
        ("κ = 20", dict(ior=1.5, alpha=0.3, beta=2.0, kappa=20.0)),
        ("κ = 100, α = 0.3", dict(ior=1.5, alpha=0.3, beta=2.0, kappa=100.0)),
        ("κ = 100, α = 1.5", dict(ior=1.5, alpha=1.5, beta=2.0, kappa=100.0)),
    ):
        t_plain = timed(lambda: build_tables(**mat, device=device), repeats=2)

        def with_grad():
            p = {k: torch.tensor(x, dtype=torch.float64, device=device, requires_grad=True) for k, x in mat.items()}
            t = build_tables(**p)
            (t.body.values.sum() + t.smith.excess.sum()).backward()

        t_grad = timed(with_grad, repeats=1)
        rows.append((label, t_plain, t_grad))
    return rows


def errors(n_materials: int, seed: int = 1) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    rels, dds, t_exact = [], [], 0.0
    count = 0
    for i in range(n_materials):
        mu = float(rng.uniform(1.2, 2.0))
        a = float(np.exp(rng.uniform(np.log(0.01), np.log(2.0))))
        b = float(rng.uniform(0.5, 4.0))
        k = 0.0 if i % 3 == 0 else float(rng.uniform(0.0, 100.0))
        p = dict(ior=mu, k_s=1.0, k_b=float(rng.uniform(0.1, 1.0)), alpha=a, beta=b, kappa=k)
        t = build_tables(ior=mu, alpha=a, beta=b, kappa=k)
        n_all, l_all, v_all = random_geometry(rng, 20000)
        peak = float(fmbrdf_stokes(n_all, l_all, v_all, **p, tables=t)[:, 0].max())
        n, l, v = random_geometry(rng, 4, max_deg=89.9)
        fast = fmbrdf_stokes(n, l, v, **p, tables=t)
        t0 = time.perf_counter()
        ex = fmbrdf_stokes(n, l, v, **p, exact=True)
        t_exact += time.perf_counter() - t0
        count += 4
        keep = ex[:, 0] > 1e-4 * peak
        rels.append(((fast[:, 0] - ex[:, 0]) / ex[:, 0]).abs()[keep])
        dds.append((dolp(fast, dim=-1, eps=0.0) - dolp(ex, dim=-1, eps=0.0)).abs()[keep])
    rel, dd = torch.cat(rels).numpy(), torch.cat(dds).numpy()
    return {
        "n": len(rel),
        "s0_median": float(np.median(rel)),
        "s0_p95": float(np.percentile(rel, 95)),
        "s0_max": float(rel.max()),
        "dolp_median": float(np.median(dd)),
        "dolp_max": float(dd.max()),
        "exact_s_per_eval": t_exact / count,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--n-error", type=int, default=24, help="materials in the error sample (4 geometries each)")
    ap.add_argument("--quick", action="store_true", help="skip the error sample")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dev = args.device
    name = torch.cuda.get_device_name() if dev.startswith("cuda") else platform.processor() or platform.machine()
    print(f"# FMBRDF forward-model benchmark — device {dev} ({name}), torch {torch.__version__}, {torch.get_num_threads()} threads\n")
    print("| pass | evaluations | dtype | time (s) | evals/s | speed-up vs MLP (8 µs/eval) |")
    print("|---|---:|---|---:|---:|---:|")
    for dtype in (torch.float32, torch.float64):
        for name_, n, dt, t, rate, ratio in throughput(dev, dtype):
            print(f"| {name_} | {n:,} | {dt} | {t:.3f} | {rate:,.0f} | {ratio:.1f}× |")
    print("\n| material switch (table build) | build (s) | build + backward (s) |")
    print("|---|---:|---:|")
    for label, t_plain, t_grad in build_costs(dev):
        print(f"| {label} | {t_plain:.3f} | {t_grad:.3f} |")
    if not args.quick:
        e = errors(args.n_error)
        print(f"\nFast vs exact ({e['n']} evaluations with s0 > 1e-4 of peak, {args.n_error} random materials, "
              f"exact reference {e['exact_s_per_eval']:.1f} s/eval):")
        print("| metric | median | 95th pct | max |")
        print("|---|---:|---:|---:|")
        print(f"| s0 relative error | {e['s0_median']:.1e} | {e['s0_p95']:.1e} | {e['s0_max']:.1e} |")
        print(f"| DoLP absolute error | {e['dolp_median']:.1e} | | {e['dolp_max']:.1e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
