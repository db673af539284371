"""Cost of ``render_parts`` — the model evaluation on the recovery's hot path (issue 13).

Times :func:`polarshape.recover.reflectometry.render_parts` (surface and body Stokes of P pixels under K
lights, irradiance included) for one material with κ = 0 (the separable case) and κ > 0, forward only
under ``torch.no_grad`` (as the normal solver calls it), and reports the median of ``--repeats`` calls in
µs per pixel·light. Inputs are a perspective view of normals within 75° of the view and K distant lights
(zenith 15–55°, golden-angle azimuths, like the scaling benchmark's scene) — the shapes the recovery uses:
normals (P, 3), lights (P, K, 3), view (P, 3), irradiance (P, K). ``--normals sphere`` (default): a
sphere's image in row-major order, as a recovery sees it; ``--normals random``: independent normals, the
worst case for the κ > 0 table lookups (each a cache miss).

Before/after: run the same script with PYTHONPATH pointing at each checkout, alternating, and compare the
medians; ``--save FILE`` stores the outputs and ``--compare A B`` reports the largest relative differences
of two saved runs (per κ, per dtype).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/render_parts.py [--pixels 200000] [--lights 12] [--kappa 0 20]
        [--dtype float32] [--threads 1] [--repeats 3] [--device cpu] [--normals sphere|random] [--save FILE]
    python benchmarks/render_parts.py --compare before.pt after.pt
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time

import torch

import polarshape
from polarshape.brdf import build_tables
from polarshape.recover.observations import Observations
from polarshape.recover.reflectometry import render_parts

MATERIAL = dict(ior=1.5, alpha=0.3, beta=2.0)


def inputs(pixels: int, lights: int, dtype: torch.dtype, device: str, seed: int = 0, field: str = "sphere") -> tuple[torch.Tensor, Observations]:
    """Normals (P, 3) and observations (lights (P, K, 3), view (P, 3), irradiance (P, K)).

    ``field``: "sphere" — the pixels of a sphere's image in row-major order (smooth normals up to 75°
    from the view, as a recovery sees them: neighbouring pixels read neighbouring table cells);
    "random" — normals drawn independently within 75° of the view (every lookup a cache miss: the
    worst case for the body table of κ > 0)."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    r_max = math.sin(math.radians(75.0))
    if field == "sphere":
        side = math.ceil(math.sqrt(pixels * 4.0 / math.pi)) + 2
        while True:
            y, x = torch.meshgrid(torch.linspace(-1.0, 1.0, side, dtype=f64), torch.linspace(-1.0, 1.0, side, dtype=f64), indexing="ij")
            inside = (x * x + y * y) <= 1.0
            if int(inside.sum()) >= pixels:
                break
            side += 8
        xy = torch.stack([x[inside], y[inside]], -1)[:pixels]  # row-major
        view = -torch.cat([xy * 0.27, torch.ones(pixels, 1, dtype=f64)], 1)  # ±15° field of view
        nxy = xy * r_max
        normals = torch.cat([nxy, -torch.sqrt(1.0 - (nxy * nxy).sum(-1, keepdim=True))], 1)
    else:
        xy = (torch.rand(pixels, 2, generator=g, dtype=f64) - 0.5) * 0.55
        view = -torch.cat([xy, torch.ones(pixels, 1, dtype=f64)], 1)
        cos_t = 1.0 - torch.rand(pixels, generator=g, dtype=f64) * (1.0 - math.cos(math.radians(75.0)))
        phi = torch.rand(pixels, generator=g, dtype=f64) * 2 * math.pi
        sin_t = (1 - cos_t**2).sqrt()
        vv = view / view.norm(dim=-1, keepdim=True)
        t1 = torch.linalg.cross(vv, torch.tensor([1.0, 0.0, 0.0], dtype=f64).expand_as(vv))
        t1 = t1 / t1.norm(dim=-1, keepdim=True)
        t2 = torch.linalg.cross(vv, t1)
        normals = cos_t[:, None] * vv + sin_t[:, None] * (torch.cos(phi)[:, None] * t1 + torch.sin(phi)[:, None] * t2)
    view = view / view.norm(dim=-1, keepdim=True)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    k = torch.arange(lights, dtype=f64)
    zen = torch.deg2rad(15.0 + 40.0 * k / max(lights - 1, 1))
    az = k * math.pi * (3.0 - math.sqrt(5.0))
    l_dir = torch.stack([torch.sin(zen) * torch.cos(az), torch.sin(zen) * torch.sin(az), -torch.cos(zen)], -1)
    light = l_dir.expand(pixels, lights, 3).contiguous()
    irradiance = 0.5 + torch.rand(pixels, lights, generator=g, dtype=f64)
    stokes = torch.zeros(pixels, lights, 3, dtype=f64)
    obs = Observations(stokes, torch.ones(pixels, lights, dtype=f64), light, irradiance, view)
    obs = Observations(*(t.to(device=device, dtype=dtype) for t in (obs.stokes, obs.weight, obs.lights, obs.irradiance, obs.view)))
    return normals.to(device=device, dtype=dtype), obs


