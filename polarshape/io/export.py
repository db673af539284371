"""Result files: normal-map and parameter-map PNGs, NumPy arrays, OpenEXR images (all atomic).

Every writer goes through :mod:`polarshape.io.atomic`: the file appears complete or not at all, and an
existing file is replaced only with ``overwrite=True`` (else ``OutputExistsError``).

Normal-map PNG (``normal_map.png`` of a result folder): 16-bit RGBA (or RGB with ``alpha=False``),
channel = round((c + 1)/2 · 65535) with (R, G, B) = (c_x, c_y, c_z); A = 65535 where the normal is
known, 0 on the background (a NaN normal), whose RGB is (0, 0, 0). c is the normal in the chosen
convention:
- ``"opencv"``: polarshape's camera frame as it is (spec §1): x right, y down, z forward (into the
  scene). Camera-facing normals have c_z < 0, so B < 32768: a frontal surface is (32768, 32768, 0).
- ``"opengl"``: OpenGL / Blender view space: x right, y up, z towards the viewer, i.e.
  c = (n_x, −n_y, −n_z). Camera-facing normals have c_z > 0: a frontal surface is (32768, 32768, 65535),
  the familiar light-blue normal map; a surface tilted to the top of the image has G > 32768.
Decoding (:func:`read_normal_map_png`) inverts this to within 1/65535 per component (no renormalisation),
NaN where A = 0 (RGBA) or where RGB = (0, 0, 0) (an RGB file).

Normals EXR (:func:`write_normals_exr`): float32 channels R, G, B = the camera-frame normal and
A = 1 on the object, 0 on the background, whose RGB is 0 (associated alpha, as OpenEXR and
compositors expect; NaN would spread through every filter and "over" operation).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from polarshape.checks import to_numpy
from polarshape.io.atomic import atomic_path, atomic_write_bytes

logger = logging.getLogger(__name__)

__all__ = [
    "NormalConvention", "read_exr", "read_normal_map_png", "read_normals_exr", "write_exr", "write_normal_map_png",
    "write_normals_exr", "write_npy", "write_rgb_png", "write_scalar_map_png",
]

NormalConvention = Literal["opencv", "opengl"]
_U16_MAX = 65535.0
# Flip from polarshape's camera frame (x right, y down, z forward) to each convention (an involution).
_CONVENTION_SIGNS: dict[str, NDArray[np.float64]] = {
    "opencv": np.array([1.0, 1.0, 1.0]),
    "opengl": np.array([1.0, -1.0, -1.0]),
}
_EXR_ORDER_ATTRIBUTE = "polarshape_channel_order"


def _signs(convention: str) -> NDArray[np.float64]:
    if convention not in _CONVENTION_SIGNS:
        raise ValueError(f"convention must be 'opencv' or 'opengl'; got {convention!r}")
    return _CONVENTION_SIGNS[convention]


def _swap_red_blue(image: NDArray[Any]) -> NDArray[Any]:
    """RGB(A) ↔ BGR(A) of an (H, W, C ≥ 3) image; grey images as they are."""
    if image.ndim != 3 or image.shape[2] < 3:
        return image
    return image[..., [2, 1, 0, *range(3, image.shape[2])]]


def _encode_png(image: NDArray[Any], path: Path) -> bytes:
    """PNG bytes of an (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA uint8/uint16 image."""
    bgr = _swap_red_blue(image)  # OpenCV stores colour as BGR(A)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr))
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode the PNG")
    return buf.tobytes()


def write_rgb_png(image: NDArray[Any], path: str | os.PathLike[str], *, overwrite: bool = True) -> Path:
    """Write an (H, W, 3) RGB uint8 or uint16 image as a PNG, atomically (colour in RGB order, not
    OpenCV's BGR). Returns the path written."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"an RGB image must have shape (H, W, 3); got {image.shape}")
    path = Path(path)
    return atomic_write_bytes(path, _encode_png(image, path), overwrite=overwrite)


def _decode_png(path: str | os.PathLike[str]) -> NDArray[Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such PNG file")
    image = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: not a readable PNG image")
    return _swap_red_blue(image)


def write_normal_map_png(
    normals: Any,
    path: str | os.PathLike[str],
    *,
    convention: NormalConvention = "opencv",
    alpha: bool = True,
    overwrite: bool = False,
) -> Path:
    """Write a normal map as a 16-bit RGBA (or RGB) PNG (module docstring: encoding and conventions).

    Args:
        normals: (H, W, 3) camera-frame unit normals (x right, y down, z forward), NaN = background.
        path: destination .png.
        convention: "opencv" (camera frame as is) or "opengl" (x right, y up, z towards the viewer).
        alpha: add an alpha channel, 65535 where the normal is finite, 0 on the background (so that
            viewers and shaders do not read the background as a normal); False: 16-bit RGB.
        overwrite: replace an existing file.

    Returns:
        The path written.

    Example:
        >>> n = np.array([[[0.0, 0.0, -1.0]]])
        >>> write_normal_map_png(n, "normal_map.png", convention="opengl")  # doctest: +SKIP
        # pixel (32768, 32768, 65535, 65535)
    """
    n = to_numpy(normals).astype(np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3); got {n.shape}")
    signs = _signs(convention)
    background = ~np.all(np.isfinite(n), axis=2)  # (H, W)
    c = np.clip(np.nan_to_num(n) * signs, -1.0, 1.0)
    coded = np.round((c + 1.0) * 0.5 * _U16_MAX).astype(np.uint16)  # (H, W, 3)
    coded[background] = 0
    if alpha:
        a = np.where(background, 0, int(_U16_MAX)).astype(np.uint16)
        coded = np.concatenate([coded, a[..., None]], axis=2)  # (H, W, 4)
    path = Path(path)
    return atomic_write_bytes(path, _encode_png(coded, path), overwrite=overwrite)


def read_normal_map_png(path: str | os.PathLike[str], convention: NormalConvention = "opencv") -> NDArray[np.float64]:
    """Read a normal map written by :func:`write_normal_map_png` (RGBA or RGB).

    Args:
        path: a 16-bit RGBA or RGB PNG.
        convention: the convention it was written with.

    Returns:
        (H, W, 3) float64 camera-frame normals (x right, y down, z forward), NaN where alpha is 0 (an
        RGBA file) or the pixel is (0, 0, 0) (an RGB file); not renormalised (within 1/65535 of the
        written unit vectors).
    """
    signs = _signs(convention)
    image = _decode_png(path)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint16:
        raise ValueError(
            f"{path}: a normal map must be a 16-bit RGB or RGBA PNG; got dtype {image.dtype}, shape {image.shape}"
        )
    rgb = image[..., :3]
    c = rgb.astype(np.float64) / _U16_MAX * 2.0 - 1.0
    n = c * signs
    background = image[..., 3] == 0 if image.shape[2] == 4 else np.all(rgb == 0, axis=2)
    n[background] = np.nan
    return n


def write_npy(array: Any, path: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
    """Write an array as .npy atomically (e.g. ``normals.npy`` (H, W, 3) float32, ``depth.npy`` (H, W)).

    Returns:
        The path written.
    """
    path = Path(path)
    if path.suffix != ".npy":
        raise ValueError(f"{path}: NumPy arrays are written to files ending in .npy")
    a = to_numpy(array)
    with atomic_path(path, overwrite=overwrite) as tmp:
        np.save(tmp, a, allow_pickle=False)
    return path


def _default_channel_names(count: int) -> tuple[str, ...]:
    if count == 1:
        return ("Y",)
    if count == 3:
        return ("R", "G", "B")
    if count == 4:
        return ("R", "G", "B", "A")
    return tuple(f"C{i}" for i in range(count))


def write_exr(
    array: Any,
    path: str | os.PathLike[str],
    channel_names: Sequence[str] | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a float image as a 32-bit float OpenEXR file (ZIP compression), atomically.

    Args:
        array: (H, W) or (H, W, C) values (stored as float32; NaN allowed).
        path: destination .exr.
        channel_names: C names (default Y / RGB / RGBA / C0…); their order is stored in the header
            (``polarshape_channel_order``) so :func:`read_exr` returns the same layout.
        overwrite: replace an existing file.

    Returns:
        The path written.
    """
    import OpenEXR

    a = to_numpy(array).astype(np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] == 0 or a.shape[1] == 0 or a.shape[2] == 0:
        raise ValueError(f"EXR images must have shape (H, W) or (H, W, C); got {a.shape}")
    names = tuple(channel_names) if channel_names is not None else _default_channel_names(a.shape[2])
    if len(names) != a.shape[2] or len(set(names)) != len(names) or any(not s or "," in s for s in names):
        raise ValueError(f"channel_names must be {a.shape[2]} distinct non-empty names without commas; got {names}")
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        _EXR_ORDER_ATTRIBUTE: ",".join(names),
    }
    channels = {name: np.ascontiguousarray(a[..., i]) for i, name in enumerate(names)}
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise ValueError(f"{path}: OpenEXR files must end in .exr")
    with atomic_path(path, overwrite=overwrite) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
    return path


def read_exr(path: str | os.PathLike[str]) -> tuple[NDArray[np.float32], tuple[str, ...]]:
    """Read an OpenEXR file written by :func:`write_exr` (or any single-part scan-line EXR).

    Returns:
        (array (H, W, C) float32, channel names): channels in the stored order when the file has
        ``polarshape_channel_order``, else R, G, B, A first, then the rest alphabetically.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such EXR file")
    f = OpenEXR.File(str(path), separate_channels=True)
    channels = {name: ch.pixels for name, ch in f.channels().items()}
    stored = f.header().get(_EXR_ORDER_ATTRIBUTE)
    if isinstance(stored, str) and set(stored.split(",")) == set(channels):
        names = tuple(stored.split(","))
    else:
        rgba = [c for c in ("R", "G", "B", "A") if c in channels]
        names = tuple(rgba + sorted(c for c in channels if c not in rgba))
    return np.stack([np.asarray(channels[c], dtype=np.float32) for c in names], axis=-1), names


def write_normals_exr(
    normals: Any, path: str | os.PathLike[str], mask: Any | None = None, *, overwrite: bool = False
) -> Path:
    """Write camera-frame normals as an RGBA float32 OpenEXR file (module docstring).

    Args:
        normals: (H, W, 3) camera-frame unit normals (x right, y down, z forward), NaN = background.
        path: destination .exr.
        mask: optional (H, W) bool object mask; A = 1 where the mask holds and the normal is finite.
        overwrite: replace an existing file.

    Returns:
        The path written: channels R, G, B = n_x, n_y, n_z and A (1 object, 0 background, where
        R = G = B = 0).
    """
    n = to_numpy(normals).astype(np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3); got {n.shape}")
    inside = np.all(np.isfinite(n), axis=2)  # (H, W)
    if mask is not None:
        m = to_numpy(mask)
        if m.shape != inside.shape:
            raise ValueError(f"mask must have shape (H, W) = {inside.shape} to match normals; got {m.shape}")
        inside &= m.astype(bool)
    rgba = np.concatenate([np.where(inside[..., None], n, 0.0), inside[..., None]], axis=2).astype(np.float32)
    return write_exr(rgba, path, ("R", "G", "B", "A"), overwrite=overwrite)


def read_normals_exr(path: str | os.PathLike[str]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Read a normals EXR (:func:`write_normals_exr`): ((H, W, 3) normals, NaN where A = 0; (H, W) mask A > 0).

    A file without an A channel (polarshape before the alpha channel) gives the mask of finite normals.
    """
    array, names = read_exr(path)
    if not {"R", "G", "B"} <= set(names):
        raise ValueError(f"{path}: a normals EXR needs channels R, G, B (and A); got {', '.join(names)}")
    normals = np.stack([array[..., names.index(c)] for c in ("R", "G", "B")], axis=-1)  # (H, W, 3)
    inside = array[..., names.index("A")] > 0 if "A" in names else np.all(np.isfinite(normals), axis=-1)
    normals[~inside] = np.nan
    return normals, inside


def write_scalar_map_png(
    values: Any,
    path: str | os.PathLike[str],
    vmin: float,
    vmax: float,
    colormap: str | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a parameter map (e.g. albedo, roughness) as a PNG.

    Values are mapped linearly, t = clip((x − vmin)/(vmax − vmin), 0, 1):
    - ``colormap=None``: 16-bit grey, round(t · 65535); an (H, W, 3) map (e.g. a colour albedo) gives
      16-bit RGB the same way; NaN → 0;
    - ``colormap="viridis"`` (any matplotlib name): 8-bit RGB through the colour map; NaN → black.

    Args:
        values: (H, W) map (or (H, W, 3) without a colour map).
        path: destination .png.
        vmin, vmax: the value range shown (vmax > vmin).
        colormap: matplotlib colour-map name or None.
        overwrite: replace an existing file.

    Returns:
        The path written.
    """
    v = to_numpy(values).astype(np.float64)
    if not (np.isfinite(vmin) and np.isfinite(vmax) and vmax > vmin):
        raise ValueError(f"need finite vmin < vmax; got vmin={vmin}, vmax={vmax}")
    if not (v.ndim == 2 or (v.ndim == 3 and v.shape[2] == 3 and colormap is None)):
        raise ValueError(f"values must have shape (H, W) (or (H, W, 3) without a colormap); got {v.shape}")
    nan = ~np.isfinite(v)
    t = np.clip((np.nan_to_num(v) - vmin) / (vmax - vmin), 0.0, 1.0)
    if colormap is None:
        image = np.round(t * _U16_MAX).astype(np.uint16)
        image[nan] = 0
    else:
        from matplotlib import colormaps

        if colormap not in colormaps:
            raise ValueError(f"unknown matplotlib colormap {colormap!r} (e.g. 'viridis', 'magma', 'gray')")
        image = colormaps[colormap](t, bytes=True)[..., :3]  # (H, W, 3) uint8
        image[nan] = 0
    path = Path(path)
    return atomic_write_bytes(path, _encode_png(image, path), overwrite=overwrite)
