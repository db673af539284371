"""Tests of polarshape.recover.normal_solver: per-pixel Levenberg–Marquardt and neighbour propagation."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from polarshape.metrics import angular_error_deg
from polarshape.brdf.fmbrdf import build_tables, fmbrdf_stokes
from polarshape.recover.normal_solver import NormalProblem, neighbour_index, propagate_normals, refine_normals
from polarshape.recover.observations import Observations


def _sphere_cap(h: int, w: int) -> Tensor:
    """(h, w, 3) unit normals of a sphere cap facing the camera (n_z < 0), ≈ 3° apart."""
    y, x = torch.meshgrid(torch.linspace(-0.35, 0.35, h, dtype=torch.float64),
                          torch.linspace(-0.35, 0.35, w, dtype=torch.float64), indexing="ij")
    return torch.stack([x, y, -(1 - x * x - y * y).sqrt()], -1)


class _Counting(NormalProblem):
    """A NormalProblem that counts the pixels it evaluates."""

    def residual(self, normals: Tensor, obs: Observations) -> tuple[Tensor, Tensor]:
        self.__dict__["evaluated"] = self.__dict__.get("evaluated", 0) + normals.shape[0]
        return super().residual(normals, obs)


def _cap_problem(n: int = 10) -> tuple[_Counting, Observations, Tensor]:
    """Noise-free observations of a sphere cap under 8 lights, the counting problem and the true normals."""
    truth = _sphere_cap(n, n).reshape(-1, 3)
    k = 8
    t = torch.linspace(0.2, 0.9, k, dtype=torch.float64)
    phi = torch.arange(k, dtype=torch.float64) * 2.4
    lights = torch.stack([t.sin() * phi.cos(), t.sin() * phi.sin(), -t.cos()], -1)
    view = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(truth.shape[0], 3)
    material = dict(ior=1.5, alpha=0.3, beta=2.0, kappa=0.0)
    s = fmbrdf_stokes(truth[:, None], lights[None], view[:, None], k_s=1.0, k_b=0.5, **material)
    p = truth.shape[0]
    obs = Observations(s, torch.ones(s.shape[:2], dtype=s.dtype), lights.expand(p, k, 3), torch.ones(p, k, dtype=s.dtype),
                       view)
    base = NormalProblem.build(build_tables(**material), obs.stokes, 1.0, True, 0.5, True, 1e-3)
    return _Counting(**vars(base)), obs, truth


def test_propagation_moves_pixels_out_of_a_wrong_basin() -> None:
    """propagate_normals: pixels started at a wrong normal take their neighbours' and keep the lower loss;
    pixels already right do not move."""
    h = w = 12
    problem, obs, truth = _cap_problem(h)
    truth_img = truth.reshape(h, w, 3)
    pixels = torch.ones(h, w, dtype=torch.bool)
    start_img = truth_img.clone()
    wrong = torch.zeros(h, w, dtype=torch.bool)
    wrong[4:7, 4:7] = True
    start_img[wrong] = torch.nn.functional.normalize(torch.tensor([0.6, 0.5, -0.6], dtype=torch.float64), dim=0)
    normals = start_img[pixels].clone()
    r, k_b = problem.residual(normals, obs)
    loss = problem.loss(r)
    before = loss.clone()
    out, _, loss_out, moved = propagate_normals(problem, normals, k_b, loss, obs, neighbour_index(pixels), max_iter=0)
    err = angular_error_deg(out, truth)
    w_flat = wrong[pixels]
    assert moved >= int(w_flat.sum())
    assert float(err[w_flat].max()) < 10.0  # a neighbour's normal (≈ 3–6° off), not the 40°+ start
    assert float(err[~w_flat].max()) < 1e-9  # right pixels untouched
    assert bool((loss_out <= before).all()) and float(loss_out[w_flat].sum()) < 0.2 * float(before[w_flat].sum())
    # and the polish lands on the truth
    polished, *_ = refine_normals(problem, out.clone(), obs, max_iter=20)
    assert float(angular_error_deg(polished, truth).max()) < 0.05


def test_converged_pixels_are_not_evaluated_again() -> None:
    """A pixel at its optimum costs its residual and the two Jacobian columns — no trial, no second
    iteration; a pixel started near it (0.1°, a finer level's start) ends on the optimum with at most
    one trial, its k_b and loss those of its normal."""
    problem, obs, truth = _cap_problem()
    p = truth.shape[0]
    normals, k_b, loss, _ = refine_normals(problem, truth.clone(), obs, max_iter=10)
    assert problem.evaluated == 3 * p
    assert float(angular_error_deg(normals, truth).max()) < 1e-3
    problem.__dict__["evaluated"] = 0
    tilt = torch.nn.functional.normalize(truth + torch.tensor([1.2e-3, -1.0e-3, 0.0], dtype=torch.float64), dim=-1)
    loss_start = problem.pixel_loss(tilt, obs)
    problem.__dict__["evaluated"] = 0
    normals, k_b, loss, _ = refine_normals(problem, tilt, obs, max_iter=10)
    assert problem.evaluated <= 4 * p, problem.evaluated / p
    assert float(angular_error_deg(normals, truth).max()) < 2e-3
    r, kb_true = NormalProblem.residual(problem, normals, obs)
    assert torch.allclose(k_b, kb_true, rtol=1e-4)
    assert bool(((loss - problem.loss(r)).abs() <= 0.01 * loss_start).all())


def test_far_start_still_converges_with_broyden_updates() -> None:
    """From 10° off, the Jacobian updated from each accepted trial (not re-taken) still leads every pixel
    to the truth, in fewer evaluations than three per iteration."""
    problem, obs, truth = _cap_problem()
    p = truth.shape[0]
    far = torch.nn.functional.normalize(truth + torch.tensor([0.15, 0.08, 0.0], dtype=torch.float64), dim=-1)
    normals, _, _, iterations = refine_normals(problem, far, obs, max_iter=30)
    assert float(angular_error_deg(normals, truth).max()) < 0.01
    assert problem.evaluated < p * (1 + 3 * iterations) * 0.75, (problem.evaluated / p, iterations)
