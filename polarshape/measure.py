"""``polarshape material``: the material of an object of known geometry, from one or more frames.

:func:`measure_material` composes short stages:

1. ``input`` — load the capture, keep the chosen frames (``frames``);
2. ``geometry`` — the normals of every super-pixel from ``shape``:
   ``"sphere"`` — a sphere whose silhouette is the capture's mask (or, without mask.png, the
   largest bright region of the brightest s0 image, with a warning): circle fitted to the
   silhouette (orthographic) or the silhouette cone's axis and half-angle (perspective, with the
   capture's intrinsics) by :func:`polarshape.acquisition.calibrate.fit_sphere`, then the normals
   of that sphere; a ``.npy`` normal map (H/2, W/2, 3), camera frame, N·V > 0, NaN where unknown;
   a mesh (``.ply``, ``.obj``, ...) with its pose (object → camera 4×4 or R|t), ray cast with the
   simulator's :func:`polarshape.scene.raycast.rasterize` at the capture's camera
   (:func:`mesh_normals`; an orthographic capture needs its metric pixel size);
3. ``observations`` — :func:`polarshape.recover.preprocess.preprocess_capture` (float64) on the
   pixels whose normal is known and not grazing (N·V ≥ :data:`MIN_COS_VIEW`), observations lit
   at N·L ≥ :data:`MIN_COS_LIGHT`;
4. ``fit`` — every model of ``models`` by :func:`polarshape.recover.material_fit.fit_model`
   (eq. 25), and with K ≥ 2 frames the leave-one-frame-out prediction errors
   (:func:`~polarshape.recover.material_fit.held_out_errors`, the paper's Fig. 7);
5. ``write`` — OUT/material.json, OUT/report.html and its PNGs, in one atomic folder.

**What material.json holds**: the FMBRDF fit whenever ``fmbrdf`` is among the models — it is the
model the rest of polarshape consumes (``polarshape run``'s ``recovery.material``, scene files) —
even when a baseline explains this data better; the ranking says so in ``fit.best_model``.
Without ``fmbrdf``, the best-ranked model a material file can hold (any but the composites
``l_ts``/``on_ts``). ``fit.models`` records every model's parameters and errors, ``fit.held_out``
the held-out errors. Ranking: by the mean held-out s0 relative RMSE with K ≥ 2 frames, else by the
eq. 25 loss on the fitted data.

Directional lights only: a point light's direction and fall-off need the object's 3-D points,
which a normal map alone does not give (refused with a message).
"""

from __future__ import annotations

import dataclasses
import html
import logging
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from polarshape import __version__
from polarshape.acquisition.calibrate import Intrinsics, fit_sphere, sphere_mask_from_image
from polarshape.brdf.geometry import angle_between, safe_normalize
from polarshape.brdf.params import FMBRDFParams
from polarshape.errors import ConfigError, OutputExistsError, SuspiciousInputWarning
from polarshape.imaging.mosaic import split_mosaic
from polarshape.imaging.pixels import counts_to_float
from polarshape.imaging.stokes import dolp
from polarshape.io.atomic import atomic_directory, atomic_write_text, check_destination
from polarshape.cameras import camera_from_spec
from polarshape.io.capture import MASK_FILE, Capture, load_capture
from polarshape.io.images import read_image
from polarshape.io.material import MATERIAL_UNITS, MaterialFile, write_material
from polarshape.io.results import is_result_folder, output_refusal
from polarshape.recover.material_fit import (
    COMPOSITE_MODELS, FIT_MODELS, HeldOutErrors, ModelFit, fit_model, held_out_errors, model_parts, rank_models,
    render_model,
)
from polarshape.recover.observations import Observations, flatten_observations
from polarshape.recover.preprocess import capture_camera, preprocess_capture
from polarshape.report import MODEL_NAMES, PARAMETER_MEANINGS
from polarshape.scene.geometry import MeshShape
from polarshape.scene.raycast import rasterize, superpixel_ground_truth

logger = logging.getLogger(__name__)

__all__ = [
    "ALL_SITES_SHRINK_PX", "MESH_SUFFIXES", "MIN_COS_LIGHT", "MIN_COS_VIEW", "MeasureResult",
    "load_pose", "measure_material", "measure_table", "mesh_normals", "normals_from_file", "select_frames", "sphere_normals",
]

