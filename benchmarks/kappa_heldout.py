"""Issue 13: can held-out data tell κ from model mismatch? The κ test's gains in-sample and held out.

    python benchmarks/kappa_heldout.py                          # every case below
    python benchmarks/kappa_heldout.py --cases blob_a0.3_k50 baek_beckmann mitsuba

Each capture is recovered end to end (``tests/test_normals.py::_recover``, the alternation) up to the κ
decision, which is intercepted: its inputs (the κ = 0 optimum of the subsample, its observations) are
scored three ways, all with the κ test's settings (coarse tables, tol 1e-3) and the recovery then goes
on at κ = 0:

- ``in``: the κ test's gain, the nested κ fit's loss drop from the κ = 0 optimum (what the recovery decides on);
- ``lights``: 2 folds of the lights (every other light held out): on the other half, the κ = 0 solve and
  then the nested κ fit from it; the two fits' losses on the held-out lights (their normals and
  material, per-pixel k_b in closed form there), summed over the folds;
- ``pixels``: the κ = 0 and the nested κ fit on half the subsample's pixels; the other half's normals
  re-fitted (6 iterations) for each material, their losses compared.

Cases: the 40² spheres and blobs of ``benchmarks/joint_solve.py`` (true κ 50 or 0), the 64² sphere
rendered with the Baek pBRDF (``tests/test_normals.py::test_baek_rendered_capture_model_mismatch``) and
the Mitsuba capture of ``../shared/data`` (Baek model) when present. A rule on held-out data separates κ
from mismatch only if every true-κ case gains more there than every mismatch case.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from test_normals import _recover, _simulate  # noqa: E402  (the tests' scenes)

import polarshape.recover.coarse_to_fine as ctf  # noqa: E402
from polarshape.acquisition.simulated import SimulatedCamera  # noqa: E402
from polarshape.io.capture import load_capture  # noqa: E402
from polarshape.brdf import build_tables  # noqa: E402
from polarshape.recover.joint_solve import JointResult, joint_solve, nested_kappa  # noqa: E402
from polarshape.recover.normal_solver import NormalProblem  # noqa: E402
from polarshape.recover.observations import Observations  # noqa: E402
from polarshape.scene.config import parse_scene_config  # noqa: E402

SHARED = REPO / ".." / "shared" / "data"


def _baek(distribution: str) -> object:
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    d["camera"]["width"] = d["camera"]["height"] = 128
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / 128
    d["objects"][0]["material"] = {"model": "baek", "ior": 1.5, "k_s": 1.0, "k_d": 0.5, "alpha": 0.25,
                                   "distribution": distribution}
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def _cases() -> dict[str, tuple[object, dict]]:
    out: dict[str, tuple[object, dict]] = {}
    for kind in ("sphere", "blob"):
        for kappa in (50.0, 0.0):
            for alpha in (0.3, 0.8, 0.03):
                out[f"{kind}_a{alpha:g}_k{kappa:g}"] = (
                    lambda kind=kind, alpha=alpha, kappa=kappa: _simulate(
                        kind, 40, alpha, kappa=kappa, exposure_us=1000.0 if alpha < 0.1 else None), {})
    for dist in ("beckmann", "ggx"):
        out[f"baek_{dist}"] = (lambda dist=dist: _baek(dist), {"max_outer_iterations": 10})
    if (SHARED / "mitsuba_sphere_a020").is_dir():
        out["mitsuba"] = (lambda: load_capture(SHARED / "mitsuba_sphere_a020"), {})
    return out


def _decision_inputs(capture: object, options: dict) -> tuple[JointResult, Observations, tuple[str, ...], dict]:
    """Recover ``capture`` and return the first κ decision's inputs (the recovery goes on at κ = 0)."""
    seen: list[tuple] = []
    original = ctf._kappa_decision

    def intercept(fit, obs_sub, names, kwargs, *, level, log):  # noqa: ANN001, ANN202
        seen.append((fit, obs_sub, tuple(names), dict(kwargs)))
        return fit

    ctf._kappa_decision = intercept
    try:
        _recover(capture, **options)
    finally:
        ctf._kappa_decision = original
    return seen[0]


