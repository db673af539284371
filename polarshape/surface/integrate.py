"""Normal integration: a depth map from a camera-frame normal map, orthographic or perspective.

Conventions (spec §1): camera frame x right, y down, z forward; pixel (u, v) = (column, row) with
pixel centres at integer coordinates; normals are unit vectors facing the camera (N·V > 0, so
n_z < 0 under an orthographic camera). Depth z is the camera-frame z coordinate of the surface
point (metres, or whatever unit ``camera.pixel_size_m`` / the scene is in), not the distance along the
ray.

**Camera.** A :mod:`polarshape.cameras` camera at the normal map's grid (for a capture, the
super-pixel camera ``camera.superpixel("centre", pixel_size_m=...)``) says which of the two models below
applies; only :func:`_field_model` tells them apart. Perspective integration uses the pinhole
intrinsics (``camera.matrix``); lens distortion is not modelled here.

**Gradients.** A surface point is P(u, v).
- Orthographic: P = (s·u, s·v, z) with s = ``camera.pixel_size_m`` (metres per pixel). The camera-facing
  normal is ∝ P_v × P_u ∝ (s z_u, s z_v, −s²), so ∂z/∂x = −n_x/n_z = p and ∂z/∂y = −n_y/n_z = q
  (x, y metric, y down); per pixel ∂z/∂u = s·p, ∂z/∂v = s·q.
- Perspective (Cao et al. 2022, "Bilateral Normal Integration", log-depth form): P = z·r with
  r = K⁻¹(u, v, 1)ᵀ (``camera.unproject`` of unit depth). From n·P_u = n·P_v = 0:
  ∂log z/∂u = −n·(K⁻¹e₁)/(n·r) and ∂log z/∂v = −n·(K⁻¹e₂)/(n·r); with zero skew these are
  −n_x/(f_x·n·r) and −n_y/(f_y·n·r).
  n·r < 0 for a camera-facing normal.

**Discretisation.** Every pixel with a right (lower) neighbour in the mask has a forward difference
term and every pixel with a left (upper) neighbour a backward one (no difference crosses the mask
border): E(f) = Σ w⁺ (D⁺f − g)² + w⁻ (D⁻f − g)² over both axes, f = z/s (orthographic, pixel units) or
log z (perspective). The "smooth" method uses w⁺ = w⁻ = ½ (plain least squares); "bilateral"
iterates w⁺ = σ_k((D⁻z̃)² − (D⁺z̃)²), w⁻ = 1 − w⁺ (the paper's sigmoid weights, σ_k(x) = 1/(1+e^(−kx))),
re-solving with the new weights (warm-started) until the relative energy change is below ``tol``
and the weights have settled (``weight_tol``; the energy alone barely moves while a cut starts to form).
z̃ is the depth in units of the pixel footprint, so that k is dimensionless and the same for every
scale: z/s orthographic, and f_x·log z (u) or f_y·log z (v) in perspective (Δz/(z/f) ≈ f·Δlog z).
The normal equations (a weighted graph Laplacian) are solved with scipy.sparse.

**Gauge.** Depth is defined up to an additive constant (orthographic) or a scale (perspective) per
4-connected component of the mask. Each component is fixed independently: if ``depth_init`` has
finite (positive, perspective) values on it, the constant is the median of (depth_init − z)
(orthographic) or of log(depth_init / z) (perspective); otherwise the component's median depth is set
to ``reference_depth``.

**Limits.** Normals only reveal a depth discontinuity through the curl it leaves in the gradient
field, i.e. where the cliff's height varies along it (an occluding contour in front of a tilted
background, a tear that closes somewhere). Two regions whose normals are identical on both sides of
a constant-height step (e.g. two fronto-parallel plateaus) integrate to one continuous surface with
any method. Where the bilateral weights cut a region off completely, its constant comes from the
weak ties left by ``weight_floor``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.ndimage
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.special import expit

from polarshape.cameras import Camera, OrthographicCamera, PerspectiveCamera
from polarshape.checks import to_numpy

logger = logging.getLogger(__name__)

Method = Literal["smooth", "bilateral"]
Solver = Literal["auto", "direct", "cg", "amg"]

_FOUR_CONNECTED = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)
# Below this many unknowns a sparse LU factorisation beats iterative solvers (benchmarks/integration.py).
_DIRECT_MAX_UNKNOWNS = 20_000


def check_normal_map(
    normals: Any, mask: Any | None, *, unit_tol: float = 1e-3
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Validate a normal map and its mask.

    Args:
        normals: (H, W, 3) camera-frame unit normals; values outside the mask are ignored.
        mask: (H, W) bool (or 0/non-zero) object mask; None means "every pixel with finite normals".
        unit_tol: allowed | ‖n‖ − 1 | inside the mask.

    Returns:
        (normals (H, W, 3) float64, mask (H, W) bool).

    Raises:
        ValueError: wrong shapes, an empty mask, non-finite or non-unit normals inside the mask.
    """
    n = to_numpy(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3) (camera-frame unit vectors); got {n.shape}")
    n = n.astype(np.float64, copy=False)
    if mask is None:
        m = np.all(np.isfinite(n), axis=2)
    else:
        m = to_numpy(mask)
        if m.shape != n.shape[:2]:
            raise ValueError(f"mask must have shape (H, W) = {n.shape[:2]} to match normals; got {m.shape}")
        m = m.astype(bool) if m.dtype == bool else m != 0
    if not m.any():
        raise ValueError("mask is empty: no pixel to integrate (check the object mask / normals' NaN pattern)")
    inside = n[m]  # (M, 3)
    bad = ~np.all(np.isfinite(inside), axis=1)
    if bad.any():
        raise ValueError(
            f"normals are NaN/inf at {int(bad.sum())} pixels inside the mask; remove them from the mask "
            "or fill them before integrating"
        )
    err = np.abs(np.linalg.norm(inside, axis=1) - 1.0)
    if err.max() > unit_tol:
        raise ValueError(
            f"normals must be unit vectors inside the mask: max | |n| - 1 | = {err.max():.3g} > {unit_tol:g} "
            f"at {int((err > unit_tol).sum())} pixels; normalise them (n / np.linalg.norm(n, axis=-1, keepdims=True))"
        )
    return n, m


