"""Time and accuracy of normal integration (smooth and bilateral) on sphere masks.

Scene: the front of a sphere seen by an orthographic camera, N×N pixels, circular mask of radius
0.42·N (the cap reaches ≈ 69° from the view axis), exact analytic normals. The depth error is the
RMSE after the best additive offset, in % of the true depth range. Optionally (``--occlusion``) the
occluding-boundary case of the tests (a spherical cap in front of a tilted plane) at each size, where
the bilateral method's advantage shows, and (``--solvers``) every linear solver for the smooth method.

Usage:
    python benchmarks/integration.py [--sizes 256 512 1024] [--solvers] [--occlusion] [--max-iter 100]

Prints a markdown table. BLAS threads oversubscribe a busy 2-core machine (pyamg slows down 3–10×):
run with OMP_NUM_THREADS=1 there.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from polarshape.cameras import OrthographicCamera
from polarshape.surface.integrate import IntegrationReport, integrate_normals


def sphere(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(normals (N, N, 3), mask (N, N), true depth (N, N), pixel size): a 1 m wide image."""
    pixel = 1.0 / size
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    x, y = (uu - (size - 1) / 2) * pixel, (vv - (size - 1) / 2) * pixel
    radius = 0.45
    mask = x**2 + y**2 < 0.42**2
    z = 2.0 - np.sqrt(np.maximum(radius**2 - x**2 - y**2, 0.0))
    n = np.stack([x, y, z - 2.0], axis=-1) / radius
    n[~mask] = np.nan
    return n, mask, z, pixel


def occlusion(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Spherical cap (to 60°) in front of a tilted plane touching its left edge (pixel units)."""
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    radius, c, slope = 0.3 * size, (size - 1) / 2, 0.5
    r2 = (uu - c) ** 2 + (vv - c) ** 2
    cap_r = radius * np.sin(np.radians(60))
    cap = r2 < cap_r**2
    z_cap = 2.0 * size - np.sqrt(np.maximum(radius**2 - r2, 0.0))
    rim = 2.0 * size - radius * np.cos(np.radians(60))
    z = np.where(cap, z_cap, rim + slope * (uu - (c - cap_r)))
    n_cap = np.stack([uu - c, vv - c, z_cap - 2.0 * size], axis=-1) / radius
    plane = np.array([slope, 0.0, -1.0]) / np.hypot(slope, 1.0)
    n = np.where(cap[..., None], n_cap, plane)
    return n, np.ones((size, size), bool), z, 1.0


def rmse_percent(depth: np.ndarray, true: np.ndarray, mask: np.ndarray) -> float:
    e = depth[mask] - true[mask]
    e -= e.mean()
    return 100.0 * float(np.sqrt(np.mean(e**2)) / np.ptp(true[mask]))


def run(case: str, size: int, method: str, solver: str, max_iter: int) -> str:
    n, mask, z, pixel = sphere(size) if case == "sphere" else occlusion(size)
    report = IntegrationReport()
    t0 = time.perf_counter()
    camera = OrthographicCamera(size, size, pixel, even=False)
    depth = integrate_normals(n, mask, camera=camera, method=method, solver=solver, max_iter=max_iter, report=report)
    seconds = time.perf_counter() - t0
    err = rmse_percent(depth, z, mask)
    return (
        f"| {case} | {size}² | {report.pixels} | {method} | {report.solver} | {seconds:.2f} | "
        f"{report.iterations} | {report.cg_steps} | {err:.4f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--solvers", action="store_true", help="also time every linear solver (smooth method)")
    parser.add_argument("--occlusion", action="store_true", help="also run the occluding-boundary case")
    parser.add_argument("--max-iter", type=int, default=100, help="bilateral iteration cap")
    args = parser.parse_args()

    print(f"machine: {platform.processor() or platform.machine()}, numpy {np.__version__}")
    print()
    print("| case | size | pixels | method | solver | time (s) | iterations | CG steps | RMSE (% of range) |")
    print("|---|---|---|---|---|---|---|---|---|")
    cases = ["sphere"] + (["occlusion"] if args.occlusion else [])
    for case in cases:
        for size in args.sizes:
            solvers = ["auto"]
            if args.solvers and case == "sphere":
                solvers = ["direct", "cg", "amg"]
            for solver in solvers:
                print(run(case, size, "smooth", solver, args.max_iter), flush=True)
            print(run(case, size, "bilateral", "auto", args.max_iter), flush=True)


if __name__ == "__main__":
    main()
