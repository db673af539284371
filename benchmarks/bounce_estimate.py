"""The one-bounce estimate of a concave surface on its own: seconds, and how far it moved (issue 13).

``polarshape.surface.interreflection.estimate_one_bounce`` on an analytic crater (the shape of
configs/scenes/crater.yaml: a plate with a dish 8 mm across and 4 mm deep, orthographic, N×N super-pixels,
body albedo 0.7, 12 distant lights, the crater's FMBRDF), with the exact depth and normals. It prints the
lattice stride, the fraction of rays that meet the surface, the mean S0 bounce inside the dish and the time;
``--save`` keeps the S0 bounce, ``--compare`` prints the difference to a saved one — run it once with the code
before (``PYTHONPATH=<old checkout>``) and once with the code after.

Usage:
    OMP_NUM_THREADS=1 PYTHONPATH=<old> python benchmarks/bounce_estimate.py --size 512 --save /tmp/old.npy
    OMP_NUM_THREADS=1 PYTHONPATH=<new> python benchmarks/bounce_estimate.py --size 512 --compare /tmp/old.npy
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from polarshape.cameras import OrthographicCamera
from polarshape.lights import DirectionalLight, Lights
from polarshape.scene.geometry import crater_depth_map
from polarshape.surface.interreflection import estimate_one_bounce

LIGHTS = [(10, 0), (20, 120), (20, 240), (35, 60), (35, 180), (35, 300), (50, 30), (50, 150), (50, 270), (60, 90),
          (60, 210), (60, 330)]  # (zenith, azimuth) degrees
PARAMS = {"ior": 1.5, "k_s": 1.0, "alpha": 0.3, "beta": 2.0, "kappa": 0.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512, help="super-pixels across (default 512)")
    ap.add_argument("--max-pixels", type=int, default=16384, help="interreflection.max_pixels (default 16384)")
    ap.add_argument("--save", type=Path, help="write the (K, H, W) S0 bounce here (.npy)")
    ap.add_argument("--compare", type=Path, help="compare with a saved S0 bounce (.npy)")
    args = ap.parse_args()
    n = args.size
    pixel = 0.0256 / n
    depth, normals = crater_depth_map(n, pixel, radius=0.008, depth=0.004, half_width=0.0115, distance=0.5)
    view = torch.zeros(n, n, 3)
    view[..., 2] = -1.0
    lights = Lights(tuple(DirectionalLight((math.sin(math.radians(z)) * math.cos(math.radians(a)),
                                            math.sin(math.radians(z)) * math.sin(math.radians(a)),
                                            -math.cos(math.radians(z)))) for z, a in LIGHTS))
    t0 = time.perf_counter()
    b = estimate_one_bounce(torch.tensor(normals, dtype=torch.float32),
                            torch.full((n, n), 0.7), depth, OrthographicCamera(n, n, pixel, even=False), view, lights,
                            PARAMS, max_pixels=args.max_pixels)
    seconds = time.perf_counter() - t0
    s0 = b.stokes[:, 0].double().numpy()  # (K, H, W)
    dish = np.nan_to_num(depth, nan=0.5) > 0.5  # the dish sinks below the plate (z = 0.5)
    print(f"{n}² super-pixels, max_pixels {args.max_pixels}: stride {b.stride}, {100 * b.rays_hit:.2f} % of the rays hit, "
          f"mean S0 bounce in the dish {s0[:, dish].mean():.5g}, {seconds:.2f} s")
    if args.save:
        np.save(args.save, s0)
    if args.compare:
        ref = np.load(args.compare)
        d = (s0 - ref)[:, dish]
        print(f"against {args.compare}: mean {d.mean() / ref[:, dish].mean():+.4%}, "
              f"rms {np.sqrt((d**2).mean()) / ref[:, dish].mean():.4%} of the dish's mean bounce; "
              f"largest |difference| {np.abs(d).max() / ref.max():.2%} of the largest bounce")


if __name__ == "__main__":
    main()