#: Pixels seen more grazing than acos(0.5) = 60° are left out of the fit. Near the limb a fitted
#: sphere's normals are least certain and the body DoLP is largest, so those pixels become eq. 25's
#: high-weight DoLP "outliers" (weight #inliers/#outliers each): measured on the 64-px test sphere,
#: θ_V up to 78° gave μ = 1.64, up to 66° μ = 1.60 (with exact normals), up to 60° μ = 1.50 (true 1.5).
MIN_COS_VIEW = 0.5

#: How much a super-pixel mask that keeps a block only when all four of its sites are on the object
#: (how capture loading reduces a mosaic-resolution mask.png, and how the simulator writes one)
#: shrinks a silhouette: the farthest site is ¼(|cos θ| + |sin θ|) super-pixels out, 1/π on average
#: around a circle. Added back to the radius fitted to a super-pixel mask.
ALL_SITES_SHRINK_PX = 1.0 / math.pi

#: Observations lit more grazing than acos(0.2) ≈ 78° are left out too: dim (s0 ~ 8 % of the
#: median) yet strongly polarised, they are what eq. 25's outlier rule flags when the highlight
#: is not (4 such pixels took weight 111 each and moved a Baek sphere's fitted μ from 1.61 to 1.82).
MIN_COS_LIGHT = 0.2

#: Mesh files ``--shape`` accepts (with ``--pose``).
MESH_SUFFIXES: tuple[str, ...] = (".ply", ".obj", ".stl", ".off", ".glb")

@dataclass(frozen=True)
class MeasureResult:
    """What :func:`measure_material` wrote and found.

    Attributes:
        out: the result folder. material: the material.json written. fits: every model's fit.
        held_out: leave-one-frame-out errors (empty with one frame). ranking: models, best first.
        summary: one line for the command line.
    """

    out: Path
    material: MaterialFile
    fits: dict[str, ModelFit]
    held_out: dict[str, HeldOutErrors]
    ranking: list[str]
    summary: str


# --- input ---------------------------------------------------------------------------------------


def select_frames(capture: Capture, frames: Sequence[int] | None) -> Capture:
    """The capture restricted to the frames ``frames`` (indices in capture.yaml's order; None = all).

    Raises:
        ConfigError: an index out of range or repeated.
    """
    if frames is None:
        return capture
    idx = [int(i) for i in frames]
    k = capture.num_lights
    bad = [i for i in idx if not 0 <= i < k]
    if bad or not idx or len(set(idx)) != len(idx):
        raise ConfigError(f"--frames {idx}: give distinct frame indices in 0..{k - 1} (the capture has {k} frames)")
    spec = capture.spec.model_copy(update={"lights": tuple(capture.spec.lights[i] for i in idx)})
    brackets = None if capture.brackets is None else capture.brackets[idx]
    return dataclasses.replace(capture, spec=spec, frames=capture.frames[idx], brackets=brackets)


def _brightest_s0(capture: Capture) -> np.ndarray:
    """(H, W) brightest super-pixel s0 over the frames, fraction of full scale."""
    mosaic = counts_to_float(capture.frames, capture.bit_depth, capture.spec.camera.black_level, dtype=torch.float64)
    s0 = split_mosaic(mosaic, capture.layout).mean(-3) * 2  # (K, H, W): ½ Σ of the four sites
    return s0.amax(0).numpy()


def _sphere_silhouette(capture: Capture) -> tuple[np.ndarray, int]:
    """(mask, pixels per super-pixel: 2 for the raw mosaic grid, 1 for the super-pixel grid).

    The capture's mask.png at mosaic resolution when there is one: reduced to super-pixels (a block
    is in when all four sites are) the silhouette shrinks by ≈ 0.3 super-pixel, which biases the
    fitted radius (measured: 13.31 instead of 13.71 super-pixels)."""
    if capture.root is not None and (capture.root / MASK_FILE).is_file():
        raw = read_image(capture.root / MASK_FILE)
        if raw.ndim == 2 and raw.shape == capture.frames.shape[1:]:
            return raw != 0, 2
    if capture.mask is not None:
        return np.asarray(capture.mask, dtype=bool), 1
    warnings.warn(
        "the capture has no mask.png: the sphere's silhouette is taken as the brightest region of the frames, "
        "which misses the unlit part of the sphere under few lights (the fitted sphere is then too small); "
        "add mask.png for an exact silhouette", SuspiciousInputWarning, stacklevel=3)
    try:
        return sphere_mask_from_image(_brightest_s0(capture)), 1
    except ValueError as err:
        raise ConfigError(f"--shape sphere: {err}") from None