#: Default slope cap: normals tilted more than ≈ 87° from the line of sight (n·r̂ > −0.05) count as
#: grazing, slope ≤ |n_xy| / 0.05 ≈ 20. Such estimates are unreliable (a super-pixel there spans a
#: large depth range) and, uncapped, a handful of them dominates the least-squares integration:
#: measured on a recovered checker-textured sphere (4 such normals among 6520), depth RMS 8.5 mm
#: of a 10 mm range with a cap at 0.001, 0.80 mm at 0.05; ground-truth spheres are unchanged.
GRAZING_EPS = 0.05


class _OrthographicField:
    """Orthographic integration: the field is f = z / s (pixel units), slopes −n_x/n_z, −n_y/n_z.

    Attributes:
        field_scale: s, metres per pixel (a slope in metres per pixel / s = a slope of f).
        axis_scale: (2,) factor turning a difference of f along u / v into pixel-footprint units.
    """

    def __init__(self, camera: OrthographicCamera) -> None:
        self.field_scale = float(camera.pixel_size_m)
        self.axis_scale = np.array([1.0, 1.0])

    def gradients(self, n: NDArray[np.float64], grazing_eps: float) -> tuple[NDArray[np.float64], ...]:
        """(g_u, g_v, clamped), each (H, W), of normals (H, W, 3): see :func:`surface_gradients`."""
        # n·r̂ with r̂ = (0, 0, 1): the denominator is n_z; dz/dx = −n_x/n_z, dz/dy = −n_y/n_z.
        denom = n[..., 2]
        clamped = ~(denom <= -grazing_eps) & np.isfinite(denom)
        denom = np.where(clamped, -grazing_eps, denom)
        g_u = -self.field_scale * n[..., 0] / denom
        g_v = -self.field_scale * n[..., 1] / denom
        return g_u, g_v, clamped

    def facing_away(self, n: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(H, W) normals (H, W, 3) with n·r > 0."""
        return n[..., 2] > 0

    def field_of_depth(self, depth: NDArray[np.float64]) -> NDArray[np.float64]:
        """Field f of depths (n,) (NaN stays NaN)."""
        return depth / self.field_scale

    def depth_of_field(
        self, field: NDArray[np.float64], init_field: NDArray[np.float64], graph: _PixelGraph, reference_depth: float
    ) -> NDArray[np.float64]:
        """(n,) depth of the solved field (n,), one additive constant per component (the gauge rule)."""
        depth_rel = field * self.field_scale  # (n,) z up to a constant
        offsets = init_field * self.field_scale - depth_rel
        return depth_rel + _component_constants(offsets, depth_rel, reference_depth, graph)


class _PerspectiveField:
    """Perspective integration: the field is f = log z, slopes from the pinhole rays r = K⁻¹(u, v, 1).

    Attributes:
        field_scale: 1 (the gradients already are gradients of log z).
        axis_scale: (2,) (f_x, f_y): a difference of log z along u / v in pixel-footprint units.
    """

    def __init__(self, camera: PerspectiveCamera) -> None:
        self.rays = camera.unproject(np.ones((camera.height, camera.width)))  # (H, W, 3) r = K⁻¹(u, v, 1), r_z = 1
        self.k_inv = np.linalg.inv(camera.matrix)  # (3, 3)
        self.field_scale = 1.0
        self.axis_scale = np.array([float(camera.fx), float(camera.fy)])

    def gradients(self, n: NDArray[np.float64], grazing_eps: float) -> tuple[NDArray[np.float64], ...]:
        """(g_u, g_v, clamped), each (H, W), of normals (H, W, 3): see :func:`surface_gradients`."""
        ray_norm = np.linalg.norm(self.rays, axis=-1)  # (H, W)
        n_dot_rhat = np.einsum("hwc,hwc->hw", n, self.rays) / ray_norm
        clamped = ~(n_dot_rhat <= -grazing_eps) & np.isfinite(n_dot_rhat)
        n_dot_r = np.where(clamped, -grazing_eps, n_dot_rhat) * ray_norm  # (H, W)
        # n·P_u = 0 with P_u = z_u r + z K⁻¹e₁  ⇒  ∂log z/∂u = −n·(K⁻¹e₁) / (n·r); same for v.
        g_u = -(n @ self.k_inv[:, 0]) / n_dot_r
        g_v = -(n @ self.k_inv[:, 1]) / n_dot_r
        return g_u, g_v, clamped

    def facing_away(self, n: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(H, W) normals (H, W, 3) with n·r > 0."""
        return np.einsum("hwc,hwc->hw", n, self.rays) > 0

    def field_of_depth(self, depth: NDArray[np.float64]) -> NDArray[np.float64]:
        """Field f = log z of depths (n,); NaN where unknown or not in front of the camera."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(depth > 0, np.log(depth), np.nan)

    def depth_of_field(
        self, field: NDArray[np.float64], init_field: NDArray[np.float64], graph: _PixelGraph, reference_depth: float
    ) -> NDArray[np.float64]:
        """(n,) depth of the solved field (n,), one scale per component (the gauge rule)."""
        return np.exp(field + _component_constants(init_field - field, field, np.log(reference_depth), graph))


_FieldModel = _OrthographicField | _PerspectiveField
_FIELD_MODELS: dict[type, type] = {OrthographicCamera: _OrthographicField, PerspectiveCamera: _PerspectiveField}


def _field_model(camera: Camera, shape: tuple[int, ...]) -> _FieldModel:
    """The integration model of ``camera`` (the one place that tells the projections apart).

    Args:
        camera: a :mod:`polarshape.cameras` camera whose grid is the normal map's.
        shape: (H, W) of the normal map.
    """
    model = _FIELD_MODELS.get(type(camera))
    if model is None:
        raise ValueError(
            "camera must be a polarshape.cameras.OrthographicCamera or PerspectiveCamera at the normal map's "
            f"grid; got {type(camera).__name__}"
        )
    if (camera.height, camera.width) != tuple(shape):
        raise ValueError(
            f"the camera's grid is (H, W) = {(camera.height, camera.width)} but the normal map's is {tuple(shape)}: "
            "pass the camera at the normal map's grid (for a capture: camera.superpixel(...))"
        )
    return model(camera)


def surface_gradients(
    normals: Any, *, camera: Camera, grazing_eps: float = GRAZING_EPS
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Per-pixel gradients of the integrated field, derived from the normals (see module docstring).

    Args:
        normals: (H, W, 3) camera-frame unit normals facing the camera (NaN allowed: gives NaN).
        camera: the camera at the normal map's grid: orthographic (field z, metres) or perspective
            (field log z).
        grazing_eps: normals with n·r̂ > −grazing_eps (grazing or facing away; r̂ the unit ray) are
            clamped to n·r̂ = −grazing_eps, which caps the slope instead of dividing by ~0
            (default :data:`GRAZING_EPS`).

    Returns:
        (g_u, g_v, clamped): g_u = ∂z/∂u, g_v = ∂z/∂v in metres per pixel (orthographic) or
        ∂log z/∂u, ∂log z/∂v per pixel (perspective), each (H, W); clamped (H, W) marks the pixels
        whose denominator was clamped.

    Example:
        >>> n = np.zeros((2, 2, 3)); n[..., 0] = 0.6; n[..., 2] = -0.8   # plane z = 0.75 x + c
        >>> gu, gv, _ = surface_gradients(n, camera=OrthographicCamera(2, 2, even=False))
        >>> round(float(gu[0, 0]), 12), round(float(gv[0, 0]), 12)
        (0.75, 0.0)
    """
    n = to_numpy(normals).astype(np.float64, copy=False)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3); got {n.shape}")
    return _field_model(camera, n.shape[:2]).gradients(n, grazing_eps)


