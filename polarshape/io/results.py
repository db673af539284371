"""The result folder of ``polarshape run``: its files, its params.json, and what it may replace.

Files (spec capture-format.md, README "Result folder"): ``normals.npy`` (H, W, 3) float32 camera-frame
unit normals, NaN outside the mask; ``normal_map.png`` (16-bit RGBA, alpha 0 outside the mask,
convention in params.json); ``normals.exr`` (float32 R, G, B = normal, A = mask); ``albedo.npy`` /
``albedo.png`` ((H, W), 16-bit grey; a colour capture's (H, W, 3), 16-bit RGB: R, G, B body albedo,
one linear scale for the three channels, 65535 = the 99.5th percentile of all their values); ``depth.npy``; ``mask.png``; ``filled.png``; ``materials.npy`` / ``materials.png`` /
``mixed.png`` (:func:`write_material_maps`: which material each pixel is, its edges);
``config.yaml``; ``params.json`` (format :data:`RESULT_FORMAT`, with the polarshape version).
Meshes and the report are written by their own stages into the same (temporary) folder.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from polarshape.io.export import (
    write_normal_map_png, write_normals_exr, write_npy, write_rgb_png, write_scalar_map_png,
)
from polarshape.io.atomic import atomic_write_text
from polarshape.io.images import write_image

__all__ = [
    "MATERIAL_COLOURS", "RESULT_FORMAT", "is_result_folder", "output_refusal", "plain_json", "write_maps",
    "write_material_maps", "write_params",
]

#: Format tag of params.json.
RESULT_FORMAT = "polarshape-result/1"


def write_maps(
    folder: Path, *, normals: np.ndarray, mask: np.ndarray, depth: np.ndarray, albedo: np.ndarray | None,
    filled: np.ndarray | None, normal_convention: str, exr: bool,
) -> list[str]:
    """Write the per-pixel result files into ``folder``; returns what was not written, with the reason.

    Args:
        normals: (H, W, 3) float normals, NaN outside the mask. mask: (H, W) bool.
        depth: (H, W) camera-frame z, NaN outside. albedo: (H, W), (H, W, 3) R, G, B (a colour capture;
        one scale for the three channels) or None. filled: (H, W) bool or None.
        normal_convention: ``opencv`` or ``opengl`` (normal_map.png, 16-bit RGBA, alpha 0 outside the
        mask). exr: also write normals.exr (RGBA: A = 1 inside the mask, 0 outside).
    """
    skipped: list[str] = []
    shown = np.where(mask[..., None], normals, np.nan)  # (H, W, 3): background = outside the mask
    write_npy(normals.astype(np.float32), folder / "normals.npy")
    write_normal_map_png(shown, folder / "normal_map.png", convention=normal_convention)
    if exr:
        write_normals_exr(normals, folder / "normals.exr", mask)
    else:
        skipped.append("normals.exr: export.exr is false")
    write_npy(depth.astype(np.float32), folder / "depth.npy")
    write_image(folder / "mask.png", np.where(mask, 255, 0).astype(np.uint8))
    if filled is not None:
        write_image(folder / "filled.png", np.where(filled, 255, 0).astype(np.uint8))
    if albedo is not None:
        write_npy(albedo.astype(np.float32), folder / "albedo.npy")
        finite = albedo[np.isfinite(albedo)]
        vmax = float(np.percentile(finite, 99.5)) if finite.size else 1.0
        write_scalar_map_png(albedo, folder / "albedo.png", 0.0, max(vmax, 1e-12))
    else:
        skipped.append("albedo.png: the model estimated no albedo map")
    return skipped


#: RGB of material 0, 1, 2, … in materials.png (repeated beyond; black outside the mask).
MATERIAL_COLOURS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
)


def write_material_maps(folder: Path, *, materials: np.ndarray, mixed: np.ndarray | None) -> None:
    """``materials.npy`` (H, W) int16 material index (−1 outside the mask), ``materials.png`` (8-bit
    RGB, material m in :data:`MATERIAL_COLOURS` [m], black outside the mask) and ``mixed.png`` (255 on
    the pixels of a material edge, left out of the material fits, or of an albedo edge, left out of every fit)."""
    write_npy(materials.astype(np.int16), folder / "materials.npy")
    palette = np.asarray(MATERIAL_COLOURS, dtype=np.uint8)  # (C, 3)
    rgb = np.where((materials >= 0)[..., None], palette[np.clip(materials, 0, None) % len(palette)], 0)
    write_rgb_png(rgb.astype(np.uint8), folder / "materials.png")
    if mixed is not None:
        write_image(folder / "mixed.png", np.where(mixed, 255, 0).astype(np.uint8))


def write_params(folder: Path, params: dict[str, Any]) -> dict[str, Any]:
    """Write ``params.json`` (JSON-ready copy of ``params``, NaN → null) atomically; returns the copy."""
    plain = plain_json(params)
    atomic_write_text(folder / "params.json", json.dumps(plain, indent=1, allow_nan=False))
    return plain


def is_result_folder(path: Path) -> bool:
    """True when ``path`` is a folder written by ``polarshape run``: its params.json has the format
    tag :data:`RESULT_FORMAT`."""
    try:
        return json.loads((path / "params.json").read_text()).get("format") == RESULT_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def output_refusal(path: Path, inputs: Iterable[str | Path | None], *, overwrite: bool) -> str | None:
    """Why a result folder may not be written at ``path``, or None when it may.

    Refused: ``path`` is an input (a capture, the config, the scene, the session file), holds one,
    or lies inside an input folder (``--out CAP/frames``); it holds a capture (capture.yaml); or,
    with ``overwrite``, it exists and is not a polarshape result (:func:`is_result_folder`) — only
    a previous result (or an empty folder) is ever replaced.
    """
    path = path.resolve()
    for item in inputs:
        if item is None:
            continue
        p = Path(item).resolve()
        if p.name == "capture.yaml" and p.is_file():
            p = p.parent  # a capture given by its capture.yaml: the folder is the input
        if p == path or path in p.parents:
            return f"it is or holds the input {p}"
        if p.is_dir() and p in path.parents:
            return f"it lies inside the input folder {p}"
    if path.exists() and (path / "capture.yaml").exists():
        return "it holds a capture (capture.yaml)"
    empty = path.is_dir() and not any(path.iterdir())
    if overwrite and path.exists() and not empty and not is_result_folder(path):
        kind = "folder" if path.is_dir() else "file"
        return (f"this {kind} is not a polarshape result (no params.json of format {RESULT_FORMAT}), and "
                "--overwrite only replaces results; choose another --out or remove it yourself")
    return None


def plain_json(value: Any) -> Any:
    """JSON-ready copy: numpy/torch scalars and arrays to Python, paths to text, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    if isinstance(value, torch.Tensor):
        return plain_json(value.detach().cpu().tolist())
    if isinstance(value, np.ndarray):
        return plain_json(value.tolist())
    if isinstance(value, np.generic):
        return plain_json(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    raise TypeError(f"params.json: cannot serialise a {type(value).__name__}")