# --- geometry ------------------------------------------------------------------------------------


def sphere_normals(capture: Capture) -> np.ndarray:
    """(H, W, 3) camera-frame unit normals of the sphere fitted to the capture's silhouette
    (super-pixel grid; NaN off the sphere). See the module docstring.

    Raises:
        ConfigError: no usable silhouette.
    """
    mask, scale = _sphere_silhouette(capture)
    camera = capture_camera(capture, "centre")
    k, h2, w2 = capture.frames.shape
    h, w = h2 // 2, w2 // 2
    try:
        if camera.projection == "orthographic":
            sphere = fit_sphere(mask)
            # super-pixel (u, v) is the block centre, raw (2u + ½, 2v + ½)
            cu, cv = ((c - 0.5) / 2 for c in sphere.center_uv) if scale == 2 else sphere.center_uv
            radius = sphere.radius_px / 2 if scale == 2 else sphere.radius_px + ALL_SITES_SHRINK_PX
            vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
            x = (uu - cu) / radius
            y = (vv - cv) / radius
            z2 = 1.0 - x * x - y * y
            inside = z2 > 0
            z = -np.sqrt(np.where(inside, z2, 0.0))  # facing the camera: N_z < 0 (rays along +z)
            normals = np.stack([x, y, z], -1)
        else:
            # the silhouette cone (axis, half-angle) is the same on either grid: use the mask's own
            grid = camera_from_spec(capture.spec.camera, w2, h2) if scale == 2 else camera
            intrinsics = Intrinsics(fx=grid.fx, fy=grid.fy, cx=grid.cx, cy=grid.cy,
                                    distortion=tuple(grid.distortion or ()))
            sphere = fit_sphere(mask, intrinsics)
            assert sphere.axis is not None and sphere.half_angle_rad is not None
            centre = np.asarray(sphere.axis)  # sphere centre at unit distance: normals do not depend on the scale
            # the super-pixel mask's shrink (ALL_SITES_SHRINK_PX), as an angle at the silhouette
            grow = 0.0 if scale == 2 else ALL_SITES_SHRINK_PX / math.sqrt(grid.fx * grid.fy)
            radius = math.sin(sphere.half_angle_rad + grow)
            d = -camera.pixel_view_directions().numpy()  # (H, W, 3) rays camera → surface
            b = d @ centre
            disc = b * b - (1.0 - radius * radius)
            inside = disc > 0
            t = b - np.sqrt(np.where(inside, disc, 0.0))
            normals = (t[..., None] * d - centre) / radius
    except ValueError as err:
        raise ConfigError(f"--shape sphere: cannot fit a sphere to the silhouette ({err}); check mask.png") from None
    logger.info("sphere: centre (%.2f, %.2f), radius %.2f pixels of the %s grid", *sphere.center_uv, sphere.radius_px,
                "mosaic" if scale == 2 else "super-pixel")
    normals[~inside] = np.nan
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def normals_from_file(path: Path, shape_hw: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) unit normals from a ``.npy`` normal map (camera frame; NaN or zero = unknown).

    Raises:
        ConfigError: unreadable, wrong shape, or no finite normal.
    """
    try:
        normals = np.load(path, allow_pickle=False).astype(np.float64)
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: cannot read the normal map ({err}); give a .npy array (H/2, W/2, 3)") from None
    if normals.shape != (*shape_hw, 3):
        raise ConfigError(f"{path}: a normal map must have shape {(*shape_hw, 3)} (the capture's super-pixel grid, "
                          f"camera frame); got {normals.shape}")
    norm = np.linalg.norm(normals, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = np.where(norm > 1e-6, normals / norm, np.nan)
    if not np.isfinite(normals).all(-1).any():
        raise ConfigError(f"{path}: the normal map holds no finite normal")
    return normals


def load_pose(path: Path) -> np.ndarray:
    """(4, 4) rigid object → camera transform from a ``.npy`` or text file holding a 4×4 matrix or
    R|t (3×4), camera frame, metres.

    Raises:
        ConfigError: unreadable, wrong shape, or R not a rotation.
    """
    try:
        m = np.load(path, allow_pickle=False) if path.suffix.lower() == ".npy" else np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as err:
        raise ConfigError(f"--pose {path}: cannot read it ({err}); give a 4x4 or 3x4 matrix (.npy or text)") from None
    m = np.asarray(m, dtype=np.float64)
    if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        raise ConfigError(f"--pose {path}: a pose is a finite 4x4 or 3x4 (R|t) matrix; got shape {m.shape}")
    pose = np.eye(4)
    pose[:3] = m[:3]
    r = pose[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0:
        raise ConfigError(f"--pose {path}: R (the upper-left 3x3) is not a rotation (R^T R = I, det R = +1); scale "
                          "the mesh file itself if it is not in metres")
    return pose


def _raw_pixel_size(capture: Capture, pixel_size_m: float | None) -> float:
    """Orthographic: metres per raw pixel — given, else the simulated scene's (ground truth)."""
    if pixel_size_m is not None:
        return float(pixel_size_m)
    scene = capture.ground_truth.get("scene")
    raw = (scene.get("scene") or {}).get("camera", {}).get("pixel_size_m") if isinstance(scene, dict) else None
    if isinstance(raw, (int, float)) and raw > 0:
        return float(raw)
    raise ConfigError("an orthographic capture has no metric scale: give --pixel-size-m (metres per raw pixel on "
                      "the object) to place the mesh")


