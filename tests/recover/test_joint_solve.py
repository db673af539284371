"""Tests of polarshape.recover.joint_solve: the Schur-complement step, the joint fit on a small
sphere against the alternation, and κ as a nested fit."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from polarshape.brdf.params import FMBRDFParams
from polarshape.metrics import angular_error_deg
from polarshape.recover.coarse_to_fine import solve_fmbrdf
from polarshape.recover.joint_solve import (
    clearly_below, first_of, joint_solve, loss_floor, nested_kappa, schur_step, settled, trimmed_gain,
)
from polarshape.recover.observations import Observations, flatten_observations
from polarshape.recover.options import RecoveryOptions

from test_coarse_to_fine import _sphere_inputs


def test_schur_step_equals_the_dense_damped_step() -> None:
    gen = torch.Generator().manual_seed(3)
    p, g, m = 5, 4, 9
    jn = torch.randn(p, m, 2, generator=gen, dtype=torch.float64)
    jg = torch.randn(p, m, g, generator=gen, dtype=torch.float64)
    r = torch.randn(p, m, generator=gen, dtype=torch.float64)
    w = torch.rand(p, m, generator=gen, dtype=torch.float64) + 0.1
    lam_n = torch.rand(p, generator=gen, dtype=torch.float64)
    lam_g = 0.3
    # the dense Jacobian of the whole problem: pixel p's residuals depend on its own 2 columns and the G globals
    dense = torch.zeros(p * m, 2 * p + g, dtype=torch.float64)
    for i in range(p):
        dense[i * m:(i + 1) * m, 2 * i:2 * i + 2] = jn[i]
        dense[i * m:(i + 1) * m, 2 * p:] = jg[i]
    wf, rf = w.flatten(), r.flatten()
    h = dense.T @ (wf[:, None] * dense)
    b = dense.T @ (wf * rf)
    lam = torch.cat([lam_n.repeat_interleave(2), torch.full((g,), lam_g, dtype=torch.float64)])
    full = -torch.linalg.solve(h + torch.diag(lam * (h.diagonal() + 1e-12)), b)
    jnw = jn * w[..., None]
    jgw = jg * w[..., None]
    dn, dg = schur_step(jnw.transpose(1, 2) @ jn, jnw.transpose(1, 2) @ jg, torch.einsum("pmi,pmj->ij", jgw, jg),
                        (jnw * r[..., None]).sum(1), (jgw * r[..., None]).sum((0, 1)), lam_n, lam_g)
    assert torch.allclose(dn.flatten(), full[:2 * p], atol=1e-10, rtol=1e-9)
    assert torch.allclose(dg, full[2 * p:], atol=1e-10, rtol=1e-9)


def _shiny_sphere() -> tuple[object, torch.Tensor, torch.Tensor]:
    inputs, truth = _sphere_inputs(16, alpha=0.1)
    start = torch.nn.functional.normalize(truth + torch.tensor([0.06, -0.04, 0.0], dtype=torch.float64), dim=-1)
    start = torch.where(inputs.mask[..., None], start, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    return inputs, truth, start


def test_joint_solve_recovers_material_and_normals_and_converges() -> None:
    inputs, truth = _sphere_inputs(16, alpha=0.3)
    gen = torch.Generator().manual_seed(0)
    inputs = replace(inputs, stokes=inputs.stokes + 1e-3 * torch.randn(inputs.stokes.shape, generator=gen,
                                                                       dtype=torch.float64))
    m = inputs.mask
    start = torch.nn.functional.normalize(truth[m] + torch.tensor([0.06, -0.04, 0.0], dtype=torch.float64), dim=-1)
    obs = flatten_observations(inputs, m)
    fit = joint_solve(start, obs, FMBRDFParams(ior=1.4, alpha=0.2, beta=2.5), names=("ior", "alpha", "beta"),
                      delta=3e-3, max_iter=20, tol=1e-5)
    assert fit.converged and fit.iterations <= 15, (fit.iterations, fit.rel_change)
    assert fit.loss <= fit.initial_loss
    assert all(b["loss"] <= a["loss"] for a, b in zip(fit.history, fit.history[1:]))  # never rises
    assert abs(fit.params.alpha - 0.3) < 0.01 and abs(fit.params.ior - 1.5) < 0.02, fit.params
    assert float(angular_error_deg(fit.normals, truth[m]).mean()) < 0.5
    # every iteration says what the LM did (damping tries, the gain ratio ρ of each try, the globals' step)
    for h in fit.history:
        assert h["attempts"] >= 1 and len(h["rho"]) == h["attempts"], h
        if h["accepted"]:
            assert len(h["step"]) == 4 and all(math.isfinite(d) for d in h["step"]), h  # μ, log α, log β, k_s
    # on this well-posed case the first step's quadratic model predicts its gain (0 < ρ; ρ ≈ 1 when exact)
    assert 0.2 < fit.history[0]["rho"][-1] < 3.0, fit.history[0]


def _fit_from(alpha: float, *, per_pixel_albedo: bool = True):  # noqa: ANN202
    """The joint solve of the noise-free 16² α 0.3 sphere at its true normals from a lobe of width ``alpha``,
    k_s 0 and k_b 0.1 (μ, β true)."""
    inputs, truth = _sphere_inputs(16, alpha=0.3)
    m = inputs.mask
    return joint_solve(truth[m], flatten_observations(inputs, m),
                       FMBRDFParams(ior=1.5, alpha=alpha, beta=2.0, k_s=0.0, k_b=0.1), names=("ior", "alpha", "beta"),
                       per_pixel_albedo=per_pixel_albedo, delta=3e-3, max_iter=20, tol=1e-5)


def test_joint_solve_reaches_a_far_specular_albedo_at_once() -> None:
    # a start lobe far too narrow (α 0.05 for 0.3) gives a closed-form k_s 19× too small; the LM's step on
    # k_s is capped relative to its value (×1.5 per iteration), so without the closed-form projection of
    # the linear globals after each step this took 16 iterations, most of them growing k_s
    fit = _fit_from(0.05)
    assert fit.history[0]["k_s"] > 0.5, fit.history[0]  # not 0.08 (×1.5 from the start's 0.053)
    assert fit.converged and fit.iterations <= 10, (fit.iterations, [h["k_s"] for h in fit.history])
    assert abs(fit.params.k_s - 1.0) < 1e-3 and abs(fit.params.alpha - 0.3) < 1e-3, fit.params
    assert all(b["loss"] <= a["loss"] for a, b in zip(fit.history, fit.history[1:]))


def test_joint_solve_with_one_global_body_albedo() -> None:
    # per_pixel_albedo=False: k_b is a fitted global, projected with k_s onto their closed form after each step
    fit = _fit_from(0.2, per_pixel_albedo=False)
    assert fit.converged and fit.iterations <= 10, (fit.iterations, fit.rel_change)
    assert abs(fit.params.k_b - 0.5) < 1e-3 and abs(fit.params.k_s - 1.0) < 1e-3, fit.params
    assert abs(fit.params.alpha - 0.3) < 1e-3 and abs(fit.params.ior - 1.5) < 1e-3, fit.params
    assert bool((fit.k_b == fit.k_b[0]).all())  # one k_b for every pixel
    assert all(b["loss"] <= a["loss"] for a, b in zip(fit.history, fit.history[1:]))


def test_the_global_body_albedo_is_projected_with_k_s_after_the_first_step() -> None:
    # from α 0.1 the closed-form k_s of the start is far below the truth (1): after the first accepted step the
    # projection puts k_s (and the global k_b) at their IRLS optimum, 0.98; the LM's capped linear step alone
    # reached 0.24
    fit = _fit_from(0.1, per_pixel_albedo=False)
    assert fit.history[0]["k_s"] > 0.5, fit.history[0]
    assert fit.converged and abs(fit.params.k_s - 1.0) < 1e-3 and abs(fit.params.k_b - 0.5) < 1e-3, fit.params


@pytest.mark.slow
def test_joint_level_at_least_as_good_as_the_alternation() -> None:
    inputs, truth, start = _shiny_sphere()
    m = inputs.mask
    out = {}
    for solver in ("joint", "alternating"):
        state, log = solve_fmbrdf(inputs, start, RecoveryOptions(model="fmbrdf", fit_kappa=False, solver=solver,
                                                                max_outer_iterations=20))
        out[solver] = (float(angular_error_deg(state.normals[m], truth[m]).mean()), abs(state.params.alpha - 0.1))
        if solver == "joint":
            assert log.counts["joint_iterations"] >= 1 and "joint" in log.timings
            assert any(h.get("solver") == "joint" for h in log.history)
    assert out["joint"][0] <= out["alternating"][0] + 1e-6, out
    assert out["joint"][1] <= out["alternating"][1] + 1e-6, out


@pytest.mark.slow
def test_nested_kappa_never_raises_the_loss_and_finds_kappa() -> None:
    inputs, truth = _sphere_inputs(10, alpha=0.3, kappa=40.0)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    base = joint_solve(truth[m], obs, FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0), names=("ior", "alpha", "beta"),
                       delta=1e-3, max_iter=3, n_grid=33, jac_grid=17)
    fit, gain = nested_kappa(base, obs, names=("ior", "alpha", "beta"), delta=1e-3, max_iter=5, n_grid=33, jac_grid=17)
    assert gain >= 0.0 and fit.loss <= fit.initial_loss
    assert abs(fit.initial_loss - base.loss) <= 1e-3 * base.loss  # the κ fit starts at the κ = 0 optimum
    assert gain > 0.5 and fit.params.kappa > 10.0, (gain, fit.params)


@pytest.mark.slow
def test_kappa_climbs_from_zero_to_a_strong_correlation() -> None:
    # noise-free α 0.8 κ 50 sphere at its true normals, κ fitted from 0: the kernel's width goes as 1/√κ, so
    # the loss is far from quadratic in κ; searched in κ itself the solve fell back to κ 2.9 (α 0.71) and
    # had not converged after 20 iterations, searched in log(1 + κ/κ₀) it reaches κ 50.5 in 15
    inputs, truth = _sphere_inputs(12, alpha=0.8, kappa=50.0)
    m = inputs.mask
    fit = joint_solve(truth[m], flatten_observations(inputs, m), FMBRDFParams(ior=1.5, alpha=0.8, beta=2.0, kappa=0.0),
                      names=("ior", "alpha", "beta", "kappa"), delta=1e-3, max_iter=20, n_grid=33, jac_grid=17)
    assert fit.converged, [(h["kappa"], h["loss"]) for h in fit.history]
    assert abs(fit.params.kappa - 50.0) < 1.0 and abs(fit.params.alpha - 0.8) < 0.01, fit.params
    assert all(b["loss"] <= a["loss"] for a, b in zip(fit.history, fit.history[1:]))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_joint_solve_on_cuda_matches_cpu() -> None:
    inputs, truth = _sphere_inputs(12, alpha=0.3)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    start = torch.nn.functional.normalize(truth[m] + torch.tensor([0.05, -0.03, 0.0], dtype=torch.float64), dim=-1)
    kw = {"names": ("ior", "alpha", "beta"), "delta": 1e-3, "max_iter": 5}
    fits = {}
    for dev in ("cpu", "cuda"):
        obs_d = Observations(*(t.float().to(dev) for t in (obs.stokes, obs.weight, obs.lights, obs.irradiance,
                                                             obs.view)))
        fits[dev] = joint_solve(start.float().to(dev), obs_d, FMBRDFParams(ior=1.4, alpha=0.25, beta=2.5), **kw)
    cpu, gpu = fits["cpu"], fits["cuda"]
    assert gpu.normals.device.type == "cuda"
    assert abs(gpu.params.alpha - cpu.params.alpha) < 1e-3 and abs(gpu.params.ior - cpu.params.ior) < 1e-3


@pytest.mark.slow
def test_joint_level_kappa_decision_on_kappa_free_data_keeps_zero_and_reports_no_rise() -> None:
    inputs, truth = _sphere_inputs(12)
    start = torch.where(inputs.mask[..., None], truth, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    state, log = solve_fmbrdf(inputs, start, RecoveryOptions(model="fmbrdf", solver="joint", max_outer_iterations=3))
    said = [s for s in log.skipped if s.startswith("kappa:")]
    assert state.params.kappa == 0.0 and len(said) == 1, log.skipped
    assert "by -" not in said[0] and "nested" in said[0], said
    assert log.counts["kappa_probes"] == 1


def test_a_normal_far_off_a_narrow_lobe_finds_its_highlight() -> None:
    # α 0.05: a pixel whose normal is 15° off its highlight sees no gradient towards it; the
    # highlight candidate (half vector of its brightest light) puts it back
    inputs, truth = _sphere_inputs(24, alpha=0.05)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    peak = obs.stokes[..., 0].amax(1) / obs.stokes[..., 0].median(1).values  # (P,)
    hot = peak.argsort(descending=True)[:3]
    start = truth[m].clone()
    start[hot] = torch.nn.functional.normalize(start[hot] + torch.tensor([0.27, 0.0, 0.0], dtype=torch.float64), dim=-1)
    assert float(angular_error_deg(start[hot], truth[m][hot]).min()) > 10.0
    fit = joint_solve(start, obs, FMBRDFParams(ior=1.5, alpha=0.05, beta=2.0, k_s=1.0), names=(), delta=1e-3,
                      max_iter=5)
    assert fit.loss < 0.1 * fit.initial_loss, (fit.loss, fit.initial_loss)
    assert float(angular_error_deg(fit.normals[hot], truth[m][hot]).max()) < 2.0


@pytest.mark.slow
def test_nested_kappa_also_starts_from_the_kappa_free_solves_start() -> None:
    # κ = 40 data; the κ = 0 "optimum" given is a degenerate corner (α at 0.01, β at 6) from which κ
    # does not grow: the κ fit must also try from that solve's own start
    inputs, truth = _sphere_inputs(10, alpha=0.3, kappa=40.0)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    kw = {"delta": 1e-3, "n_grid": 33, "jac_grid": 17}
    base = joint_solve(truth[m], obs, FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0), names=("ior", "alpha", "beta"),
                       max_iter=2, **kw)
    corner = replace(base, params=replace(base.params, alpha=0.01, beta=6.0))
    fit, gain = nested_kappa(corner, obs, names=("ior", "alpha", "beta"), max_iter=5, **kw)
    assert gain > 0.5 and fit.params.kappa > 10.0, (gain, fit.params)


@pytest.mark.slow
def test_nested_kappa_gain_on_noise_free_kappa_free_data_is_measured_against_the_loss_floor() -> None:
    # noise-free κ = 0 data: the κ = 0 optimum's loss is table discretisation (1e-11 on these tables) and
    # rounding (1e-26 on full ones); the gain was taken relative to that raw loss and read 61 % for a
    # κ of 0.03; relative to max(loss, loss_floor(δ)) it is no gain at all
    inputs, truth = _sphere_inputs(10)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    kw = {"names": ("ior", "alpha", "beta"), "delta": 1e-3}
    base = joint_solve(truth[m], obs, FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0), max_iter=3, **kw)
    fit, gain = nested_kappa(base, obs, max_iter=5, n_grid=33, jac_grid=17, **kw)
    assert fit.loss <= fit.initial_loss < loss_floor(1e-3)
    assert 0.0 <= gain < 0.01, (gain, fit.initial_loss, fit.loss)


def test_joint_solve_stop_ends_the_solve_when_the_caller_has_decided() -> None:
    inputs, truth = _sphere_inputs(10, alpha=0.3)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    start = torch.nn.functional.normalize(truth[m] + torch.tensor([0.06, -0.04, 0.0], dtype=torch.float64), dim=-1)
    kw = {"names": ("alpha",), "delta": 1e-3, "max_iter": 6, "tol": 1e-12, "n_grid": 17, "jac_grid": 17}
    seen: list[tuple[float, int]] = []

    def stop(initial: float, history: list[dict]) -> bool:
        seen.append((initial, len(history)))
        return len(history) >= 2

    fit = joint_solve(start, obs, FMBRDFParams(ior=1.5, alpha=0.4, beta=2.0), stop=stop, **kw)
    assert fit.iterations == 2 and [n for _, n in seen] == [1, 2], (fit.iterations, seen)
    assert seen[0][0] == fit.initial_loss and not fit.converged


def test_settled_stops_only_a_fast_descent_below_its_tolerance() -> None:
    stop = settled(1e-3, 0.1)

    def h(*rel: float) -> list[dict]:
        return [{"rel_change": r} for r in rel]

    assert not stop(1.0, h(5e-4))  # one iteration: no rate yet
    assert stop(1.0, h(5e-5))  # one iteration below a tenth of 0.1 %: it started where it had settled
    assert stop(1.0, h(0.1, 7e-4))  # below 0.1 % and 140× smaller than the change before
    assert not stop(1.0, h(2e-3, 7e-4))  # below 0.1 % but crawling (ρ 0.35): the rest may be large
    assert not stop(1.0, h(0.2, 0.015))  # fast, but the change itself above 0.1 %


def test_a_polish_stops_once_its_gain_over_the_kappa_free_optimum_clearly_ends_below_the_decision() -> None:
    # the κ polish of the 256² α 0.03 sphere exposed not to clip (coarse_to_fine._kappa_decision): its first three
    # full-table iterations from the coarse test's κ 100, against the κ = 0 optimum's loss 3.36204e-7 (gain 22.7 %,
    # changes shrinking at ρ 0.3: the rest is ~1e-4, far from the 25 % that keeps κ; it crawled on to 23.6 % in 17 more)
    history = [{"loss": 2.59982e-7, "rel_change": 1.39e-3}, {"loss": 2.59816e-7, "rel_change": 6.38e-4},
               {"loss": 2.59767e-7, "rel_change": 1.89e-4}]
    polish = first_of(settled(1e-3, 0.1), clearly_below(0.25, 1e-12, reference=3.36204e-7))
    assert not polish(2.60344e-7, history[:2])  # no rate before the third iteration
    assert polish(2.60344e-7, history)
    assert not settled(1e-3, 0.1)(2.60344e-7, history)  # the tolerance test alone would not stop it (ρ 0.3)
    # the same descent from a κ = 0 optimum it already beats by 27 %: never stopped by the gain test
    assert not first_of(clearly_below(0.25, 1e-12, reference=3.56e-7))(2.60344e-7, history)
    assert not first_of()(1.0, history)  # no test: never stops


def test_trimmed_gain_is_measured_against_a_floor() -> None:
    # noise-free data: per-pixel losses of 1e-34 are rounding; their ratio is no gain (it read −2.6e10 %)
    base = torch.full((100,), 1e-34, dtype=torch.float64)
    trial = base * torch.linspace(0.0, 3.0, 100, dtype=torch.float64)
    assert abs(trimmed_gain(base, trial)) > 0.1  # the raw ratio: rounding read as a gain or a loss
    assert abs(trimmed_gain(base, trial, floor=1e-8)) < 1e-20
    assert trimmed_gain(0.95 * torch.ones(100, dtype=torch.float64) + 0.05, 0.95 * torch.ones(100, dtype=torch.float64),
                        floor=1e-8) == pytest.approx(0.05)  # a floor under the losses changes nothing


def test_trimmed_gain_leaves_out_a_gain_carried_by_a_few_pixels() -> None:
    base = torch.ones(200, dtype=torch.float64)
    few = base.clone()
    few[:2] = 0.0  # two pixels explained, the rest slightly worse: 1 % gain in all, none without them
    few[2:] = 1.0001
    assert (base.sum() - few.sum()) / base.sum() > 0.009
    assert trimmed_gain(base, few) < 0.0
    broad = 0.95 * base  # every pixel 5 % better
    assert trimmed_gain(base, broad) == pytest.approx(0.05)


@pytest.mark.slow
def test_kappa_is_dropped_on_a_shiny_kappa_free_sphere() -> None:
    # 40² α 0.03 sphere, true κ 0: two highlight pixels let κ trade with α for a > 1 % gain (κ 100
    # was kept); without the 2 % of pixels that gain most the gain is gone
    from test_normals import _recover, _simulate

    result = _recover(_simulate("sphere", 40, 0.03, exposure_us=1000.0), solver="joint")
    said = [s for s in result.skipped if "kappa:" in s]
    assert result.params["kappa"] == 0.0 and len(said) == 1 and "nested" in said[0], result.skipped


@pytest.mark.slow
def test_nested_kappa_second_start_stops_once_its_gain_clearly_ends_below_the_decision(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # κ-free data; the κ = 0 solve came from far (α ×4: cornered) and κ does not pay from its optimum, so
    # the κ fit starts again from there. That second start stays above the optimum's loss: with the
    # decision's gain given it stops as soon as it clearly ends below it — fewer iterations (table
    # builds), and the same fit, gain and (dropped) decision as run to its end
    import polarshape.recover.joint_solve as js

    inputs, truth = _sphere_inputs(10)
    m = inputs.mask
    obs = flatten_observations(inputs, m)
    kw = {"delta": 1e-3, "n_grid": 33, "jac_grid": 17}
    far = FMBRDFParams(ior=1.5, alpha=1.2, beta=2.0)
    base = joint_solve(truth[m], obs, FMBRDFParams(ior=1.5, alpha=0.3, beta=2.0), names=("ior", "alpha", "beta"),
                       max_iter=3, **kw)
    base = replace(base, start_params=far)
    solve = js.joint_solve
    out = {}
    for decide in (None, 0.25):
        iterations: list[int] = []

        def counted(*args: object, **kwargs: object) -> js.JointResult:
            fit = solve(*args, **kwargs)  # type: ignore[arg-type]
            iterations.append(fit.iterations)
            return fit

        monkeypatch.setattr(js, "joint_solve", counted)
        fit, gain = nested_kappa(base, obs, names=("ior", "alpha", "beta"), max_iter=20, decide_gain=decide, **kw)
        out[decide] = (iterations, fit.loss, fit.params.kappa, gain)
    (runs, loss, kappa, gain), (runs_stop, loss_stop, kappa_stop, gain_stop) = out[None], out[0.25]
    assert len(runs) == len(runs_stop) == 2, out  # the second start ran in both
    assert runs_stop[1] < runs[1], out
    assert (loss_stop, kappa_stop, gain_stop) == (loss, kappa, gain) and gain < 0.25, out
