"""Normal integration: a depth map from a camera-frame normal map, orthographic or perspective.

Conventions (spec §1): camera frame x right, y down, z forward; pixel (u, v) = (column, row) with
pixel centres at integer coordinates; normals are unit vectors facing the camera (N·V > 0, so
n_z < 0 under an orthographic camera). Depth z is the camera-frame z coordinate of the surface
point (metres, or whatever unit ``pixel_size`` / the scene is in), not the distance along the ray.

**Gradients.** A surface point is P(u, v).
- Orthographic: P = (s·u, s·v, z) with s = ``pixel_size`` (metres per pixel). The camera-facing
  normal is ∝ P_v × P_u ∝ (s z_u, s z_v, −s²), so ∂z/∂x = −n_x/n_z = p and ∂z/∂y = −n_y/n_z = q
  (x, y metric, y down); per pixel ∂z/∂u = s·p, ∂z/∂v = s·q.
- Perspective (Cao et al. 2022, "Bilateral Normal Integration", log-depth form): P = z·r with
  r = K⁻¹(u, v, 1)ᵀ. From n·P_u = n·P_v = 0: ∂log z/∂u = −n·(K⁻¹e₁)/(n·r) and
  ∂log z/∂v = −n·(K⁻¹e₂)/(n·r); with zero skew these are −n_x/(f_x·n·r) and −n_y/(f_y·n·r).
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

logger = logging.getLogger(__name__)

Projection = Literal["orthographic", "perspective"]
Method = Literal["smooth", "bilateral"]
Solver = Literal["auto", "direct", "cg", "amg"]

_FOUR_CONNECTED = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)
# Below this many unknowns a sparse LU factorisation beats iterative solvers (benchmarks/integration.py).
_DIRECT_MAX_UNKNOWNS = 20_000


def _to_numpy(array: Any, name: str) -> NDArray[Any]:
    """Accept numpy arrays and (CPU or CUDA) torch tensors; return a numpy array."""
    if hasattr(array, "detach") and hasattr(array, "cpu"):
        array = array.detach().cpu().numpy()
    if not isinstance(array, np.ndarray):
        try:
            array = np.asarray(array)
        except Exception as exc:  # pragma: no cover - exotic inputs
            raise TypeError(f"{name} must be a numpy array or torch tensor; got {type(array).__name__}") from exc
    return array


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
    n = _to_numpy(normals, "normals")
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3) (camera-frame unit vectors); got {n.shape}")
    n = n.astype(np.float64, copy=False)
    if mask is None:
        m = np.all(np.isfinite(n), axis=2)
    else:
        m = _to_numpy(mask, "mask")
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


def _check_camera(
    projection: str, pixel_size: float, K: Any | None
) -> NDArray[np.float64] | None:
    """Validate the projection model; returns K (3, 3) float64 for perspective, None otherwise."""
    if projection == "orthographic":
        if not (np.isfinite(pixel_size) and pixel_size > 0):
            raise ValueError(f"pixel_size must be a positive number of metres per pixel; got {pixel_size!r}")
        return None
    if projection == "perspective":
        if K is None:
            raise ValueError("projection='perspective' needs K, the (3, 3) intrinsic matrix at the normal map's resolution")
        k = _to_numpy(K, "K").astype(np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise ValueError(f"K must be a finite (3, 3) intrinsic matrix; got shape {k.shape}")
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
            raise ValueError(
                "K must be upper triangular [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; "
                f"got {k.tolist()}"
            )
        return k
    raise ValueError(f"projection must be 'orthographic' or 'perspective'; got {projection!r}")


#: Default slope cap: normals tilted more than ≈ 87° from the line of sight (n·r̂ > −0.05) count as
#: grazing, slope ≤ |n_xy| / 0.05 ≈ 20. Such estimates are unreliable (a super-pixel there spans a
#: large depth range) and, uncapped, a handful of them dominates the least-squares integration:
#: measured on a recovered checker-textured sphere (4 such normals among 6520), depth RMS 8.5 mm
#: of a 10 mm range with a cap at 0.001, 0.80 mm at 0.05; ground-truth spheres are unchanged.
GRAZING_EPS = 0.05


def surface_gradients(
    normals: Any,
    *,
    projection: Projection = "orthographic",
    pixel_size: float = 1.0,
    K: Any | None = None,
    grazing_eps: float = GRAZING_EPS,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Per-pixel gradients of the integrated field, derived from the normals (see module docstring).

    Args:
        normals: (H, W, 3) camera-frame unit normals facing the camera (NaN allowed: gives NaN).
        projection: "orthographic" (field z, metres) or "perspective" (field log z).
        pixel_size: metres per pixel (orthographic).
        K: (3, 3) intrinsics at this resolution (perspective).
        grazing_eps: normals with n·r̂ > −grazing_eps (grazing or facing away; r̂ the unit ray) are
            clamped to n·r̂ = −grazing_eps, which caps the slope instead of dividing by ~0
            (default :data:`GRAZING_EPS`).

    Returns:
        (g_u, g_v, clamped): g_u = ∂z/∂u, g_v = ∂z/∂v in metres per pixel (orthographic) or
        ∂log z/∂u, ∂log z/∂v per pixel (perspective), each (H, W); clamped (H, W) marks the pixels
        whose denominator was clamped.

    Example:
        >>> n = np.zeros((2, 2, 3)); n[..., 0] = 0.6; n[..., 2] = -0.8   # plane z = 0.75 x + c
        >>> gu, gv, _ = surface_gradients(n)
        >>> round(float(gu[0, 0]), 12), round(float(gv[0, 0]), 12)
        (0.75, 0.0)
    """
    n = _to_numpy(normals, "normals").astype(np.float64, copy=False)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3); got {n.shape}")
    k = _check_camera(projection, pixel_size, K)
    h, w = n.shape[:2]
    if k is None:
        # n·r̂ with r̂ = (0, 0, 1): the denominator is n_z; dz/dx = −n_x/n_z, dz/dy = −n_y/n_z.
        denom = n[..., 2]
        clamped = ~(denom <= -grazing_eps) & np.isfinite(denom)
        denom = np.where(clamped, -grazing_eps, denom)
        g_u = -pixel_size * n[..., 0] / denom
        g_v = -pixel_size * n[..., 1] / denom
        return g_u, g_v, clamped
    k_inv = np.linalg.inv(k)
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([uu, vv, np.ones_like(uu)], axis=-1)  # (H, W, 3)
    ray = pix @ k_inv.T  # (H, W, 3) r = K⁻¹(u, v, 1), r_z = 1
    ray_norm = np.linalg.norm(ray, axis=-1)  # (H, W)
    n_dot_rhat = np.einsum("hwc,hwc->hw", n, ray) / ray_norm
    clamped = ~(n_dot_rhat <= -grazing_eps) & np.isfinite(n_dot_rhat)
    n_dot_r = np.where(clamped, -grazing_eps, n_dot_rhat) * ray_norm  # (H, W)
    # n·P_u = 0 with P_u = z_u r + z K⁻¹e₁  ⇒  ∂log z/∂u = −n·(K⁻¹e₁) / (n·r); same for v.
    g_u = -(n @ k_inv[:, 0]) / n_dot_r
    g_v = -(n @ k_inv[:, 1]) / n_dot_r
    return g_u, g_v, clamped


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
    d = graph.incidence  # (E, n)
    lap = (d.T @ sp.diags(coeff) @ d).tocsr()  # (n, n) weighted graph Laplacian
    rhs = d.T @ target  # (n,)
    free = np.ones(graph.n)
    free[graph.pinned] = 0.0
    # Pinning one node per component removes the constant null space of each component.
    lap = (sp.diags(free) @ lap @ sp.diags(free) + sp.diags(1.0 - free)).tocsr()
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