@dataclass(frozen=True)
class _PixelGraph:
    """Masked pixels as graph nodes, 4-neighbour pairs as edges.

    Attributes:
        index: (H, W) int64, node index of each masked pixel, −1 outside.
        tail, head: (E,) node indices of each edge, head = right (u-edges) or lower (v-edges) neighbour.
        axis: (E,) 0 for u-edges, 1 for v-edges.
        incidence: (E, n) sparse, row e = f[head] − f[tail].
        component: (n,) int64 component id (0 … C−1) of each node, 4-connectivity.
        pinned: (C,) one node per component whose value is fixed to 0 while solving.
    """

    index: NDArray[np.int64]
    tail: NDArray[np.int64]
    head: NDArray[np.int64]
    axis: NDArray[np.int64]
    incidence: sp.csr_matrix
    component: NDArray[np.int64]
    pinned: NDArray[np.int64]

    @property
    def n(self) -> int:
        return int(self.component.shape[0])


def _pixel_graph(mask: NDArray[np.bool_]) -> _PixelGraph:
    n = int(mask.sum())
    index = np.full(mask.shape, -1, dtype=np.int64)
    index[mask] = np.arange(n)
    both_u = mask[:, :-1] & mask[:, 1:]
    both_v = mask[:-1, :] & mask[1:, :]
    tail = np.concatenate([index[:, :-1][both_u], index[:-1, :][both_v]])
    head = np.concatenate([index[:, 1:][both_u], index[1:, :][both_v]])
    axis = np.concatenate([np.zeros(int(both_u.sum()), np.int64), np.ones(int(both_v.sum()), np.int64)])
    n_edges = tail.shape[0]
    rows = np.repeat(np.arange(n_edges), 2)
    cols = np.stack([head, tail], axis=1).ravel()
    vals = np.tile([1.0, -1.0], n_edges)
    incidence = sp.csr_matrix((vals, (rows, cols)), shape=(n_edges, n))
    labels, _ = scipy.ndimage.label(mask, structure=_FOUR_CONNECTED)
    component = labels[mask].astype(np.int64) - 1  # (n,)
    # First node of each component (nodes are in raster order).
    _, pinned = np.unique(component, return_index=True)
    return _PixelGraph(index, tail, head, axis, incidence, component, pinned.astype(np.int64))


