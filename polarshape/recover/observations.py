"""What the solvers see: a capture's observations as image tensors and as flat per-pixel batches.

- :class:`RecoveryInputs` — images at super-pixel resolution (H, W) under K lights, made by
  :func:`polarshape.recover.preprocess.preprocess_capture`; light directions and irradiance are
  always per pixel, (K, H, W, 3) and (K, H, W), for directional and point lights alike (what
  :meth:`polarshape.lights.Lights.illuminate` returns), so no solver tests the light type.
- :class:`ColourInputs` — a colour polarisation capture's per-channel Stokes and validity
  (``RecoveryInputs.colour``; :mod:`polarshape.recover.colour` solves its per-channel albedo);
- :class:`Observations` — the same data flattened to the P pixels being solved, pixel first.
- :func:`flatten_observations`, :func:`downsample_inputs` (the coarse-to-fine pyramid),
  :func:`crop_inputs` / :func:`paste_crop` (solve on the mask's bounding box, then put it back).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from polarshape.recover.noise import NoiseModel

__all__ = ["ColourInputs", "Observations", "RecoveryInputs", "crop_inputs", "downsample_inputs", "flatten_observations", "paste_crop"]


@dataclass(frozen=True)
class ColourInputs:
    """Per-channel observations of a colour polarisation capture (camera.mosaic.bayer), on the
    super-pixel grid of the :class:`RecoveryInputs` that hold them.

    Attributes:
        stokes: (K, 3, 3, H, W) Stokes per colour channel (R, G, B; s0, s1, s2), pixel frames,
            fraction of full scale (:func:`polarshape.imaging.colour.colour_stokes_from_mosaic`).
        valid: (K, 3, H, W) bool usable observations of each channel (the combined observation
            valid and the channel itself not dark).
        bayer: the Bayer pattern of the block grid as stored (``camera.mosaic.bayer``).
    """

    stokes: Tensor
    valid: Tensor
    bayer: str

    def crop(self, rows: slice, cols: slice) -> ColourInputs:
        """The same observations on the sub-grid ``rows``, ``cols``."""
        return ColourInputs(self.stokes[..., rows, cols], self.valid[..., rows, cols], self.bayer)


@dataclass(frozen=True)
class RecoveryInputs:
    """Tensors for recovery (super-pixel resolution H × W, K lights).

    Attributes:
        stokes: (K, 3, H, W) linear Stokes (s0, s1, s2) in each pixel's frame, fraction of full scale.
        valid: (K, H, W) bool usable observations (not dark, not saturated, inside ``mask``).
        saturated: (K, H, W) bool observations with a saturated site.
        mask: (H, W) bool object mask.
        lights: (K, H, W, 3) unit directions surface → light, camera frame.
        irradiance: (K, H, W) irradiance E ≥ 0 at normal incidence (relative units).
            Under directional lights both are the same at every pixel, and preprocessing returns
            them as zero-stride views (``expand`` of (K, 1, 1, 3) and (K, 1, 1)): they index,
            slice and broadcast like full tensors but take no memory; read-only (``.clone()``
            before writing into them).
        view: (H, W, 3) unit directions surface → camera.
        noise_std: estimated σ of s0 from quantisation and read noise, fraction of full scale.
        has_polarisation: False when the linear Stokes components hold no signal above the noise
            (no polariser, or an unpolarised scene: intensity only).
        offset: (row, column) of this grid's pixel (0, 0) in the full super-pixel grid (crops).
        noise: σ of an observed s0 as a function of the signal, measured from the capture's four-site
            redundancy (:func:`polarshape.recover.noise.estimate_noise`); None when not estimated.
        colour: a colour capture's per-channel observations (``stokes`` is then their channel
            mean); None for a mono capture. :func:`crop_inputs` crops it; :func:`downsample_inputs`
            and light subsets leave it out (None).
        albedo_edges: (H, W) bool blocks on an albedo step (texture), their observations left out of
            ``valid`` (:mod:`polarshape.recover.edges`); None when not looked for. Cropped like
            ``mask``; :func:`downsample_inputs` leaves it out.
    """

    stokes: Tensor
    valid: Tensor
    saturated: Tensor
    mask: Tensor
    lights: Tensor
    irradiance: Tensor
    view: Tensor
    noise_std: float
    has_polarisation: bool
    offset: tuple[int, int] = (0, 0)
    noise: NoiseModel | None = None
    colour: ColourInputs | None = None
    albedo_edges: Tensor | None = None

    @property
    def num_lights(self) -> int:
        return int(self.stokes.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.stokes.shape[-2]), int(self.stokes.shape[-1])


@dataclass(frozen=True)
class Observations:
    """Flattened observations of P pixels under K lights (camera frame).

    Attributes:
        stokes: (P, K, 3) observed Stokes, fraction of full scale, pixel frames.
        weight: (P, K) ≥ 0 observation weights (0 = unusable: dark, saturated, masked).
        lights: (P, K, 3) unit directions surface → light.
        irradiance: (P, K) relative irradiance E.
        view: (P, 3) unit directions surface → camera.
    """

    stokes: Tensor
    weight: Tensor
    lights: Tensor
    irradiance: Tensor
    view: Tensor

    @property
    def num_pixels(self) -> int:
        return int(self.stokes.shape[0])

    def select(self, index: Tensor) -> Observations:
        """The observations of the pixels ``index`` (1-D long or bool over P)."""
        return Observations(self.stokes[index], self.weight[index], self.lights[index], self.irradiance[index],
                            self.view[index])


def flatten_observations(inputs: RecoveryInputs, pixels: Tensor) -> Observations:
    """Observations of the pixels where ``pixels`` (H, W) is True, row-major."""
    stokes = inputs.stokes.permute(2, 3, 0, 1)[pixels]  # (P, K, 3)
    weight = inputs.valid.permute(1, 2, 0)[pixels].to(stokes.dtype)  # (P, K)
    lights = inputs.lights.permute(1, 2, 0, 3)[pixels]  # (P, K, 3)
    irradiance = inputs.irradiance.permute(1, 2, 0)[pixels]  # (P, K)
    return Observations(stokes, weight, lights, irradiance, inputs.view[pixels])


def _pool(x: Tensor, h2: int, w2: int) -> Tensor:
    """2×2 means of (C, H, W) over the even part of the grid: (C, h2, w2)."""
    return F.avg_pool2d(x[:, : 2 * h2, : 2 * w2].unsqueeze(0), 2)[0]


def _same_at_every_pixel(x: Tensor, *dims: int) -> bool:
    """Whether ``x`` is a zero-stride view along ``dims`` (``expand``): one value for every pixel."""
    return all(x.stride(d) == 0 or x.shape[d] == 1 for d in dims)


def downsample_inputs(inputs: RecoveryInputs) -> RecoveryInputs:
    """Half resolution: 2×2 means of Stokes; a pixel is in the mask when all four are; an observation
    is valid when all four are; directions are averaged and renormalised (zero-stride lights and
    irradiance, the same at every pixel, stay zero-stride views)."""
    h, w = inputs.shape
    h2, w2 = h // 2, w // 2
    k = inputs.num_lights
    dt = inputs.stokes.dtype
    valid = _pool(inputs.valid.to(dt), h2, w2) > 0.999  # (K, h2, w2)
    mask = _pool(inputs.mask.to(dt)[None], h2, w2)[0] > 0.999
    stokes = F.avg_pool2d(inputs.stokes[..., : 2 * h2, : 2 * w2], 2)
    sat = F.max_pool2d(inputs.saturated[:, : 2 * h2, : 2 * w2].to(dt).unsqueeze(1), 2).squeeze(1) > 0
    view = _pool(inputs.view.permute(2, 0, 1), h2, w2).permute(1, 2, 0)
    view = view / view.norm(dim=-1, keepdim=True)
    if _same_at_every_pixel(inputs.lights, 1, 2):  # directional lights: their mean is themselves
        lights = inputs.lights[:, :h2, :w2]
    else:
        lights = _pool(inputs.lights.permute(0, 3, 1, 2).reshape(k * 3, h, w), h2, w2).reshape(k, 3, h2, w2)
        lights = lights.permute(0, 2, 3, 1)
        lights = lights / lights.norm(dim=-1, keepdim=True)
    if _same_at_every_pixel(inputs.irradiance, 1, 2):
        irradiance = inputs.irradiance[:, :h2, :w2]
    else:
        irradiance = _pool(inputs.irradiance, h2, w2)
    # 2×2 means: ¼ of the variance (exact for independent pixels; neighbours of a bilinear demosaic
    # are correlated, so an underestimate there, as with noise_std / 2)
    noise = None if inputs.noise is None else inputs.noise.scaled(0.25)
    return RecoveryInputs(stokes, valid & mask, sat, mask, lights, irradiance, view, inputs.noise_std / 2,
                          inputs.has_polarisation, inputs.offset, noise)


def crop_inputs(inputs: RecoveryInputs, margin: int = 0) -> RecoveryInputs:
    """Crop every per-pixel tensor to the bounding box of the mask (plus ``margin`` pixels).

    Returns the inputs unchanged when the mask is empty.
    """
    rows = torch.nonzero(inputs.mask.any(1)).flatten()
    cols = torch.nonzero(inputs.mask.any(0)).flatten()
    if rows.numel() == 0:
        return inputs
    h, w = inputs.shape
    r0, r1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, h)
    c0, c1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, w)
    return replace(
        inputs,
        stokes=inputs.stokes[..., r0:r1, c0:c1],
        valid=inputs.valid[:, r0:r1, c0:c1],
        saturated=inputs.saturated[:, r0:r1, c0:c1],
        mask=inputs.mask[r0:r1, c0:c1],
        lights=inputs.lights[:, r0:r1, c0:c1],
        irradiance=inputs.irradiance[:, r0:r1, c0:c1],
        view=inputs.view[r0:r1, c0:c1],
        offset=(inputs.offset[0] + r0, inputs.offset[1] + c0),
        colour=None if inputs.colour is None else inputs.colour.crop(slice(r0, r1), slice(c0, c1)),
        albedo_edges=None if inputs.albedo_edges is None else inputs.albedo_edges[r0:r1, c0:c1],
    )


def paste_crop(part: Tensor, crop: RecoveryInputs, full: RecoveryInputs, fill: float | bool = math.nan,
               *, channels_last: bool = False) -> Tensor:
    """Put a result on ``crop``'s grid back into ``full``'s grid (:func:`crop_inputs`).

    Args:
        part: (..., h, w) on the crop's grid, or (h, w, C) with ``channels_last`` (normals).
        crop, full: the cropped inputs and the inputs they were cropped from.
        fill: the value outside the crop (NaN for normals and albedo, 0 / False for the rest).

    Returns:
        (..., H, W) or (H, W, C) in ``full.stokes``'s dtype (bool stays bool).
    """
    h, w = full.shape
    ch, cw = crop.shape
    r0, c0 = crop.offset[0] - full.offset[0], crop.offset[1] - full.offset[1]
    dtype = part.dtype if part.dtype == torch.bool else full.stokes.dtype
    if channels_last:
        out = torch.full((h, w, part.shape[-1]), fill, dtype=dtype, device=part.device)
        out[r0:r0 + ch, c0:c0 + cw] = part.to(dtype)
    else:
        out = torch.full((*part.shape[:-2], h, w), fill, dtype=dtype, device=part.device)
        out[..., r0:r0 + ch, c0:c0 + cw] = part.to(dtype)
    return out
