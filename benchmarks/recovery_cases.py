"""Figures behind issue 4's closing note: the recovery on chosen hard cases, one table per case.

    python benchmarks/recovery_cases.py textured        # checker texture: propagation on/off, filled pixels
    python benchmarks/recovery_cases.py no-polariser    # camera without polariser: intensity-only fit
    python benchmarks/recovery_cases.py shiny           # α = 0.05 at 1 ms: α vs resolution
    python benchmarks/recovery_cases.py signal          # polarisation_signal of polarised / unpolarised captures
    python benchmarks/recovery_cases.py kappa           # can the loss tell κ from model mismatch?
    python benchmarks/recovery_cases.py integration --result DIR   # slope cap on a `polarshape run` result

The simulated captures are the tests' (``tests/test_normals.py::_simulate``: the scene files
of ``configs/scenes`` at n × n super-pixels, 12-bit, shot and read noise), so the figures match
what the tests assert. ``signal`` and ``kappa`` also use ``../shared/data`` when present.
Machine-dependent times are printed with the machine; errors are mean angular errors (degrees).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from test_normals import _errors, _recover, _simulate  # noqa: E402  (the tests' scenes)

import polarshape.acquisition.simulated as simulated  # noqa: E402
from polarshape.acquisition.simulated import SimulatedCamera  # noqa: E402
from polarshape.brdf import build_tables  # noqa: E402
from polarshape.io.capture import Capture, load_capture  # noqa: E402
from polarshape.imaging.mosaic import split_mosaic  # noqa: E402
from polarshape.imaging.pixels import counts_to_float  # noqa: E402
from polarshape.brdf.params import FMBRDFParams  # noqa: E402
from polarshape.metrics import angular_error_deg  # noqa: E402
from polarshape.recover.normal_solver import NormalProblem, huber_delta, refine_normals  # noqa: E402
from polarshape.recover.observations import flatten_observations  # noqa: E402
from polarshape.recover.preprocess import polarisation_signal, preprocess_capture  # noqa: E402
from polarshape.recover.reflectometry import fit_reflectance, objective  # noqa: E402
from polarshape.scene.config import parse_scene_config  # noqa: E402

SHARED = REPO / ".." / "shared" / "data"


def _unpolarised_camera() -> object:
    """Make the simulated camera see ½ s0 at every site (no polariser array); returns the original."""
    original = simulated.mosaic_radiance
    simulated.mosaic_radiance = lambda stokes, angle_map: 0.5 * stokes[..., 0, :, :]
    return original


def textured(n: int) -> None:
    d = yaml.safe_load((REPO / "configs/scenes/textured.yaml").read_text())
    d.update(lights=yaml.safe_load((REPO / "configs/scenes/sphere.yaml").read_text())["lights"], objects=d["objects"][:1])
    d["camera"].update(width=2 * n, height=2 * n, pixel_size_m=1.2e-4 * 128 / n, pixel_format="PolarizeMono12")
    capture = SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    print(f"checker-textured sphere, 9 distant lights, {n}²")
    for propagate in (True, False):
        t0 = time.perf_counter()
        r = _recover(capture, propagate=propagate)
        m = r.mask & torch.isfinite(gt).all(-1)
        e = angular_error_deg(r.normals.double()[m], gt[m])
        print(f"  propagate {propagate!s:5}: mean {float(e.mean()):.2f} median {float(e.median()):.2f} "
              f"> 10°: {int((e > 10).sum())} of {int(m.sum())}, filled {int(r.filled.sum())}, "
              f"{time.perf_counter() - t0:.1f} s")


def no_polariser() -> None:
    original = _unpolarised_camera()
    try:
        for alpha in (0.3, 0.8):
            capture = _simulate("sphere", 56, alpha)
            r = _recover(capture, fit_kappa=False)
            lamb = _recover(capture, model="lambertian")
            print(f"sphere 56², α {alpha}, no polariser: FMBRDF intensity-only {_errors(r, capture)[0]:.2f}° "
                  f"(α {r.params['alpha']:.3f}, β {r.params['beta']:.2f}, k_s {r.params['k_s']:.3g}), "
                  f"Lambertian PS {_errors(lamb, capture)[0]:.2f}°")
    finally:
        simulated.mosaic_radiance = original


def shiny() -> None:
    for kind, n in (("sphere", 56), ("sphere", 84), ("sphere", 112), ("blob", 80), ("blob", 120)):
        capture = _simulate(kind, n, 0.05, exposure_us=1000)
        inputs = preprocess_capture(capture)
        gt = torch.from_numpy(capture.ground_truth["normals"]).float()
        pix = inputs.mask & torch.isfinite(gt).all(-1)
        known = fit_reflectance(gt[pix], flatten_observations(inputs, pix), fit_kappa=False, delta=0.01).params
        r = _recover(capture, fit_kappa=False, max_outer_iterations=12)
        print(f"{kind} {n}², α 0.05 at 1 ms: saturated obs {int(inputs.saturated[:, inputs.mask].sum())}; "
              f"α true normals {known.alpha:.4f}, joint {r.params['alpha']:.4f} (μ {r.params['ior']:.3f}), "
              f"error {_errors(r, capture)[0]:.2f}°")


def _signal(capture: Capture) -> float:
    inputs = preprocess_capture(capture)
    mosaic = counts_to_float(capture.frames, capture.bit_depth, capture.spec.camera.black_level, dtype=torch.float64)
    return polarisation_signal(inputs.stokes[:, 1:], split_mosaic(mosaic, capture.layout), inputs.valid)


def signal() -> None:
    cases: list[tuple[str, object]] = [(f"{k} {n}² α {a}", (k, n, a)) for k, n, a in
                                       (("sphere", 56, 0.3), ("sphere", 56, 0.8), ("blob", 80, 0.05), ("blob", 80, 0.8))]
    for label, (k, n, a) in cases:
        print(f"{label}: polarised {_signal(_simulate(k, n, a)):.3f}", end="")
        original = _unpolarised_camera()
        try:
            print(f", no polariser {_signal(_simulate(k, n, a)):.3f}")
        finally:
            simulated.mosaic_radiance = original
    for name in ("official_sphere128", "mitsuba_sphere_a020"):
        if (SHARED / name).is_dir():
            print(f"{name}: {_signal(load_capture(SHARED / name)):.3f}")


def _alternate(normals: torch.Tensor, obs, params: FMBRDFParams, fit_kappa: bool, delta: float, rounds: int):
    normals = normals.clone()
    for _ in range(rounds):
        params = fit_reflectance(normals, obs, init=params, fit_kappa=fit_kappa, delta=delta, grid_search=False,
                                 max_iter=4).params
        tables = build_tables(ior=params.ior, alpha=params.alpha, beta=params.beta, kappa=params.kappa)
        problem = NormalProblem.build(tables, obs.stokes, params.k_s, True, params.k_b, True, delta)
        normals = refine_normals(problem, normals, obs, max_iter=6)[0]
    return objective(params, normals, obs, delta=delta), params


def kappa() -> None:
    """After the κ = 0 recovery: re-fit μ, α, β (and κ, from 20) with the normals of a 2048-pixel
    subsample, 4 alternations each way; the gain is the relative loss drop of the κ arm."""
    cases: list[tuple[str, Capture, dict]] = [
        ("sphere 56² κ 40", _simulate("sphere", 56, 0.3, kappa=40.0), {}),
        ("blob 80² κ 20", _simulate("blob", 80, 0.3, kappa=20.0), {}),
        ("sphere 56² κ 0", _simulate("sphere", 56, 0.3), {}),
    ]
    for name, options in (("mitsuba_sphere_a020", {}), ("official_sphere128", {"sample_at": "top_left"})):
        if (SHARED / name).is_dir():
            cases.append((name, load_capture(SHARED / name), options))
    for label, capture, options in cases:
        r = _recover(capture, fit_kappa=False, **options)
        inputs = preprocess_capture(capture, **options)
        pix = r.mask & torch.isfinite(r.normals).all(-1)
        obs, normals = flatten_observations(inputs, pix), r.normals[pix]
        idx = torch.randperm(normals.shape[0], generator=torch.Generator().manual_seed(0))[:2048].sort().values
        sub_obs, sub_n = obs.select(idx), normals[idx]
        delta = huber_delta(obs, inputs.noise_std)
        start = FMBRDFParams(**{k: r.params[k] for k in ("ior", "alpha", "beta", "kappa")})
        loss0, _ = _alternate(sub_n, sub_obs, start, False, delta, 4)
        loss1, p1 = _alternate(sub_n, sub_obs, FMBRDFParams(**{**vars(start), "kappa": 20.0}), True, delta, 4)
        print(f"{label}: κ arm lowers the loss by {100 * (loss0 - loss1) / loss0:.2f} % (κ {p1.kappa:.1f})")


def integration(result: Path) -> None:
    from polarshape.cameras import OrthographicCamera
    from polarshape.surface.integrate import integrate_normals

    capture = load_capture(result / "capture")
    params = yaml.safe_load((result / "params.json").read_text())
    truth = capture.ground_truth["depth"]
    normals = np.load(result / "normals.npy").astype(np.float64)
    pixel = params["integration"]["pixel_size_m"]
    for source, n in (("ground truth", capture.ground_truth["normals"].astype(np.float64)), ("recovered", normals)):
        for eps in (1e-3, 0.02, 0.05, 0.1):
            camera = OrthographicCamera(n.shape[1], n.shape[0], pixel, even=False)
            depth = integrate_normals(n, np.isfinite(n).all(-1), camera=camera,
                                      reference_depth=float(np.nanmedian(truth)), grazing_eps=eps)
            k = np.isfinite(depth) & np.isfinite(truth)
            diff = depth[k] - truth[k]
            rms = np.sqrt(np.mean((diff - np.median(diff)) ** 2))
            print(f"{source} normals, grazing_eps {eps}: depth RMS {1000 * rms:.4f} mm of a {1000 * np.ptp(truth[k]):.2f} mm range")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", choices=("textured", "no-polariser", "shiny", "signal", "kappa", "integration"))
    parser.add_argument("--size", type=int, default=128, help="textured: super-pixels across")
    parser.add_argument("--result", type=Path, help="integration: a `polarshape run` result folder (orthographic, with ground truth)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    print(f"# {args.case} — {platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} threads")
    if args.case == "textured":
        textured(args.size)
    elif args.case == "no-polariser":
        no_polariser()
    elif args.case == "shiny":
        shiny()
    elif args.case == "signal":
        signal()
    elif args.case == "kappa":
        kappa()
    else:
        if args.result is None:
            parser.error("integration needs --result DIR (run: polarshape run CONFIG --out DIR)")
        integration(args.result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