def _bilateral_weights(
    graph: _PixelGraph, field: NDArray[np.float64], axis_scale: NDArray[np.float64], k: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The paper's one-sided weights, per edge: w⁺ of its tail pixel and w⁻ = 1 − w⁺ of its head pixel.

    Args:
        graph: the pixel graph (n nodes, E edges).
        field: (n,) current field f (z/s orthographic, log z perspective).
        axis_scale: (2,) factor turning a difference of f along u / v into pixel-footprint units.
        k: sigmoid sharpness (dimensionless).

    Returns:
        (w_tail, w_head), each (E,) in [0, 1].
    """
    d = (graph.incidence @ field) * axis_scale[graph.axis]  # (E,) z̃ differences
    w_tail = np.empty_like(d)
    w_head = np.empty_like(d)
    for ax in (0, 1):
        sel = np.flatnonzero(graph.axis == ax)
        tail, head, d_ax = graph.tail[sel], graph.head[sel], d[sel]
        d_plus = np.full(graph.n, np.nan)
        d_minus = np.full(graph.n, np.nan)
        d_plus[tail] = d_ax  # forward difference D⁺ at the tail pixel
        d_minus[head] = d_ax  # backward difference D⁻ at the head pixel
        # A pixel with a neighbour on one side only shows no one-sided discontinuity: w⁺ = w⁻ = ½.
        d_plus = np.where(np.isnan(d_plus), d_minus, d_plus)
        d_minus = np.where(np.isnan(d_minus), d_plus, d_minus)
        w_plus = expit(k * (d_minus * d_minus - d_plus * d_plus))  # (n,) σ_k((D⁻z̃)² − (D⁺z̃)²)
        w_tail[sel] = w_plus[tail]
        w_head[sel] = 1.0 - w_plus[head]
    return w_tail, w_head


def _system(
    graph: _PixelGraph, coeff: NDArray[np.float64], target: NDArray[np.float64]
) -> tuple[sp.csr_matrix, NDArray[np.float64]]:
    """Normal equations of Σ_e c_e (f_head − f_tail − t_e)², one node per component pinned to 0.

    Args:
        graph: the pixel graph.
        coeff: (E,) c_e > 0.
        target: (E,) c_e·t_e.

    Returns:
        (L (n, n) CSR, symmetric positive definite; rhs (n,)).
    """
    free = np.ones(graph.n)
    free[graph.pinned] = 0.0
    # D^T diag(c) D written out (a weighted graph Laplacian: −c_e at (tail, head) and (head, tail), each node's
    # Σ c on the diagonal), with the pinned nodes' rows and columns replaced by the identity: pinning one node
    # per component removes the constant null space of each component.
    keep = (free[graph.tail] * free[graph.head]) > 0  # (E,) edges between two free nodes
    off = -coeff[keep]
    diag = np.bincount(graph.tail, coeff, graph.n) + np.bincount(graph.head, coeff, graph.n)  # (n,)
    diag = np.where(free > 0, diag, 1.0)
    nodes = np.arange(graph.n)
    rows = np.concatenate([graph.tail[keep], graph.head[keep], nodes])
    cols = np.concatenate([graph.head[keep], graph.tail[keep], nodes])
    lap = sp.csr_matrix((np.concatenate([off, off, diag]), (rows, cols)), shape=(graph.n, graph.n))
    rhs = graph.incidence.T @ target  # (n,) D^T target
    return lap, rhs * free


class _LinearSolver:
    """Solves the pinned normal equations (warm-started for the iterative solvers)."""

    def __init__(self, solver: Solver, n: int, rtol: float) -> None:
        if solver not in ("auto", "direct", "cg", "amg"):
            raise ValueError(f"solver must be 'auto', 'direct', 'cg' or 'amg'; got {solver!r}")
        if solver == "auto":
            solver = "amg" if n > _DIRECT_MAX_UNKNOWNS and _has_pyamg() else "direct"
            if n > _DIRECT_MAX_UNKNOWNS and solver == "direct":
                logger.info("pyamg is not installed: solving %d unknowns with sparse LU (pip install pyamg is faster)", n)
        if solver == "amg" and not _has_pyamg():
            raise ValueError("solver='amg' needs the pyamg package (pip install pyamg), or use solver='cg'/'direct'")
        self.solver: str = solver
        self.rtol = rtol
        self.iterations = 0

    def __call__(self, lap: sp.csr_matrix, rhs: NDArray[np.float64], x0: NDArray[np.float64]) -> NDArray[np.float64]:
        if self.solver == "direct":
            return np.asarray(spla.spsolve(lap.tocsc(), rhs), dtype=np.float64)
        if self.solver == "amg":
            import pyamg

            # Classical (Ruge–Stüben) AMG suits these graph Laplacians (M-matrices): 3–10× faster than
            # smoothed aggregation here. Rebuilding it for every bilateral iteration measured faster
            # than reusing a stale hierarchy (more CG steps).
            precond: Any = pyamg.ruge_stuben_solver(lap).aspreconditioner(cycle="V")
            maxiter = 1000
        else:
            precond = sp.diags(1.0 / lap.diagonal())
            maxiter = 20 * lap.shape[0]
        steps = [0]

        def _count(_: NDArray[np.float64]) -> None:
            steps[0] += 1

        x, info = spla.cg(lap, rhs, x0=x0, rtol=self.rtol, atol=0.0, maxiter=maxiter, M=precond, callback=_count)
        self.iterations += steps[0]
        if info > 0:
            logger.warning("conjugate gradients stopped after %d steps without reaching rtol=%g", info, self.rtol)
        return np.asarray(x, dtype=np.float64)


def _has_pyamg() -> bool:
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


def _component_median(values: NDArray[np.float64], component: NDArray[np.int64], n_comp: int) -> NDArray[np.float64]:
    """(C,) median of ``values`` (n,) over each component; NaN where a component has no finite value."""
    finite = np.isfinite(values)
    out = np.full(n_comp, np.nan)
    if finite.any():
        present = np.unique(component[finite])
        out[present] = scipy.ndimage.median(values[finite], labels=component[finite] + 1, index=present + 1)
    return out


def _component_constants(
    offsets: NDArray[np.float64], relative: NDArray[np.float64], reference: float, graph: _PixelGraph
) -> NDArray[np.float64]:
    """(n,) the gauge constant of each node's component (module docstring: gauge).

    Args:
        offsets: (n,) depth_init − solution in the gauge's space (NaN where depth_init is unknown).
        relative: (n,) the solution in the gauge's space.
        reference: the reference depth in the gauge's space.
        graph: the pixel graph.

    Returns:
        The median offset of the component, or ``reference − median(relative)`` where it has none.
    """
    n_comp = graph.pinned.shape[0]
    const = _component_median(offsets, graph.component, n_comp)
    fallback = reference - _component_median(relative, graph.component, n_comp)
    return np.where(np.isfinite(const), const, fallback)[graph.component]


@dataclass
class IntegrationReport:
    """Diagnostics of one :func:`integrate_normals` call (pass an instance as ``report=`` to fill it).

    Attributes:
        pixels: number of integrated pixels.
        components: number of 4-connected components integrated.
        solver: the linear solver used ("direct", "cg" or "amg").
        iterations: re-weighted solves (1 for the smooth method).
        cg_steps: conjugate-gradient steps over all solves (0 for the direct solver).
        energy: final value of the (weighted) least-squares energy, in units of the field f squared.
        seconds: wall time.
    """

    pixels: int = 0
    components: int = 0
    solver: str = ""
    iterations: int = 0
    cg_steps: int = 0
    energy: float = float("nan")
    seconds: float = 0.0


@dataclass(frozen=True)
class _BilateralOptions:
    """The re-weighting options of :func:`integrate_normals` (checked even for the smooth method)."""

    k: float
    max_iter: int
    tol: float
    weight_tol: float
    weight_floor: float

    def __post_init__(self) -> None:
        k, max_iter, tol, weight_tol, weight_floor = self.k, self.max_iter, self.tol, self.weight_tol, self.weight_floor
        if not (k > 0 and max_iter >= 1 and tol >= 0 and weight_tol >= 0 and 0 < weight_floor < 1):
            raise ValueError(
                "bilateral options out of range: need k > 0, max_iter >= 1, tol >= 0, weight_tol >= 0, "
                f"0 < weight_floor < 1; got k={k}, max_iter={max_iter}, tol={tol}, weight_tol={weight_tol}, "
                f"weight_floor={weight_floor}"
            )


def _checked_slopes(
    nmap: NDArray[np.float64], mask: NDArray[np.bool_], model: _FieldModel, grazing_eps: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(g_u, g_v), each (H, W), of the normals (H, W, 3); warns about capped slopes and refuses a
    normal map that mostly faces away from the camera (a flipped sign convention)."""
    g_u, g_v, clamped = model.gradients(nmap, grazing_eps)
    n_clamped = int((clamped & mask).sum())
    if n_clamped:
        n_away = int((model.facing_away(nmap) & mask).sum())
        if n_away > 0.5 * mask.sum():
            raise ValueError(
                f"{n_away} of {int(mask.sum())} normals face away from the camera (n·r > 0); polarshape's "
                "camera frame has n_z < 0 for a surface facing an orthographic camera (spec §1): flip the "
                "normals' sign or convert them from another convention"
            )
        logger.warning(
            "%d normals are grazing or face away from the camera (%d facing away); their slope is capped",
            n_clamped,
            n_away,
        )
    return g_u, g_v


def _drop_small_components(mask: NDArray[np.bool_], min_component_size: int) -> NDArray[np.bool_]:
    """(H, W) the mask without its 4-connected components of fewer than ``min_component_size`` pixels."""
    if min_component_size <= 1:
        return mask
    labels, n_lab = scipy.ndimage.label(mask, structure=_FOUR_CONNECTED)
    sizes = np.bincount(labels.ravel(), minlength=n_lab + 1)
    small = (sizes < min_component_size) & (np.arange(n_lab + 1) > 0)
    if not small.any():
        return mask
    dropped = small[labels]
    logger.info("leaving %d components (%d pixels) below %d pixels out", int(small.sum()), int(dropped.sum()), min_component_size)
    mask = mask & ~dropped
    if not mask.any():
        raise ValueError(f"every connected component of the mask is smaller than min_component_size={min_component_size}")
    return mask


def _initial_field(
    depth_init: Any | None, mask: NDArray[np.bool_], graph: _PixelGraph, model: _FieldModel
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The field of ``depth_init`` and the solver's start.

    Returns:
        (init_field (n,), NaN where depth_init is unknown or absent; x0 (n,), init_field with each
        component's median in its gaps (0 without one), shifted so that the pinned nodes are 0).
    """
    init_field = np.full(graph.n, np.nan)
    if depth_init is not None:
        init = to_numpy(depth_init).astype(np.float64)
        if init.shape != mask.shape:
            raise ValueError(f"depth_init must have shape (H, W) = {mask.shape}; got {init.shape}")
        init_field = model.field_of_depth(init[mask])
    init_median = _component_median(init_field, graph.component, graph.pinned.shape[0])  # (C,)
    x0 = np.where(np.isfinite(init_field), init_field, np.nan_to_num(init_median)[graph.component])
    return init_field, x0 - x0[graph.pinned][graph.component]  # the pinned gauge: pinned node at 0


_Pair = tuple[NDArray[np.float64], NDArray[np.float64]]


def _weighted_solve(
    graph: _PixelGraph,
    linear: _LinearSolver,
    weights: _Pair,
    targets: _Pair,
    field: NDArray[np.float64],
    weight_floor: float,
) -> tuple[NDArray[np.float64], float]:
    """One weighted least-squares solve, warm-started at ``field`` (n,).

    Args:
        weights: (w_tail, w_head), each (E,): w⁺ of each edge's tail pixel and w⁻ of its head pixel.
        targets: (g_tail, g_head), each (E,): the field's gradient along the edge at its two pixels.
        weight_floor: lower bound of an edge's total weight.

    Returns:
        (field (n,), energy Σ w⁺ (Df − g⁺)² + w⁻ (Df − g⁻)²).
    """
    (w_tail, w_head), (g_tail, g_head) = weights, targets
    coeff = np.maximum(w_tail + w_head, weight_floor)
    lap, rhs = _system(graph, coeff, w_tail * g_tail + w_head * g_head)
    field = linear(lap, rhs, field)
    diff = graph.incidence @ field  # (E,)
    return field, float(np.sum(w_tail * (diff - g_tail) ** 2 + w_head * (diff - g_head) ** 2))


def _bilateral_solve(
    graph: _PixelGraph,
    linear: _LinearSolver,
    targets: _Pair,
    x0: NDArray[np.float64],
    axis_scale: NDArray[np.float64],
    options: _BilateralOptions,
    *,
    init_complete: bool,
) -> tuple[NDArray[np.float64], float, int]:
    """Re-weighted solves until the energy and the weights settle (module docstring: discretisation).

    Args:
        init_complete: x0 comes from a depth_init known everywhere in the mask.

    Returns:
        (field (n,), final energy, number of solves).
    """
    g_tail = targets[0]
    if init_complete:
        # A complete depth_init already shows its cliffs: start from its weights, not from ½.
        weights = _bilateral_weights(graph, x0, axis_scale, options.k)
    else:
        weights = (np.full(graph.tail.shape, 0.5), np.full(graph.tail.shape, 0.5))
    field, energy_prev = x0, np.inf
    energy_unit = float(graph.tail.shape[0]) * (1.0 + float(np.mean(g_tail**2)) if g_tail.size else 1.0)
    for it in range(options.max_iter):
        field, energy = _weighted_solve(graph, linear, weights, targets, field, options.weight_floor)
        new = _bilateral_weights(graph, field, axis_scale, options.k)
        weight_change = float(max(np.abs(a - b).max(initial=0.0) for a, b in zip(new, weights)))
        weights = new
        change = abs(energy_prev - energy) / max(energy_prev, 1e-300) if np.isfinite(energy_prev) else np.inf
        logger.debug(
            "bilateral iteration %d: energy %.6g, relative change %.3g, largest weight change %.3g",
            it + 1,
            energy,
            change,
            weight_change,
        )
        exact_fit = energy <= 1e-20 * energy_unit  # integrable field solved to rounding error
        if weight_change < options.weight_tol and (change < options.tol or exact_fit):
            break
        energy_prev = energy
    return field, energy, it + 1


def integrate_normals(
    normals: Any,
    mask: Any | None,
    *,
    camera: Camera,
    method: Method = "smooth",
    depth_init: Any | None = None,
    reference_depth: float = 1.0,
    k: float = 2.0,
    max_iter: int = 100,
    tol: float = 1e-4,
    weight_tol: float = 0.05,
    weight_floor: float = 1e-4,
    solver: Solver = "auto",
    rtol: float = 1e-8,
    min_component_size: int = 1,
    unit_tol: float = 1e-3,
    grazing_eps: float = GRAZING_EPS,
    report: IntegrationReport | None = None,
) -> NDArray[np.float64]:
    """Integrate a camera-frame normal map into a depth map (module docstring: maths and gauge).

    Args:
        normals: (H, W, 3) camera-frame unit normals facing the camera (n_z < 0 orthographic);
            numpy array or torch tensor (any device); ignored outside the mask.
        mask: (H, W) bool, pixels to integrate; None = the pixels whose normals are finite.
        camera: a :mod:`polarshape.cameras` camera whose grid is the normal map's (H, W), pixel centres
            at integer (u, v): orthographic (depth comes out in the unit of ``pixel_size_m``) or
            perspective (its pinhole intrinsics). For a capture: ``camera.superpixel("centre", ...)``.
        method: "smooth" (least squares) or "bilateral" (discontinuity-preserving, Cao et al. 2022).
        depth_init: optional (H, W) depth (same unit; NaN where unknown): warm start of the solver, the
            initial bilateral weights, and the per-component constant (see the gauge rule).
        reference_depth: median depth of each component that ``depth_init`` does not cover (> 0).
        k: bilateral sigmoid sharpness, dimensionless (differences in pixel-footprint units). The
            paper's k = 2 keeps occluding boundaries and cliffs next to slopes ≳ 0.5 (≈ 27°); gentler
            cliffs need k ≈ 5–15, but a larger k also cuts creases (slope jumps) and can then fail
            (measured on the synthetic cases of tests/surface/test_integrate.py).
        max_iter: most bilateral iterations (re-weighted solves). A cut grows along a boundary by a
            few pixels per iteration, so long boundaries need more iterations.
        tol: bilateral stopping rule: stop when the relative energy change is below ``tol`` and no
            weight changed by more than ``weight_tol`` since the previous iteration.
        weight_tol: see ``tol`` (the energy alone changes little while a cut starts to form).
        weight_floor: lower bound of an edge's total bilateral weight (keeps the system well posed when
            the weights cut a region off; then its constant follows from the weak remaining ties).
        solver: "direct" (sparse LU), "cg" (Jacobi-preconditioned conjugate gradients), "amg"
            (conjugate gradients preconditioned by pyamg's Ruge–Stüben AMG) or "auto"
            (direct up to 20 000 pixels, then amg if pyamg is installed, else direct).
        rtol: relative residual of the iterative solvers.
        min_component_size: connected components (4-connectivity) with fewer pixels are left NaN.
        unit_tol: allowed | ‖n‖ − 1 | inside the mask.
        grazing_eps: slope cap for grazing / back-facing normals (see :func:`surface_gradients`).
        report: optional :class:`IntegrationReport`, filled in with diagnostics.

    Returns:
        (H, W) float64 depth (camera-frame z, > 0 in perspective), NaN outside the mask.

    Raises:
        ValueError: bad shapes, empty mask, non-unit or NaN normals in the mask, most normals facing
            away from the camera (flipped convention), a camera not at the normal map's grid, bad options.

    Example:
        >>> n = np.zeros((8, 8, 3)); n[..., 0] = 0.6; n[..., 2] = -0.8
        >>> z = integrate_normals(n, np.ones((8, 8), bool), camera=OrthographicCamera(8, 8, 0.01))
        >>> round(float(z[0, 1] - z[0, 0]), 6)   # dz/dx = −n_x/n_z = 0.75, times 0.01 m per pixel
        0.0075
    """
    t_start = time.perf_counter()
    nmap, m = check_normal_map(normals, mask, unit_tol=unit_tol)
    model = _field_model(camera, m.shape)
    if method not in ("smooth", "bilateral"):
        raise ValueError(f"method must be 'smooth' or 'bilateral'; got {method!r}")
    if not (np.isfinite(reference_depth) and reference_depth > 0):
        raise ValueError(f"reference_depth must be a positive depth; got {reference_depth!r}")
    options = _BilateralOptions(k, max_iter, tol, weight_tol, weight_floor)

    g_u, g_v = _checked_slopes(nmap, m, model, grazing_eps)
    m = _drop_small_components(m, min_component_size)
    graph = _pixel_graph(m)
    g_nodes = np.stack([g_u[m], g_v[m]]) / model.field_scale  # (2, n) gradients of the solved field f
    targets = (g_nodes[graph.axis, graph.tail], g_nodes[graph.axis, graph.head])  # (E,) each
    init_field, x0 = _initial_field(depth_init, m, graph, model)

    linear = _LinearSolver(solver, graph.n, rtol)
    if method == "bilateral":
        complete = bool(np.all(np.isfinite(init_field)))
        field, energy, iterations = _bilateral_solve(
            graph, linear, targets, x0, model.axis_scale, options, init_complete=complete
        )
    else:
        half = np.full(graph.tail.shape, 0.5)  # plain least squares: w⁺ = w⁻ = ½
        field, energy = _weighted_solve(graph, linear, (half, half), targets, x0, weight_floor)
        iterations = 1

    depth = np.full(m.shape, np.nan)
    depth[m] = model.depth_of_field(field, init_field, graph, reference_depth)
    seconds = time.perf_counter() - t_start
    if report is not None:
        report.pixels, report.components, report.solver = graph.n, graph.pinned.shape[0], linear.solver
        report.iterations, report.cg_steps, report.energy = iterations, linear.iterations, energy
        report.seconds = seconds
    logger.info(
        "integrated %d pixels (%d components, %s, %s, solver %s): %d iterations, %d CG steps, %.3f s",
        graph.n,
        graph.pinned.shape[0],
        camera.projection,
        method,
        linear.solver,
        iterations,
        linear.iterations,
        seconds,
    )
    return depth