def integrate_normals(
    normals: Any,
    mask: Any | None,
    *,
    projection: Projection = "orthographic",
    pixel_size: float = 1.0,
    K: Any | None = None,
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
        projection: "orthographic" or "perspective".
        pixel_size: metres per pixel (orthographic); depth comes out in the same unit.
        K: (3, 3) intrinsics at the normal map's resolution, pixel centres at integer (u, v) (perspective).
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
            away from the camera (flipped convention), bad camera or options.

    Example:
        >>> n = np.zeros((8, 8, 3)); n[..., 0] = 0.6; n[..., 2] = -0.8
        >>> z = integrate_normals(n, np.ones((8, 8), bool), pixel_size=0.01)
        >>> round(float(z[0, 1] - z[0, 0]), 6)   # dz/dx = −n_x/n_z = 0.75, times 0.01 m per pixel
        0.0075
    """
    t_start = time.perf_counter()
    nmap, m = check_normal_map(normals, mask, unit_tol=unit_tol)
    kmat = _check_camera(projection, pixel_size, K)
    if method not in ("smooth", "bilateral"):
        raise ValueError(f"method must be 'smooth' or 'bilateral'; got {method!r}")
    if not (np.isfinite(reference_depth) and reference_depth > 0):
        raise ValueError(f"reference_depth must be a positive depth; got {reference_depth!r}")
    if not (k > 0 and max_iter >= 1 and tol >= 0 and weight_tol >= 0 and 0 < weight_floor < 1):
        raise ValueError(
            "bilateral options out of range: need k > 0, max_iter >= 1, tol >= 0, weight_tol >= 0, "
            f"0 < weight_floor < 1; got k={k}, max_iter={max_iter}, tol={tol}, weight_tol={weight_tol}, "
            f"weight_floor={weight_floor}"
        )
    h, w = m.shape

    g_u, g_v, clamped = surface_gradients(nmap, projection=projection, pixel_size=pixel_size, K=kmat, grazing_eps=grazing_eps)
    n_clamped = int((clamped & m).sum())
    if n_clamped:
        if kmat is None:
            facing_away = nmap[..., 2] > 0
        else:
            vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
            ray = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(kmat).T
            facing_away = np.einsum("hwc,hwc->hw", nmap, ray) > 0
        n_away = int((facing_away & m).sum())
        if n_away > 0.5 * m.sum():
            raise ValueError(
                f"{n_away} of {int(m.sum())} normals face away from the camera (n·r > 0); polarshape's "
                "camera frame has n_z < 0 for a surface facing an orthographic camera (spec §1): flip the "
                "normals' sign or convert them from another convention"
            )
        logger.warning(
            "%d normals are grazing or face away from the camera (%d facing away); their slope is capped",
            n_clamped,
            n_away,
        )

    if min_component_size > 1:
        labels, n_lab = scipy.ndimage.label(m, structure=_FOUR_CONNECTED)
        sizes = np.bincount(labels.ravel(), minlength=n_lab + 1)
        small = (sizes < min_component_size) & (np.arange(n_lab + 1) > 0)
        if small.any():
            dropped = small[labels]
            logger.info("leaving %d components (%d pixels) below %d pixels out", int(small.sum()), int(dropped.sum()), min_component_size)
            m = m & ~dropped
            if not m.any():
                raise ValueError(f"every connected component of the mask is smaller than min_component_size={min_component_size}")

    graph = _pixel_graph(m)
    n_comp = graph.pinned.shape[0]
    # Gradients of the solved field f: z/s per pixel (orthographic), log z per pixel (perspective).
    field_scale = pixel_size if kmat is None else 1.0
    g_nodes = np.stack([g_u[m], g_v[m]]) / field_scale  # (2, n)
    g_tail = g_nodes[graph.axis, graph.tail]  # (E,)
    g_head = g_nodes[graph.axis, graph.head]  # (E,)
    axis_scale = np.array([1.0, 1.0]) if kmat is None else np.array([kmat[0, 0], kmat[1, 1]])

    # Initial field from depth_init (NaN where unknown).
    init_field = np.full(graph.n, np.nan)
    if depth_init is not None:
        init = _to_numpy(depth_init, "depth_init").astype(np.float64)
        if init.shape != (h, w):
            raise ValueError(f"depth_init must have shape (H, W) = {(h, w)}; got {init.shape}")
        vals = init[m]
        if kmat is None:
            init_field = vals / field_scale
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                init_field = np.where(vals > 0, np.log(vals), np.nan)
    init_median = _component_median(init_field, graph.component, n_comp)  # (C,)
    x0 = np.where(np.isfinite(init_field), init_field, np.nan_to_num(init_median)[graph.component])
    x0 = x0 - x0[graph.pinned][graph.component]  # the pinned gauge: pinned node at 0

    linear = _LinearSolver(solver, graph.n, rtol)
    if method == "bilateral" and bool(np.all(np.isfinite(init_field))):
        # A complete depth_init already shows its cliffs: start from its weights, not from ½.
        w_tail, w_head = _bilateral_weights(graph, x0, axis_scale, k)
    else:
        w_tail = np.full(graph.tail.shape, 0.5)
        w_head = np.full(graph.tail.shape, 0.5)

    field = x0
    energy_prev = np.inf
    energy_unit = float(graph.tail.shape[0]) * (1.0 + float(np.mean(g_tail**2)) if g_tail.size else 1.0)
    n_iter = max_iter if method == "bilateral" else 1
    for it in range(n_iter):
        coeff = np.maximum(w_tail + w_head, weight_floor)
        lap, rhs = _system(graph, coeff, w_tail * g_tail + w_head * g_head)
        field = linear(lap, rhs, field)
        diff = graph.incidence @ field  # (E,)
        energy = float(np.sum(w_tail * (diff - g_tail) ** 2 + w_head * (diff - g_head) ** 2))
        if method == "smooth":
            break
        w_tail_new, w_head_new = _bilateral_weights(graph, field, axis_scale, k)
        weight_change = float(max(np.abs(w_tail_new - w_tail).max(initial=0.0), np.abs(w_head_new - w_head).max(initial=0.0)))
        w_tail, w_head = w_tail_new, w_head_new
        change = abs(energy_prev - energy) / max(energy_prev, 1e-300) if np.isfinite(energy_prev) else np.inf
        logger.debug(
            "bilateral iteration %d: energy %.6g, relative change %.3g, largest weight change %.3g",
            it + 1,
            energy,
            change,
            weight_change,
        )
        exact_fit = energy <= 1e-20 * energy_unit  # integrable field solved to rounding error
        if weight_change < weight_tol and (change < tol or exact_fit):
            break
        energy_prev = energy

    # Gauge: one constant per component (module docstring).
    if kmat is None:
        depth_rel = field * field_scale  # (n,) z up to a constant
        const = _component_median(init_field * field_scale - depth_rel, graph.component, n_comp)
        fallback = reference_depth - _component_median(depth_rel, graph.component, n_comp)
        const = np.where(np.isfinite(const), const, fallback)
        depth_nodes = depth_rel + const[graph.component]
    else:
        const = _component_median(init_field - field, graph.component, n_comp)
        fallback = np.log(reference_depth) - _component_median(field, graph.component, n_comp)
        const = np.where(np.isfinite(const), const, fallback)
        depth_nodes = np.exp(field + const[graph.component])

    depth = np.full((h, w), np.nan)
    depth[m] = depth_nodes
    if report is not None:
        report.pixels, report.components, report.solver = graph.n, n_comp, linear.solver
        report.iterations, report.cg_steps, report.energy = it + 1, linear.iterations, energy
        report.seconds = time.perf_counter() - t_start
    logger.info(
        "integrated %d pixels (%d components, %s, %s, solver %s): %d iterations, %d CG steps, %.3f s",
        graph.n,
        n_comp,
        projection,
        method,
        linear.solver,
        it + 1,
        linear.iterations,
        time.perf_counter() - t_start,
    )
    return depth
