"""Objects of several materials: how many, which pixel is which, and each one's parameters.

A layer around the one-material solve (:func:`polarshape.recover.coarse_to_fine.solve_fmbrdf`):

1. **one material** — today's solve; with ``recovery.materials: 1`` it is the answer, unchanged;
2. **split** — the material that explains its pixels worst is split in two, started from the two
   lobe widths that explain its pixels best between them (:func:`_start_pair`: glossy and matte
   parts differ first in the lobe). **Early test** (``auto`` only): the two start lobes label the
   pixels at the held normals (Potts ICM, no re-fit, no normal refinement, coarse tables); when a
   part holds less than :data:`MIN_PART_FRACTION` of the pixels, one lobe explains (almost) every
   pixel and the split is refused there — what a one-material object pays for the test (measured:
   2 % of the one-material solve at 80², :data:`START_TABLE_GRID`). Otherwise the split alternates
   :data:`SPLIT_ROUNDS` times: every pixel's normal refined under each material (a few LM
   iterations from the one-material normal), the pixel given the material whose loss
   (:meth:`polarshape.recover.normal_solver.NormalProblem.pixel_loss`, its albedo solved in closed
   form) is lowest under a Potts prior (:func:`potts_icm`: neighbours tend to share a material),
   each new material re-fitted on its pixels (:func:`polarshape.recover.reflectometry.fit_reflectance`).
   The split is done on a lattice of at most :data:`SELECTION_PIXELS` pixels (every s-th row and
   column: the neighbourhood is kept);
3. **model choice** (``auto``) — held-out lights: the lights are halved (alternate lights); each
   half labels the pixels (Potts ICM) with the candidate materials, and the labels are scored by
   the negative log-likelihood (Huber loss / σ², σ = the Huber δ / 3 of the one-material fit) of
   the *other* half (:func:`_held_out_nll`). The split is kept when it lowers that held-out
   negative log-likelihood by at least :data:`MIN_HELD_OUT_GAIN` of it, its in-sample gain (NLL plus
   Potts energy) exceeds a BIC term, ½ · 5 · ln(observations) for the 5 parameters (μ, α, β, κ,
   k_s) of the new material, each part holds at least :data:`MIN_PART_FRACTION` of the pixels and
   no material is at the limits of the fit (:func:`_bound_hits`); then the next split is tried (at
   most :data:`MAX_MATERIALS`). A number ``N`` splits until there are N materials, whatever the
   gain. A refinement that ends with a material at the limits of the fit falls back to one material;
4. **refinement** (M ≥ 2) — rounds of: each material and its pixels' normals solved on its own
   region (``solve_fmbrdf`` with the material as a start), then every pixel's normal refined under
   every material and the pixels reassigned (Potts ICM): labels are revisited as the normals
   improve; until a round reassigns at most :data:`STABLE_FRACTION` of the pixels (at most
   :data:`REFINE_ROUNDS`).

**Mixed pixels**: a super-pixel on a material edge sees two materials at once. Pixels with an
8-neighbour of another material are marked (``mixed``, ``mixed.png``) and left out of every
material fit; their normal is the one of the material that explains them best.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.brdf.fmbrdf import FMBRDFTables
from polarshape.brdf.params import FMBRDFParams
from polarshape.recover.coarse_to_fine import (
    FMBRDFState, KnownMaterial, SolveLog, TableCache, fit_albedo_scale, solve_fmbrdf,
)
from polarshape.recover.normal_solver import NormalProblem, huber_delta, refine_normals
from polarshape.recover.observations import Observations, RecoveryInputs, flatten_observations
from polarshape.recover.options import MAX_MATERIALS, RecoveryOptions
from polarshape.recover.reflectometry import ALPHA_GRID, fit_reflectance
from polarshape.recover.selfcheck import parameters_at_bounds

logger = logging.getLogger(__name__)

__all__ = [
    "MaterialsState", "boundary_pixels", "material_tables", "pixel_losses", "potts_energy", "potts_icm",
    "region_inputs", "select_materials", "solve_materials",
]

#: Assign / re-fit alternations of one split (on the lattice).
SPLIT_ROUNDS = 2
#: Most solve-and-reassign rounds once M ≥ 2 is chosen (fewer when the labels hold).
REFINE_ROUNDS = 3
#: The labels hold when a round reassigns at most this fraction of the pixels.
STABLE_FRACTION = 0.005
#: Potts weight: the negative log-likelihood a pixel pays per 8-neighbour of another material.
POTTS_WEIGHT = 2.0
#: A split is kept only when each part holds at least this fraction of the object's pixels.
MIN_PART_FRACTION = 0.03
#: Most pixels of the lattice the split and the model choice see.
SELECTION_PIXELS = 1024
#: Most pixels (a lattice) whose one-material residuals give the Huber δ and σ² of the selection: the
#: residuals' robust σ is a median over ~K·3 values a pixel, so a lattice gives it to < 1 % without
#: rendering every pixel of a large frame again.
DELTA_PIXELS = 16384
#: Parameters a material adds to the model (μ, α, β, κ, k_s): the BIC term's count.
MATERIAL_PARAMETERS = 5
#: A split is kept only when it lowers the held-out-light negative log-likelihood
#: (:func:`_held_out_nll`) by at least this fraction. The BIC term alone assumes the model is right,
#: and a one-material fit's model error (another BRDF than the FMBRDF, demosaicing at edges, grazing
#: light) can always be bought down in-sample by one more "material"; held out, such a material
#: predicts much less, a real one about as much. Measured (README, "several materials"): true splits
#: hold out 0.64 (the two-material blob), spurious ones 0.18 and below (Baek's pBRDF spheres, a Baek
#: blob), one-material captures ≈ 0 or refused by the early test.
MIN_HELD_OUT_GAIN = 0.4
#: Each half of the lights holds at least this many (fewer lights: the in-sample relative gain decides).
MIN_HALF_LIGHTS = 2
#: LM iterations of each pixel's normal under each candidate material during a split.
SPLIT_LM_ITERATIONS = 3
#: Table resolution (``n_grid`` of :func:`polarshape.brdf.build_tables`) of the start lobes: they only
#: choose the start (the split's re-fits use 33 too), and seven tables at full resolution would be
#: most of the cost of the model choice on a one-material object.
START_TABLE_GRID = 33
#: ICM sweeps of one labelling.
ICM_SWEEPS = 6

_KERNEL_8 = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])


@dataclass(frozen=True)
class MaterialsState:
    """A solution with M materials on one grid (H, W).

    Attributes:
        params: the M materials.
        labels: (H, W) int64 material of each pixel, −1 outside the mask.
        mixed: (H, W) bool pixels on a material edge (left out of the material fits).
        normals: (H, W, 3) unit normals, NaN outside the mask.
        k_b: (H, W) body albedo, NaN outside the mask.
        selection: one record per split tried (M, gain, penalty, kept).
    """

    params: list[FMBRDFParams]
    labels: Tensor
    mixed: Tensor
    normals: Tensor
    k_b: Tensor
    selection: list[dict]

    def largest(self) -> int:
        """The material with the most pixels (the one of the run's top-level ``params``)."""
        sizes = [int((self.labels == m).sum()) for m in range(len(self.params))]
        return max(range(len(sizes)), key=lambda m: sizes[m])

    def material_state(self, m: int) -> FMBRDFState:
        """Material ``m`` as a one-material state (normals and k_b NaN off its pixels)."""
        sel = self.labels == m
        nan = torch.full_like(self.k_b, math.nan)
        return FMBRDFState(self.params[m], torch.where(sel[..., None], self.normals, nan[..., None]),
                           torch.where(sel, self.k_b, nan))


def material_tables(p: FMBRDFParams, device: torch.device, cache: TableCache | None = None, n_grid: int = 65
                    ) -> FMBRDFTables:
    """The fast evaluator's tables of ``p`` (:func:`polarshape.brdf.build_tables`, ``n_grid``), taken
    from and kept in the run's ``cache`` (:class:`polarshape.recover.coarse_to_fine.TableCache`, keyed
    by (μ, α, β, κ, n_grid)) when one is given: the model choice scores the same materials many
    times, the one-material solve has built the first one, and building tables is most of the
    model choice's cost on a one-material object."""
    return p.build_tables(device=device, n_grid=n_grid) if cache is None else cache.get(p, device, n_grid)


def pixel_losses(materials: list[FMBRDFParams], normals: Tensor, obs: Observations, *, per_pixel_albedo: bool,
                 polarised: bool, delta: float, cache: TableCache | None = None, n_grid: int = 65) -> Tensor:
    """(M, P) robust loss of each of P pixels (normals (P, 3) held) under each material, its body
    albedo solved in closed form (:meth:`NormalProblem.pixel_loss`); ``cache``, ``n_grid``: see
    :func:`material_tables`."""
    out = []
    for p in materials:
        problem = NormalProblem.build(material_tables(p, normals.device, cache, n_grid), obs.stokes, p.k_s, per_pixel_albedo,
                                      p.k_b, polarised, delta)
        out.append(problem.pixel_loss(normals, obs))
    return torch.stack(out)


def _neighbour_counts(labels: Tensor, pixels: Tensor, m: int) -> Tensor:
    """(M, H, W) how many of each pixel's 8 neighbours inside ``pixels`` carry each of ``m`` labels."""
    onehot = F.one_hot(labels.clamp_min(0), m).permute(2, 0, 1).to(torch.float32)  # (M, H, W)
    onehot = onehot * pixels.to(onehot.dtype)
    kernel = _KERNEL_8.to(onehot.device).expand(m, 1, 3, 3)
    return F.conv2d(onehot.unsqueeze(0), kernel, padding=1, groups=m)[0]


def potts_icm(costs: Tensor, pixels: Tensor, weight: float, labels: Tensor | None = None,
              sweeps: int = ICM_SWEEPS) -> Tensor:
    """Labels minimising Σ cost + ``weight`` · (8-neighbour pairs of different labels), by iterated
    conditional modes in four interleaved phases (pixels of one phase are never neighbours).

    Args:
        costs: (M, H, W) cost of each label at each pixel (negative log-likelihood).
        pixels: (H, W) bool pixels to label.
        weight: Potts weight per disagreeing neighbour.
        labels: (H, W) start (default: each pixel's cheapest label).

    Returns:
        (H, W) int64 labels, −1 outside ``pixels``.
    """
    m, h, w = costs.shape
    lab = costs.argmin(0) if labels is None else labels.clamp_min(0).clone()
    if m > 1:
        yy, xx = torch.meshgrid(torch.arange(h, device=costs.device), torch.arange(w, device=costs.device),
                                indexing="ij")
        phase = 2 * (yy % 2) + (xx % 2)
        for _ in range(sweeps):
            before = lab.clone()
            for ph in range(4):
                counts = _neighbour_counts(lab, pixels, m).to(costs.dtype)  # (M, H, W)
                energy = costs + weight * (counts.sum(0, keepdim=True) - counts)
                upd = pixels & (phase == ph)
                lab = torch.where(upd, energy.argmin(0), lab)
            if bool((lab == before).all()):
                break
    return torch.where(pixels, lab, torch.full_like(lab, -1))


def potts_energy(labels: Tensor, pixels: Tensor) -> float:
    """Number of 8-neighbour pairs inside ``pixels`` (H, W) with different ``labels`` (H, W)."""
    m = int(labels.max()) + 1 if bool(pixels.any()) else 1
    counts = _neighbour_counts(labels, pixels, max(m, 1))
    same = counts.gather(0, labels.clamp_min(0).unsqueeze(0))[0]
    differ = (counts.sum(0) - same)[pixels]
    return float(differ.sum()) / 2.0


def boundary_pixels(labels: Tensor, pixels: Tensor) -> Tensor:
    """(H, W) bool: pixels with an 8-neighbour inside ``pixels`` of another label (a material edge)."""
    m = int(labels.max()) + 1 if bool(pixels.any()) else 1
    if m <= 1:
        return torch.zeros_like(pixels)
    counts = _neighbour_counts(labels, pixels, m)
    same = counts.gather(0, labels.clamp_min(0).unsqueeze(0))[0]
    return pixels & (counts.sum(0) - same > 0)


def _lattice(mask: Tensor, most: int) -> tuple[slice, slice]:
    """Every s-th row and column, s the smallest stride leaving ≤ ``most`` mask pixels."""
    stride = max(1, math.ceil(math.sqrt(int(mask.sum()) / most)))
    return slice(0, None, stride), slice(0, None, stride)


def _lattice_observations(inputs: RecoveryInputs, rows: slice, cols: slice) -> tuple[Tensor, Observations]:
    """The lattice's mask (h, w) and the observations of its mask pixels (row-major)."""
    lat = inputs.mask[rows, cols]
    lat_inputs = replace(inputs, stokes=inputs.stokes[..., rows, cols], valid=inputs.valid[:, rows, cols],
                         saturated=inputs.saturated[:, rows, cols], mask=lat, lights=inputs.lights[:, rows, cols],
                         irradiance=inputs.irradiance[:, rows, cols], view=inputs.view[rows, cols])
    return lat, flatten_observations(lat_inputs, lat)


@dataclass
class _Grid:
    """The split's working data: a lattice of the object, its normals of the one-material fit."""

    pixels: Tensor  # (h, w) bool
    obs: Observations  # of the P pixels, row-major
    normals: Tensor  # (P, 3)
    per_pixel: bool
    polarised: bool
    delta: float
    sigma2: float
    options: RecoveryOptions
    seed: int
    tables: TableCache = field(default_factory=TableCache)  # the run's tables (:func:`material_tables`)

    def losses(self, materials: list[FMBRDFParams], normals: Tensor, keep: Tensor | None = None) -> Tensor:
        """(M, h, w) negative log-likelihood of each pixel under each material at held ``normals``
        (P, 3) or (M, P, 3) (+inf off the pixels), of the lights ``keep`` (K,) bool only if given."""
        obs = self.obs
        if keep is not None:
            obs = replace(obs, weight=obs.weight * keep.to(obs.weight.dtype))
        out = torch.full((len(materials), *self.pixels.shape), math.inf, dtype=self.normals.dtype,
                         device=self.normals.device)
        for m, p in enumerate(materials):
            n = normals if normals.dim() == 2 else normals[m]
            out[m, self.pixels] = pixel_losses([p], n, obs, per_pixel_albedo=self.per_pixel, polarised=self.polarised,
                                               delta=self.delta, cache=self.tables)[0] / self.sigma2
        return out

    def costs(self, materials: list[FMBRDFParams]) -> tuple[Tensor, Tensor]:
        """(M, h, w) negative log-likelihood of each pixel under each material (+inf off the pixels),
        each pixel's normal refined under that material (a few LM iterations from the held normal:
        a material is judged at its own best normal, not at one biased by another), and those
        normals (M, P, 3)."""
        out = torch.full((len(materials), *self.pixels.shape), math.inf, dtype=self.normals.dtype,
                         device=self.normals.device)
        normals = []
        for m, p in enumerate(materials):
            problem = NormalProblem.build(material_tables(p, self.normals.device, self.tables), self.obs.stokes,
                                          p.k_s, self.per_pixel, p.k_b, self.polarised, self.delta)
            n_m, _, loss, _ = refine_normals(problem, self.normals, self.obs, max_iter=SPLIT_LM_ITERATIONS)
            out[m, self.pixels] = loss / self.sigma2
            normals.append(n_m)
        return out, torch.stack(normals)

    def label(self, materials: list[FMBRDFParams], start: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Potts-ICM labels (h, w) and the normals (M, P, 3) each material gave the pixels."""
        costs, normals = self.costs(materials)
        return potts_icm(costs, self.pixels, POTTS_WEIGHT, start), normals

    def fit(self, init: FMBRDFParams, sel: Tensor, normals: Tensor) -> FMBRDFParams:
        """Material re-fitted on the lattice pixels ``sel`` (P,) bool at ``normals`` (P, 3)."""
        idx = torch.nonzero(sel).flatten()
        if idx.numel() < 16:
            return init
        if idx.numel() > self.options.subsample_pixels:
            gen = torch.Generator().manual_seed(self.seed)
            idx = idx[torch.randperm(idx.numel(), generator=gen)[: self.options.subsample_pixels].to(idx.device)]
        n, obs = normals[idx], self.obs.select(idx)
        init = fit_albedo_scale(n, obs, init, per_pixel_albedo=self.per_pixel, polarised=self.polarised)
        fit = fit_reflectance(n, obs, init=init, per_pixel_albedo=self.per_pixel,
                              fit_kappa=bool(self.options.fit_kappa) or init.kappa > 0, polarised=self.polarised,
                              delta=self.delta, grid_search=False, max_iter=4, n_grid=33)
        return fit.params


def _energy(costs: Tensor, labels: Tensor, pixels: Tensor) -> float:
    """Σ NLL of each pixel's label + Potts weight · disagreeing neighbour pairs."""
    nll = float(costs.gather(0, labels.clamp_min(0).unsqueeze(0))[0][pixels].sum())
    return nll + POTTS_WEIGHT * potts_energy(labels, pixels)


def _start_pair(grid: _Grid, base: FMBRDFParams, sel: Tensor) -> tuple[FMBRDFParams, FMBRDFParams, Tensor]:
    """The two lobes that start a split of ``base`` on the lattice pixels ``sel`` (P,) bool: of the
    lobe widths of :data:`polarshape.recover.reflectometry.ALPHA_GRID` (μ, β, κ of ``base``, albedos
    solved on ``sel``), the pair whose better member explains the pixels best at the held normals —
    wherever the one-material compromise landed (measured: at α 0.52 on a blob of α 0.08 and
    0.45, at the bound 0.01 on a sphere cap of the same two). Also returns the pair's (2, S) losses
    of the S pixels of ``sel`` at the held normals (the early test of :func:`_split`)."""
    n, obs = grid.normals[sel], grid.obs.select(sel)
    lobe_tables = TableCache(len(ALPHA_GRID))  # used by the start only: kept out of the run's tables
    starts = []
    for a in ALPHA_GRID:
        lobe = replace(base, alpha=a)
        starts.append(fit_albedo_scale(n, obs, lobe, per_pixel_albedo=grid.per_pixel, polarised=grid.polarised,
                                       tables=material_tables(lobe, n.device, lobe_tables, START_TABLE_GRID)))
    loss = pixel_losses(starts, n, obs, per_pixel_albedo=grid.per_pixel, polarised=grid.polarised,
                        delta=grid.delta, cache=lobe_tables, n_grid=START_TABLE_GRID)  # (A, S)
    pairs = [(i, j) for i in range(len(starts)) for j in range(i + 1, len(starts))]
    i, j = min(pairs, key=lambda ij: float(torch.minimum(loss[ij[0]], loss[ij[1]]).sum()))
    return starts[i], starts[j], loss[[i, j]]


@dataclass
class _Trial:
    """One split tried (:func:`_split`): its materials, and — unless the early test refused it —
    its labels (h, w), energy, costs (M, h, w) and each material's normals (M, P, 3)."""

    materials: list[FMBRDFParams]
    early_sizes: list[int]
    early_gain: float
    labels: Tensor | None = None
    energy: float = math.nan
    costs: Tensor | None = None
    normals: Tensor | None = None


def _split(grid: _Grid, materials: list[FMBRDFParams], labels: Tensor, costs: Tensor, target: int, early: bool
           ) -> _Trial:
    """Material ``target`` split in two (module docstring, step 2); ``costs`` (M, h, w): the current
    materials'. ``early``: stop after the early test when the two start lobes, at the held
    normals, leave a part below :data:`MIN_PART_FRACTION` of the pixels (``labels`` then None).
    The early test's in-sample gain is recorded, not used."""
    sel = labels[grid.pixels] == target
    narrow, wide, start_loss = _start_pair(grid, materials[target], sel)
    trial = [*materials[:target], narrow, *materials[target + 1:], wide]
    new = len(trial) - 1
    smallest = MIN_PART_FRACTION * int(grid.pixels.sum())
    # the early test: the two start lobes at the held normals (no refit, no normal refinement)
    region = torch.zeros_like(grid.pixels)
    region[grid.pixels] = sel
    start = torch.full((2, *grid.pixels.shape), math.inf, dtype=start_loss.dtype, device=start_loss.device)
    start[:, region] = start_loss / grid.sigma2
    lab0 = potts_icm(start, region, POTTS_WEIGHT)
    early_sizes = [int((lab0 == 0).sum()), int((lab0 == 1).sum())]
    early_gain = float(costs[target][region].sum()) - _energy(start, lab0, region)
    out = _Trial(trial, early_sizes, early_gain)
    if early and min(early_sizes) < smallest:
        return out
    lab = None
    for rnd in range(SPLIT_ROUNDS):
        lab, normals = grid.label(trial, lab)
        inner = ~boundary_pixels(lab, grid.pixels)[grid.pixels]
        flat = lab[grid.pixels]
        sizes = [int((flat == m).sum()) for m in (target, new)]
        logger.debug("materials: split of %d, round %d: parts %s", target, rnd, sizes)
        if min(sizes) < smallest:  # one start explains (almost) nothing: no second material here
            break
        for m in (target, new):
            trial[m] = grid.fit(trial[m], (flat == m) & inner, normals[m])
    out.costs, out.normals = grid.costs(trial)
    out.labels = potts_icm(out.costs, grid.pixels, POTTS_WEIGHT, lab)
    out.energy = _energy(out.costs, out.labels, grid.pixels)
    return out


def _light_halves(k: int, device: torch.device) -> list[Tensor] | None:
    """Two complementary halves of the K lights, alternate lights (each half spans the rig as the
    capture orders it): (K,) bool each; None with fewer than 2 · :data:`MIN_HALF_LIGHTS` lights."""
    if k < 2 * MIN_HALF_LIGHTS:
        return None
    even = torch.arange(k, device=device) % 2 == 0
    return [even, ~even]


def _cross_scored(per_half: list[Tensor], pixels: Tensor) -> float:
    """Σ over the two halves h of the NLL ``per_half[h]`` (M, h, w) at the labels (Potts ICM) that
    the other half's costs choose, over ``pixels`` (h, w)."""
    chosen = [potts_icm(c, pixels, POTTS_WEIGHT) for c in per_half]
    return sum(float(per_half[h].gather(0, chosen[1 - h].clamp_min(0).unsqueeze(0))[0][pixels].sum())
               for h in range(2))


def _held_out_nll(grid: _Grid, materials: list[FMBRDFParams], normals: Tensor, halves: list[Tensor]) -> float:
    """Held-out-light negative log-likelihood of a labelling model: for each half of the lights,
    the pixels labelled (Potts ICM) from the other half alone, then scored on this half; summed.

    The materials and each material's normals (M, P, 3) are held: what is held out is the choice of
    which pixel is which material — the freedom a spurious split buys its gain with. A real material
    is a property of the surface: the lights that did not choose it see it too. A "material" that
    stands for model error (another BRDF) follows where the lights put the error, and predicts the
    other lights less well."""
    return _cross_scored([grid.losses(materials, normals, keep) for keep in halves], grid.pixels)


def _bound_hits(materials: list[FMBRDFParams]) -> list[str]:
    """Parameters of ``materials`` at the limits of the fit (k_s 0 aside: a matte part has none).

    A split that only pays with a material at a bound explains a failure of the one-material model
    (light directions flipped, another BRDF) rather than a second material (measured: y-flipped
    lights on a sphere, relative gain 55 %)."""
    return [f"material {m}: {hit}" for m, p in enumerate(materials)
            for hit in parameters_at_bounds(p.as_dict()) if not hit.startswith("k_s")]


def _select(grid: _Grid, first: FMBRDFParams, wanted: int | None, log: SolveLog
            ) -> tuple[list[FMBRDFParams], list[dict]]:
    """Step 2–3 of the module docstring on the lattice: the materials (one or more) and the record."""
    materials = [first]
    normals = grid.normals.unsqueeze(0)  # (M, P, 3) each material's normals
    # the one material at its own converged normals (refining them again would gain nothing)
    costs = grid.losses(materials, grid.normals)
    labels = torch.where(grid.pixels, 0, -1)
    energy = float(costs[0][grid.pixels].sum())
    n_obs = float((grid.obs.weight > 0).sum()) * (3 if grid.polarised else 1)
    penalty = 0.5 * MATERIAL_PARAMETERS * math.log(max(n_obs, 2.0))
    halves = _light_halves(grid.obs.weight.shape[1], grid.normals.device)
    held: float | None = None  # the current model's held-out NLL (computed when a split needs it)
    p = int(grid.pixels.sum())
    records: list[dict] = []
    limit = MAX_MATERIALS if wanted is None else wanted
    while len(materials) < limit:
        own = costs.gather(0, labels.clamp_min(0).unsqueeze(0))[0]  # (h, w) each pixel's NLL
        share = [float(own[(labels == m) & grid.pixels].sum()) for m in range(len(materials))]
        target = max(range(len(materials)), key=lambda m: share[m])
        t = _split(grid, materials, labels, costs, target, early=wanted is None)
        record: dict = {"materials": len(t.materials), "split": target, "energy": energy, "penalty": penalty,
                        "early_sizes": t.early_sizes, "early_relative_gain": t.early_gain / max(energy, 1e-30),
                        "alpha": [m.alpha for m in t.materials], "ior": [m.ior for m in t.materials]}
        if t.labels is None:  # refused by the early test
            record.update(kept=False, decided="early")
            records.append(record)
            why = (f"the two start lobes leave a part below {100 * MIN_PART_FRACTION:g} % of the pixels "
                   f"(parts {t.early_sizes} lattice pixels, early test)")
            logger.info("materials: split of material %d refused early: parts %s", target, t.early_sizes)
            log.skipped.append(f"materials: a split into {len(t.materials)} materials does not pay ({why}): "
                               f"{len(materials)} material(s)")
            break
        sizes = [int(((t.labels == m) & grid.pixels).sum()) for m in range(len(t.materials))]
        gain = energy - t.energy
        big_enough = min(sizes) >= MIN_PART_FRACTION * p
        if halves is not None:
            held = _held_out_nll(grid, materials, normals, halves) if held is None else held
            held_after = _held_out_nll(grid, t.materials, t.normals, halves)
            decision = (held - held_after) / max(held, 1e-30)
        else:  # too few lights to hold half out: the in-sample gain decides
            held_after, decision = math.nan, gain / max(energy, 1e-30)
        pays = gain > penalty and decision > MIN_HELD_OUT_GAIN
        bounds = _bound_hits([t.materials[target], t.materials[-1]])
        keep = wanted is not None or (pays and big_enough and not bounds)
        record.update({"gain_nll": gain, "relative_gain": gain / max(energy, 1e-30), "held_out_nll": held,
                       "held_out_gain": decision, "sizes": sizes, "at_bounds": bounds, "kept": keep,
                       "decided": "held-out" if halves is not None else "in-sample"})
        records.append(record)
        logger.info("materials: split of material %d: energy %.4g, gain %.4g (penalty %.4g, relative %.3g), held-out "
                    "gain %.3g, parts %s, alpha %s: %s", target, energy, gain, penalty, gain / max(energy, 1e-30),
                    decision, sizes, [round(m.alpha, 3) for m in t.materials], "kept" if keep else "not kept")
        if not keep:
            why = ("too small a part" if not big_enough else "gain below the penalty" if gain <= penalty
                   else f"held-out-light gain {decision:.3g} below {MIN_HELD_OUT_GAIN:g}" if not pays
                   else f"a new material at the limits of the fit ({', '.join(bounds)}): the model failing, not a "
                   "material")
            log.skipped.append(f"materials: a split into {len(t.materials)} materials does not pay (negative "
                               f"log-likelihood gain {gain:.4g} of {energy:.4g}, penalty {penalty:.4g}, held-out-light "
                               f"gain {decision:.3g}, parts {sizes} lattice pixels: {why}): "
                               f"{len(materials)} material(s)")
            break
        materials, labels, energy, costs, normals = t.materials, t.labels, t.energy, t.costs, t.normals
        held = held_after if halves is not None else None
    return materials, records


def region_inputs(inputs: RecoveryInputs, region: Tensor) -> RecoveryInputs:
    """The inputs seen through ``region`` (H, W) bool: only its pixels are in the mask."""
    return replace(inputs, mask=region, valid=inputs.valid & region.unsqueeze(0))


def _reassign(inputs: RecoveryInputs, materials: list[FMBRDFParams], normals: Tensor, labels: Tensor | None,
              options: RecoveryOptions, delta: float, sigma2: float, tables: TableCache | None = None
              ) -> tuple[Tensor, Tensor, Tensor]:
    """Every pixel's normal refined under every material; pixels reassigned by Potts ICM (``tables``:
    the run's, :func:`material_tables`).

    Returns normals (H, W, 3), k_b (H, W), labels (H, W) (−1 off the mask)."""
    pixels = inputs.mask
    obs = flatten_observations(inputs, pixels)
    n0 = normals[pixels]
    polarised = inputs.has_polarisation
    cand_n, cand_kb, cand_loss = [], [], []
    for p in materials:
        problem = NormalProblem.build(material_tables(p, n0.device, tables), obs.stokes, p.k_s,
                                      options.per_pixel_albedo, p.k_b, polarised, delta)
        n_m, kb_m, loss_m, _ = refine_normals(problem, n0, obs, max_iter=6)
        cand_n.append(n_m)
        cand_kb.append(kb_m)
        cand_loss.append(loss_m / sigma2)
    costs = torch.full((len(materials), *pixels.shape), math.inf, dtype=n0.dtype, device=n0.device)
    costs[:, pixels] = torch.stack(cand_loss)
    labels = potts_icm(costs, pixels, POTTS_WEIGHT, labels)
    pick = labels[pixels]  # (P,)
    n_all = torch.stack(cand_n)  # (M, P, 3)
    kb_all = torch.stack(cand_kb)  # (M, P)
    ar = torch.arange(pick.numel(), device=pick.device)
    out_n = torch.full_like(normals, math.nan)
    out_n[pixels] = n_all[pick, ar]
    out_kb = torch.full(pixels.shape, math.nan, dtype=n0.dtype, device=n0.device)
    out_kb[pixels] = kb_all[pick, ar]
    return out_n, out_kb, labels


def _drop_empty(materials: list[FMBRDFParams], labels: Tensor, mask: Tensor, log: SolveLog
                ) -> tuple[list[FMBRDFParams], Tensor]:
    """Materials left with fewer than :data:`MIN_PART_FRACTION` of the pixels after a reassignment
    are dropped (their pixels take the remaining material they fit best: the next reassignment)."""
    sizes = [int((labels == m).sum()) for m in range(len(materials))]
    keep = [m for m, n in enumerate(sizes) if n >= MIN_PART_FRACTION * int(mask.sum())]
    if len(keep) == len(materials) or not keep:
        return materials, labels
    log.skipped.append(f"materials: {len(materials) - len(keep)} material(s) lost their pixels to the others "
                       f"once the normals moved (pixels {sizes}): dropped")
    new_index = torch.full((len(materials),), -1, dtype=labels.dtype, device=labels.device)
    new_index[keep] = torch.arange(len(keep), dtype=labels.dtype, device=labels.device)
    relabelled = torch.where(labels >= 0, new_index[labels.clamp_min(0)], labels)
    nearest = keep[0]  # a dropped material's pixels: the first kept one until the next reassignment
    relabelled = torch.where(mask & (relabelled < 0), int(new_index[nearest]), relabelled)
    return [materials[m] for m in keep], relabelled


def select_materials(inputs: RecoveryInputs, state: FMBRDFState, options: RecoveryOptions, *, wanted: int | None,
                     seed: int = 0, log: SolveLog | None = None, tables: TableCache | None = None
                     ) -> tuple[list[FMBRDFParams], list[dict], float, float]:
    """Steps 2–3 of the module docstring: the materials chosen from the one-material ``state``.

    Args:
        inputs: cropped recovery inputs (H, W).
        state: the one-material solve of ``inputs``.
        wanted: a number of materials, or None (``auto``: as many as pay).
        tables: the run's tables (:func:`material_tables`; the solve's holds ``state``'s material).

    Returns:
        the materials (one or more, on the lattice), one record per split tried, the Huber δ and σ²
        of the one-material fit.
    """
    log = SolveLog() if log is None else log
    mask = inputs.mask
    p1 = state.params
    tables = TableCache() if tables is None else tables
    rows, cols = _lattice(mask, DELTA_PIXELS)  # δ from a lattice's residuals (not every pixel rendered again)
    lat_d, obs_d = _lattice_observations(inputs, rows, cols)
    problem = NormalProblem.build(material_tables(p1, mask.device, tables), obs_d.stokes, p1.k_s,
                                  options.per_pixel_albedo, p1.k_b, inputs.has_polarisation, 1.0)
    delta = huber_delta(obs_d, inputs.noise_std, problem.residual(state.normals[rows, cols][lat_d], obs_d)[0])
    sigma2 = (delta / 3.0) ** 2
    rows, cols = _lattice(mask, SELECTION_PIXELS)
    lat, lat_obs = _lattice_observations(inputs, rows, cols)
    grid = _Grid(lat, lat_obs, state.normals[rows, cols][lat],
                 options.per_pixel_albedo, inputs.has_polarisation, delta, sigma2, options, seed, tables)
    materials, records = _select(grid, p1, wanted, log)
    return materials, records, delta, sigma2


def solve_materials(inputs: RecoveryInputs, initial_normals: Tensor, options: RecoveryOptions, *, seed: int = 0,
                    progress: bool = False, log: SolveLog | None = None,
                    material: KnownMaterial | None = None, tables: TableCache | None = None) -> MaterialsState:
    """Materials, their pixels and the normals of ``inputs`` (module docstring).

    Args:
        inputs: cropped recovery inputs (H, W), K lights.
        initial_normals: (H, W, 3) start (robust Lambertian PS).
        options: ``options.materials``: ``"auto"`` or a number of materials.
        material: a known material (``recovery.material``): one material, as given.
        tables: the run's tables (:class:`polarshape.recover.coarse_to_fine.TableCache`), shared by the
            solves, the selection and the caller's render (None: a cache of this call's own).

    Returns:
        :class:`MaterialsState`; with one material, the one-material solve's answer as it is.
    """
    log = SolveLog() if log is None else log
    tables = TableCache() if tables is None else tables
    state, _ = solve_fmbrdf(inputs, initial_normals, options, seed=seed, progress=progress, log=log, material=material,
                            tables=tables)
    mask = inputs.mask
    single = MaterialsState([state.params], torch.where(mask, 0, -1), torch.zeros_like(mask), state.normals,
                            state.k_b, [])
    wanted = None if options.materials == "auto" else int(options.materials)
    if wanted == 1 or not bool(mask.any()):
        return single
    if material is not None:
        log.skipped.append("materials: one material, the known recovery.material")
        return single
    t0 = time.perf_counter()
    with torch.no_grad():
        materials, records, delta, sigma2 = select_materials(inputs, state, options, wanted=wanted, seed=seed, log=log,
                                                             tables=tables)
    log.add_time("materials_selection", t0)
    if len(materials) == 1:
        return replace(single, selection=records)
    # the full grid's labels from the lattice materials, then solve-and-reassign rounds
    t0 = time.perf_counter()
    normals = torch.where(torch.isfinite(state.normals), state.normals, initial_normals)
    with torch.no_grad():
        normals, k_b, labels = _reassign(inputs, materials, normals, None, options, delta, sigma2, tables)
    log.add_time("materials_reassign", t0)
    for rnd in range(REFINE_ROUNDS):
        before = labels
        mixed = boundary_pixels(labels, mask)
        for m in range(len(materials)):
            region = (labels == m) & ~mixed
            if int(region.sum()) < 16:
                continue
            start = torch.where(torch.isfinite(normals), normals, initial_normals)
            st, _ = solve_fmbrdf(region_inputs(inputs, region), start, options, seed=seed + 1 + m, log=log,
                                 material=KnownMaterial(materials[m], "initial"), tables=tables)
            materials[m] = st.params
            normals = torch.where(region[..., None], st.normals, normals)
        t0 = time.perf_counter()
        with torch.no_grad():
            normals, k_b, labels = _reassign(inputs, materials, normals, labels, options, delta, sigma2, tables)
            count = len(materials)
            materials, labels = _drop_empty(materials, labels, mask, log)
        log.add_time("materials_reassign", t0)
        if len(materials) == 1:
            break
        if len(materials) < count:  # renumbered: reassign among the others at the next round
            continue
        sizes = [int((labels == m).sum()) for m in range(len(materials))]
        moved = int(((labels != before) & mask).sum())
        log.history.append({"stage": "materials", "iteration": rnd, "materials": len(materials), "sizes": sizes,
                            "alpha": [p.alpha for p in materials], "ior": [p.ior for p in materials],
                            "pixels_reassigned": moved})
        logger.info("materials round %d: %d materials, sizes %s, %d pixels reassigned, %s", rnd, len(materials),
                    sizes, moved, [p.as_dict() for p in materials])
        if moved <= STABLE_FRACTION * int(mask.sum()):
            break  # the labels hold: the materials were fitted on them
    bounds = _bound_hits(materials)
    if wanted is None and (len(materials) == 1 or bounds):
        if bounds:  # the split's materials ended at the limits of the fit: the one-material answer stands
            log.skipped.append(f"materials: the {len(materials)}-material fit ended at the limits of the model "
                               f"({', '.join(bounds)}): one material kept")
        return replace(single, selection=records)
    mixed = boundary_pixels(labels, mask)
    return MaterialsState(materials, labels, mixed, normals, k_b, records)