def compare(path_a: str, path_b: str) -> None:
    """Largest differences of two ``--save`` runs (A = before, B = after).

    Per pixel·light relative: max over (s0, s1, s2) of |B − A| / max |A| of that pixel·light, over those
    whose |A| exceeds 1e-9 of the largest (all lit ones but the terminator, where N·L is a cancelling sum).
    For float32, each run is also compared with A's float64 result of the same κ (the float32 error of
    each evaluator: the change is within float32's own precision when the two are alike)."""
    a, b = torch.load(path_a), torch.load(path_b)

    def rel(x: torch.Tensor, y: torch.Tensor) -> str:
        scale = x.abs().amax(-1)
        lit = scale > 1e-9 * scale.max()
        r = (y - x).abs().amax(-1) / scale.clamp_min(1e-300)
        return f"max rel {r[lit].max().item():.2e}, median rel {r[lit].median().item():.1e}, max |Δ|/max|s| {(y - x).abs().max().item() / x.abs().max().item():.1e}"

    for key in a:
        for i, part in enumerate(("surface", "body")):
            x, y = a[key][i].double(), b[key][i].double()
            print(f"{key} {part}: after vs before: {rel(x, y)}")
            ref_key = key.replace("float32", "float64")
            if ref_key != key and ref_key in a:
                ref = a[ref_key][i].double()
                print(f"    vs float64 before: before {rel(ref, x)}; after {rel(ref, y)}")


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pixels", type=int, default=200_000)
    parser.add_argument("--lights", type=int, default=12)
    parser.add_argument("--kappa", type=float, nargs="+", default=[0.0, 20.0])
    parser.add_argument("--dtype", choices=["float32", "float64"], nargs="+", default=["float32"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--normals", choices=["sphere", "random"], default="sphere", help="normal field (see inputs())")
    parser.add_argument("--save", help="store the outputs (per κ, dtype) in this file")
    parser.add_argument("--compare", nargs=2, metavar=("A", "B"), help="largest relative differences of two --save files")
    args = parser.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    torch.set_num_threads(args.threads)
    print(f"polarshape from {polarshape.__file__}; torch {torch.__version__}; {platform.processor() or platform.machine()}; "
          f"{args.threads} thread(s); P = {args.pixels}, K = {args.lights}, {args.normals} normals")
    saved = {}
    for dt_name in args.dtype:
        dtype = getattr(torch, dt_name)
        normals, obs = inputs(args.pixels, args.lights, dtype, args.device, field=args.normals)
        for kappa in args.kappa:
            tables = build_tables(**MATERIAL, kappa=kappa, device=args.device)
            with torch.no_grad():
                out = render_parts(tables, normals, obs)  # warm-up
                times = []
                for _ in range(args.repeats):
                    sync(args.device)
                    t0 = time.perf_counter()
                    render_parts(tables, normals, obs)
                    sync(args.device)
                    times.append(time.perf_counter() - t0)
            med = statistics.median(times)
            per = med / (args.pixels * args.lights) * 1e6
            print(f"kappa {kappa:g} {dt_name}: median {med:.3f} s per call ({', '.join(f'{t:.3f}' for t in times)}), "
                  f"{per:.3f} µs per pixel·light")
            saved[f"kappa={kappa:g} {dt_name}"] = tuple(t.cpu() for t in out)
    if args.save:
        torch.save(saved, args.save)


if __name__ == "__main__":
    main()