def _loss_on(fit: JointResult, obs: Observations, kw: dict) -> float:
    """Sum of the per-pixel Huber losses of ``fit``'s normals and material on ``obs`` (the κ test's grid;
    no iteration: ``joint_solve`` with ``max_iter=0`` would also move pixels to highlight candidates)."""
    p = fit.params
    tables = build_tables(ior=p.ior, alpha=p.alpha, beta=p.beta, kappa=p.kappa, n_grid=ctf.KAPPA_TEST_GRID)
    problem = NormalProblem.build(tables, obs.stokes, p.k_s, kw["per_pixel_albedo"], p.k_b, kw["polarised"],
                                  float(kw["delta"]))
    return float(problem.pixel_loss(fit.normals, obs).sum())


def _with_weight(obs: Observations, weight: torch.Tensor) -> Observations:
    return Observations(obs.stokes, weight, obs.lights, obs.irradiance, obs.view)


def score(fit: JointResult, obs: Observations, names: tuple[str, ...], kw: dict) -> dict[str, float]:
    test = {**kw, "n_grid": ctf.KAPPA_TEST_GRID, "jac_grid": ctf.KAPPA_JAC_GRID, "tol": 1e-3}
    t0 = time.perf_counter()
    nested, gain_in = nested_kappa(fit, obs, names=names, **test)
    out = {"in": gain_in, "kappa": nested.params.kappa, "test_s": time.perf_counter() - t0}
    # held-out lights: every other light
    k = obs.weight.shape[1]
    l0 = l1 = 0.0
    for fold in range(2):
        held = (torch.arange(k, device=obs.weight.device) % 2 == fold).to(obs.weight.dtype)
        train, heldout = _with_weight(obs, obs.weight * (1 - held)), _with_weight(obs, obs.weight * held)
        base = joint_solve(fit.normals, train, fit.params, names=names, **test)
        base = replace(base, start_normals=fit.start_normals, start_params=fit.start_params)
        kap, _ = nested_kappa(base, train, names=names, **test)
        l0 += _loss_on(base, heldout, kw)
        l1 += _loss_on(kap, heldout, kw)
    out["lights"] = (l0 - l1) / l0
    # held-out pixels: half of the subsample
    p = obs.stokes.shape[0]
    perm = torch.randperm(p, generator=torch.Generator().manual_seed(0))
    a, b = perm[: p // 2].sort().values, perm[p // 2:].sort().values
    base = joint_solve(fit.normals[a], obs.select(a), fit.params, names=names, **test)
    starts = None if fit.start_normals is None else fit.start_normals[a]
    base = replace(base, start_normals=starts, start_params=fit.start_params)
    kap, _ = nested_kappa(base, obs.select(a), names=names, **test)
    h0 = joint_solve(fit.normals[b], obs.select(b), base.params, names=(), **{**test, "max_iter": 6})
    h1 = joint_solve(fit.normals[b], obs.select(b), kap.params, names=(), **{**test, "max_iter": 6})
    out["pixels"] = (h0.loss - h1.loss) / h0.loss
    return out


def main() -> None:
    cases = _cases()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(cases), choices=list(cases))
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"# {platform.machine()}, torch {torch.__version__}, 1 thread; gains in % of the κ = 0 fit's loss")
    print(f"{'case':<18} {'κ test':>7} {'κ':>6} {'lights':>7} {'pixels':>7} {'test s':>7}")
    for name in args.cases:
        make, options = cases[name]
        fit, obs, names, kw = _decision_inputs(make(), options)
        s = score(fit, obs, names, kw)
        print(f"{name:<18} {100 * s['in']:>6.1f}% {s['kappa']:>6.1f} {100 * s['lights']:>6.1f}% "
              f"{100 * s['pixels']:>6.1f}% {s['test_s']:>7.1f}", flush=True)


if __name__ == "__main__":
    main()