def mesh_normals(capture: Capture, mesh_path: Path, pose: np.ndarray, *, pixel_size_m: float | None = None
                 ) -> np.ndarray:
    """(H, W, 3) camera-frame unit normals of a posed mesh, ray cast at the capture's raw pixels
    (:func:`polarshape.scene.raycast.rasterize`) and reduced to super-pixels as the simulator's
    ground truth is (a super-pixel is on the mesh when all four sites are); NaN off the mesh.

    Args:
        capture: the capture (camera). mesh_path: any mesh trimesh reads, metres.
        pose: (4, 4) object → camera transform (:func:`load_pose`).
        pixel_size_m: orthographic: metres per raw pixel (default: the simulated scene's).

    Raises:
        ConfigError: unreadable mesh, no metric scale, the mesh not in view.
    """
    import trimesh

    k, h2, w2 = capture.frames.shape
    size = _raw_pixel_size(capture, pixel_size_m) if capture.spec.camera.projection == "orthographic" else 1.0
    camera = camera_from_spec(capture.spec.camera, w2, h2, pixel_size_m=size)
    try:
        mesh = trimesh.load(mesh_path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        raise ConfigError(f"--shape {mesh_path}: cannot load the mesh ({exc}); give a file trimesh reads") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(f"--shape {mesh_path}: the file holds no triangles")
    mesh.apply_transform(pose)
    geometry = rasterize([MeshShape(mesh)], camera)
    normals, _, on = superpixel_ground_truth(geometry)
    if not bool(on.any()):
        raise ConfigError(f"--shape {mesh_path}: the posed mesh covers no pixel of the image; check --pose (object → "
                          "camera, metres, OpenCV frame: z into the scene)" + (" and --pixel-size-m" if size != 1.0 else ""))
    return normals.numpy()


def _shape_normals(capture: Capture, shape: str | Path, pose: str | Path | None, pixel_size_m: float | None
                   ) -> tuple[np.ndarray, str]:
    """(normals (H, W, 3), what they are) for ``--shape``."""
    if str(shape) == "sphere":
        return sphere_normals(capture), "sphere"
    path = Path(shape)
    if not path.is_file():
        raise ConfigError(f"--shape {path}: no such file")
    if path.suffix.lower() in MESH_SUFFIXES:
        if pose is None:
            raise ConfigError(f"--shape {path}: a mesh needs --pose (a 4x4 or 3x4 object → camera matrix, .npy or text)")
        return mesh_normals(capture, path, load_pose(Path(pose)), pixel_size_m=pixel_size_m), str(path)
    if path.suffix.lower() != ".npy":
        raise ConfigError(f"--shape {path}: give 'sphere', a .npy normal map (H/2, W/2, 3) or a mesh "
                          f"({', '.join(MESH_SUFFIXES)}) with --pose")
    k, h2, w2 = capture.frames.shape
    return normals_from_file(path, (h2 // 2, w2 // 2)), str(path)


# --- observations ----------------------------------------------------------------------------


def _observations(capture: Capture, normals: np.ndarray, device: str) -> tuple[torch.Tensor, Observations, np.ndarray]:
    """(normals (P, 3), observations, the (H, W) pixels used) of the known, non-grazing pixels."""
    if capture.lights().has_point_lights:
        raise ConfigError("capture.yaml has point lights: `polarshape material` supports directional lights only "
                          "(a point light's direction needs the object's 3-D points)")
    view = capture_camera(capture, "centre").pixel_view_directions().numpy()  # (H, W, 3)
    known = np.isfinite(normals).all(-1)
    cos_v = np.where(known, np.nan_to_num(normals * view).sum(-1), -1.0)
    if known.any() and np.median(cos_v[known]) < 0:
        raise ConfigError("the normals face away from the camera (N·V < 0); the camera frame is OpenCV's (z into the "
                          "scene), so a surface facing the camera has N_z < 0: negate the normal map")
    pixels = known & (cos_v >= MIN_COS_VIEW)
    if capture.mask is not None:
        pixels &= np.asarray(capture.mask, dtype=bool)
    if not pixels.any():
        raise ConfigError("no pixel has a known normal facing the camera inside the mask")
    inputs = preprocess_capture(dataclasses.replace(capture, mask=pixels), dtype=torch.float64, device=device)
    sel = torch.as_tensor(pixels, device=inputs.mask.device) & inputs.mask
    obs = flatten_observations(inputs, sel)
    n = torch.as_tensor(normals, dtype=torch.float64, device=inputs.mask.device)[sel]
    lit = (n.unsqueeze(1) * obs.lights).sum(-1) >= MIN_COS_LIGHT  # (P, K)
    obs = Observations(obs.stokes, obs.weight * lit.to(obs.weight.dtype), obs.lights, obs.irradiance, obs.view)
    return n, obs, sel.cpu().numpy()


# --- report ----------------------------------------------------------------------------------


def _curve_angles(normals: torch.Tensor, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """(θ_H, θ_V) in degrees of every observation (P, K): the half-vector angle (the specular
    lobe's axis) and the viewing angle (the body DoLP's axis)."""
    n, l, v = torch.broadcast_tensors(normals.unsqueeze(1), obs.lights, obs.view.unsqueeze(1))
    h = safe_normalize(l + v)
    return np.degrees(angle_between(n, h).numpy()), np.degrees(angle_between(n, v).numpy())


def _binned(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> np.ndarray:
    idx = np.digitize(x, edges) - 1
    return np.array([np.median(y[idx == i]) if (idx == i).any() else np.nan for i in range(len(edges) - 1)])


def _plot_curves(folder: Path, normals: torch.Tensor, obs: Observations, fits: dict[str, ModelFit]) -> list[str]:
    """intensity_curve.png (s0 vs θ_H) and dolp_curve.png (DoLP vs θ_V): observed points and binned
    medians, each model's fitted values' binned medians."""
    from matplotlib.figure import Figure  # ~0.7 s to import: only when a plot is drawn
    valid = (obs.weight > 0).numpy()
    th_h, th_v = _curve_angles(normals, obs)
    observed = obs.stokes
    written = []
    for name, x, quantity, xlabel in (("intensity_curve.png", th_h, "s0", "θ_H: angle between N and H (deg)"),
                                      ("dolp_curve.png", th_v, "DoLP", "θ_V: angle between N and V (deg)")):
        fig = Figure(figsize=(6.4, 4.2))
        ax = fig.add_subplot()

        def value(s: torch.Tensor) -> np.ndarray:
            return (s[..., 0] if quantity == "s0" else dolp(s, dim=-1, eps=1e-6)).numpy()

        xs, ys = x[valid], value(observed)[valid]
        edges = np.linspace(0.0, max(float(xs.max()), 1.0) + 1e-6, 25)
        mid = 0.5 * (edges[1:] + edges[:-1])
        ax.scatter(xs, ys, s=3, c="0.7", label="observed")
        ax.plot(mid, _binned(xs, ys, edges), "k-", lw=2, label="observed (median)")
        for model, fit in fits.items():
            fitted = value(render_model(model, fit.params, normals, obs))[valid]
            ax.plot(mid, _binned(xs, fitted, edges), "--", lw=1.5, label=MODEL_NAMES.get(model, model))
        ax.set_xlabel(xlabel)
        ax.set_ylabel("intensity s0 (fraction of full scale)" if quantity == "s0" else "DoLP")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(folder / name, dpi=110)
        written.append(name)
    return written


def _plot_held_out(folder: Path, held_out: dict[str, HeldOutErrors]) -> str:
    from matplotlib.figure import Figure
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.add_subplot()
    names = list(held_out)
    ax.bar(np.arange(len(names)) - 0.2, [held_out[m].mean_relative_rmse for m in names], 0.4, label="intensity s0")
    ax.bar(np.arange(len(names)) + 0.2, [held_out[m].mean_dolp_relative_rmse for m in names], 0.4, label="DoLP")
    ax.set_xticks(np.arange(len(names)), [MODEL_NAMES.get(m, m) for m in names], fontsize=7)
    ax.set_ylabel("held-out relative RMSE (mean over frames)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "held_out.png", dpi=110)
    return "held_out.png"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table border=1 cellpadding=3 style='border-collapse:collapse'><tr>{head}</tr>{body}</table>"


def _write_report(folder: Path, normals: torch.Tensor, obs: Observations, fits: dict[str, ModelFit],
                  held_out: dict[str, HeldOutErrors], ranking: list[str], material: MaterialFile, source: dict[str, Any]
                  ) -> None:
    pngs = _plot_curves(folder, normals, obs, fits)
    parts = [f"<h1>Material of {html.escape(str(source.get('capture')))}</h1>",
             f"<p>shape: {html.escape(str(source.get('shape')))}; frames {source.get('frames')}; "
             f"{obs.num_pixels} pixels; objective: eq. 25 (intensity + DoLP with outlier weights). "
             f"material.json holds <b>{material.model}</b>; best model: <b>{ranking[0]}</b>.</p>",
             "<h2>Fits</h2>",
             _table(["model", "eq. 25 loss", "s0 RMS", "s0 relative RMSE", "DoLP relative RMSE", "seconds"],
                    [[MODEL_NAMES.get(m, m), f"{fits[m].loss:.4g}", f"{fits[m].residual_rms:.4g}",
                      f"{fits[m].relative_rmse:.4f}", f"{fits[m].dolp_relative_rmse:.4f}", f"{fits[m].seconds:.1f}"]
                     for m in ranking if m in fits])]
    parts.append("<h2>Parameters</h2>")
    for m, fit in fits.items():
        parts.append(f"<h3>{html.escape(MODEL_NAMES.get(m, m))}</h3>")
        parts.append(_table(["parameter", "value", "meaning", "unit"],
                            [[k, f"{v:.5g}", PARAMETER_MEANINGS.get(k, ("", "", ""))[1], MATERIAL_UNITS.get(k, "1")]
                             for k, v in fit.params.items()]))
    parts.append("<h2>Observed and fitted curves</h2>")
    parts += [f"<img src='{p}'>" for p in pngs]
    if held_out:
        parts.append("<h2>Held-out frames (each predicted from a fit to the others; Fig. 7's metric)</h2>")
        frames = next(iter(held_out.values())).frames
        parts.append(_table(["model", *[f"frame {f}" for f in frames], "mean s0", "mean DoLP"],
                            [[MODEL_NAMES.get(m, m), *[f"{e:.4f}" for e in h.relative_rmse],
                              f"{h.mean_relative_rmse:.4f}", f"{h.mean_dolp_relative_rmse:.4f}"]
                             for m, h in held_out.items()]))
        parts.append(f"<img src='{_plot_held_out(folder, held_out)}'>")
    parts.append(f"<p>polarshape {__version__}</p>")
    atomic_write_text(folder / "report.html", "<!doctype html><meta charset=utf-8><title>polarshape material</title>"
                      + "\n".join(parts) + "\n")


# --- material.json ---------------------------------------------------------------------------


def _material_model(models: Sequence[str], ranking: list[str]) -> str:
    if "fmbrdf" in models:
        return "fmbrdf"
    for m in ranking:
        if m not in COMPOSITE_MODELS:
            return m
    raise ConfigError(f"--models {','.join(models)}: material.json holds one model, and the composites "
                      f"{', '.join(COMPOSITE_MODELS)} cannot be written to one; add fmbrdf or baek")


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (material.json is strict JSON)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _material_file(model: str, fits: dict[str, ModelFit], fit_record: dict[str, Any], source: dict[str, Any]
                   ) -> MaterialFile:
    params = fits[model].params
    if model == "fmbrdf":
        p = FMBRDFParams(**{k: params[k] for k in ("ior", "alpha", "beta", "kappa", "k_s", "k_b")})
        return MaterialFile.from_fmbrdf(p, fit=fit_record, source=source)
    names = model_parts(model)
    assert len(names) == 1
    return MaterialFile(model=model, parameters=dict(params),  # type: ignore[arg-type]
                        units={k: MATERIAL_UNITS[k] for k in params}, fit=fit_record, source=source)


def _protect(inputs: Sequence[Path | None], overwrite: bool) -> Callable[[Path], str | None]:
    """The folder check of :func:`polarshape.io.atomic.atomic_directory`: never an input; with
    ``overwrite`` only over an empty folder, a material folder or a result folder."""
    def reason(path: Path) -> str | None:
        why = output_refusal(path, inputs, overwrite=False)
        if why:
            return why
        if overwrite and path.is_dir() and any(path.iterdir()) and not (path / "material.json").exists() \
                and not is_result_folder(path):
            return "it is not a polarshape material folder (no material.json), and --overwrite only replaces those"
        return None
    return reason


def _validate_models(models: Sequence[str]) -> tuple[str, ...]:
    out = tuple(dict.fromkeys(models))
    if not out:
        raise ConfigError("--models: give at least one model")
    for m in out:
        try:
            model_parts(m)
        except ValueError as err:
            raise ConfigError(f"--models: {err}") from None
    return out


def measure_material(
    capture: str | Path | Capture,
    *,
    shape: str | Path = "sphere",
    out: str | Path,
    frames: Sequence[int] | None = None,
    models: Sequence[str] = FIT_MODELS,
    held_out: bool = True,
    overwrite: bool = False,
    device: str = "cpu",
    pose: str | Path | None = None,
    pixel_size_m: float | None = None,
) -> MeasureResult:
    """Fit the material of an object of known geometry and write OUT/material.json and OUT/report.html.

    Args:
        capture: capture folder (or a loaded :class:`Capture`).
        shape: ``"sphere"``, a ``.npy`` normal map (H/2, W/2, 3), camera frame, or a mesh file
            (:data:`MESH_SUFFIXES`) placed by ``pose`` (module docstring).
        out: result folder (created atomically; never over an input, over an existing folder only
            with ``overwrite`` and only when it is a material or result folder).
        frames: frame indices to use (default all).
        models: fit models (:data:`polarshape.recover.material_fit.FIT_MODELS`, or plain model names).
        held_out: with K ≥ 2 frames, also predict each frame from a fit to the others.
        overwrite: replace an existing result folder.
        device: torch device of the fit.
        pose: a mesh's object → camera transform file (:func:`load_pose`).
        pixel_size_m: a mesh in an orthographic capture: metres per raw pixel (default: the
            simulated scene's).

    Returns:
        :class:`MeasureResult`.

    Raises:
        ConfigError: bad shape, frames or models; CaptureError: bad capture; OutputExistsError.
    """
    t0 = time.perf_counter()
    models = _validate_models(models)
    out = Path(out)
    cap_path = None if isinstance(capture, Capture) else Path(capture)
    shape_path = None if str(shape) == "sphere" else Path(shape)
    protect = _protect([cap_path, shape_path, None if pose is None else Path(pose)], overwrite)
    why = protect(out.absolute())
    if why:
        raise OutputExistsError(f"{out.absolute()}: {why}; refusing to write there")
    check_destination(out.absolute(), overwrite)  # before the fit, the same refusal as the folder's write
    cap = load_capture(cap_path) if cap_path is not None else capture
    assert isinstance(cap, Capture)
    cap = select_frames(cap, frames)
    normals_map, shape_name = _shape_normals(cap, shape, pose, pixel_size_m)
    normals, obs, used = _observations(cap, normals_map, device)
    fits = {m: fit_model(m, normals, obs) for m in models}
    k = int(obs.stokes.shape[1])
    errors = held_out_errors(normals, obs, models) if held_out and k >= 2 else {}
    ranking = rank_models(fits, errors)
    chosen = _material_model(models, ranking)
    source = {"capture": str(cap.root or cap_path), "shape": shape_name, "pose": None if pose is None else str(pose),
              "frames": list(frames) if frames is not None else list(range(cap.num_lights)),
              "frame_files": [light.frame for light in cap.spec.lights], "pixels": int(used.sum()),
              "polarshape": __version__}
    record: dict[str, Any] = {"objective": "eq25", "observations": fits[chosen].observations,
              "residual_rms": fits[chosen].residual_rms, "relative_rmse": fits[chosen].relative_rmse,
              "best_model": ranking[0], "ranking": ranking,
              "ranked_by": "mean held-out s0 relative RMSE" if errors else "eq. 25 loss",
              "models": {m: f.as_dict() for m, f in fits.items()},
              "held_out": {m: h.as_dict() for m, h in errors.items()}}
    material = _material_file(chosen, fits, _finite(record), source)
    with atomic_directory(out, overwrite=overwrite, protect=protect) as tmp:
        write_material(tmp / "material.json", material)
        _write_report(tmp, normals, obs, fits, errors, ranking, material, source)
    p = material.parameters
    shown = ", ".join(f"{k_}={v:.4g}" for k_, v in p.items())
    summary = (f"{out}: {material.model} {shown}; best model {ranking[0]} "
               f"({time.perf_counter() - t0:.1f} s)")
    return MeasureResult(out, material, fits, errors, ranking, summary)


def measure_table(table: str | Path, *, out: str | Path, overwrite: bool = False, fit_kappa: bool = False
                  ) -> tuple[Path, MaterialFile, str]:
    """The FMBRDF fitted to a tabulated BRDF (a MERL binary file,
    :func:`polarshape.recover.table_fit.fit_material_table`), written as OUT/material.json.

    Args:
        table: the MERL ``.binary`` file (read only).
        out: the folder to write (atomically; never the table's folder or over an input).
        overwrite: replace an existing material or result folder.
        fit_kappa: fit κ too (5–10× slower; intensity determines it only weakly).

    Returns:
        (out, material, one-line summary).
    """
    from polarshape.recover.table_fit import fit_material_table

    table, out = Path(table), Path(out)
    protect = _protect([table], overwrite)
    why = protect(out.absolute())
    if why:
        raise OutputExistsError(f"{out.absolute()}: {why}; refusing to write there")
    check_destination(out.absolute(), overwrite)  # before the fit, the same refusal as the folder's write
    material, report = fit_material_table(table, fit_kappa=fit_kappa)
    with atomic_directory(out, overwrite=overwrite, protect=protect) as tmp:
        write_material(tmp / "material.json", material)
    p = material.parameters
    summary = (f"{out}: fmbrdf ior {p['ior']:.3f}, alpha {p['alpha']:.3f} rad, beta {p['beta']:.2f}, kappa "
               f"{p['kappa']:.1f}, k_s {p['k_s']:.3g}, k_b {p['k_b']:.3g}; log-RMSE {report['log_rmse']:.4g} over "
               f"{report['samples']} cells of {table.name}")
    logger.info("%s", summary)
    return out, material, summary
