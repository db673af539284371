"""Tests of polarshape.recover.preprocess: Capture → super-pixel Stokes, validity, lights, views."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarshape.imaging.mosaic import mosaic_from_stokes
from polarshape.imaging.pixels import float_to_counts
from polarshape.io.capture import Capture, parse_capture_spec
from polarshape.recover.observations import crop_inputs
from polarshape.recover.preprocess import capture_camera, preprocess_capture


def _capture(stokes: torch.Tensor, *, projection: str = "orthographic", mask: np.ndarray | None = None,
             lights: list[dict] | None = None) -> Capture:
    """A 12-bit capture whose frames are the mosaics of ``stokes`` (K, 3, H, W) (fraction of full scale)."""
    k = stokes.shape[0]
    camera: dict = {"projection": projection, "bit_depth": 12}
    if projection == "perspective":
        h, w = stokes.shape[-2:]
        camera["intrinsics"] = {"fx": 50.0, "fy": 50.0, "cx": w - 0.5, "cy": h - 0.5}
    if lights is None:
        lights = [{"direction": [math.sin(0.5) * math.cos(a), math.sin(0.5) * math.sin(a), -math.cos(0.5)]}
                  for a in np.linspace(0, 2 * math.pi, k, endpoint=False)]
    for i, light in enumerate(lights):
        light["frame"] = f"frames/{i:03d}.png"
    spec = parse_capture_spec({"format": "polarshape-capture/1", "camera": camera, "lights": lights})
    layout = spec.camera.mosaic.to_layout()
    frames = np.stack([float_to_counts(mosaic_from_stokes(stokes[i].double(), layout), 12) for i in range(k)])
    return Capture(spec=spec, frames=frames, mask=mask)


def _stokes(k: int = 4, h: int = 6, w: int = 8) -> torch.Tensor:
    # s0 changes with the light (a real capture's does; frames that do not are refused)
    s0 = 0.4 + 0.02 * torch.arange(k, dtype=torch.float64)[:, None, None].expand(k, h, w)
    s1 = torch.full((k, h, w), 0.1, dtype=torch.float64)
    s2 = torch.full((k, h, w), -0.05, dtype=torch.float64)
    return torch.stack([s0, s1, s2], 1)


def test_orthographic_stokes_round_trip_and_shapes() -> None:
    stokes = _stokes()
    inp = preprocess_capture(_capture(stokes))
    assert inp.stokes.shape == (4, 3, 6, 8)
    assert inp.stokes.dtype == torch.float32
    torch.testing.assert_close(inp.stokes.double(), stokes, atol=2e-3, rtol=0)
    assert inp.valid.all() and inp.mask.all()
    assert inp.has_polarisation
    assert inp.lights.shape == (4, 6, 8, 3) and inp.irradiance.shape == (4, 6, 8)  # per pixel, every light type
    torch.testing.assert_close(inp.lights.norm(dim=-1), torch.ones(4, 6, 8))
    torch.testing.assert_close(inp.view, torch.tensor([0.0, 0.0, -1.0]).expand(6, 8, 3))


@pytest.mark.parametrize("demosaic", ["superpixel", "bilinear"])
def test_dark_and_saturated_observations_are_invalid(demosaic: str) -> None:
    stokes = _stokes()
    stokes[1, 0, 2, 3] = 0.001  # dark
    stokes[1, 1:, 2, 3] = 0.0
    stokes[2, 0, 4, 5] = 2.2  # I_θ = ½(s0 ± ...) > 1 at every site: clipped
    inp = preprocess_capture(_capture(stokes), demosaic=demosaic)
    assert not inp.valid[1, 2, 3] and not inp.valid[2, 4, 5]
    assert inp.saturated[2, 4, 5] and not inp.saturated[1, 2, 3]
    if demosaic == "superpixel":
        assert int((~inp.valid).sum()) == 2
    else:  # bilinear interpolation carries the clipped sites into the 8 neighbouring blocks
        assert bool(inp.saturated[2, 3:6, 4:7].all()) and int(inp.saturated.sum()) == 9
        assert int((~inp.valid).sum()) == 10


def test_bilinear_samples_one_point_per_block() -> None:
    """A horizontal ramp of s0: the super-pixel estimate mixes sites half a pixel apart and invents
    s1 ≠ 0; the bilinear estimate at the block centre (or at one site) does not."""
    from polarshape.recover.preprocess import superpixel_stokes

    k, h, w = 1, 6, 12
    x = torch.arange(2 * w, dtype=torch.float64)
    layout = _capture(_stokes(1, h, w)).layout
    mosaic = (0.2 + 0.02 * x).expand(2 * h, 2 * w).unsqueeze(0)  # unpolarised ramp: I_θ = ½ s0 = ramp
    plain = superpixel_stokes(mosaic, layout, demosaic="superpixel")
    centre = superpixel_stokes(mosaic, layout, demosaic="bilinear")
    corner = superpixel_stokes(mosaic, layout, demosaic="bilinear", sample_at="top_left")
    inner = (..., slice(1, -1), slice(1, -1))
    assert float(plain[:, 1:][inner].abs().max()) > 0.005  # spurious polarisation from the gradient
    torch.testing.assert_close(centre[:, 1:][inner], torch.zeros_like(centre[:, 1:][inner]), atol=1e-9, rtol=0)
    torch.testing.assert_close(corner[:, 1:][inner], torch.zeros_like(corner[:, 1:][inner]), atol=1e-9, rtol=0)
    # s0 at the centre of block j is the ramp at x = 2j + 0.5; at its top-left site, at x = 2j
    j = torch.arange(w, dtype=torch.float64)
    torch.testing.assert_close(centre[0, 0][inner], (2 * (0.2 + 0.02 * (2 * j + 0.5))).expand(h, w)[1:-1, 1:-1])
    torch.testing.assert_close(corner[0, 0][inner], (2 * (0.2 + 0.02 * (2 * j))).expand(h, w)[1:-1, 1:-1])
    with pytest.raises(ValueError, match="sample_at 'top_left' needs demosaic 'bilinear'"):
        superpixel_stokes(mosaic, layout, demosaic="superpixel", sample_at="top_left")
    with pytest.raises(ValueError, match="demosaic must be one of"):
        superpixel_stokes(mosaic, layout, demosaic="nearest")


def test_mask_restricts_validity_and_crop() -> None:
    mask = np.zeros((6, 8), dtype=bool)
    mask[1:4, 2:7] = True
    inp = preprocess_capture(_capture(_stokes(), mask=mask))
    assert int(inp.valid.sum()) == 4 * int(mask.sum())
    crop = crop_inputs(inp)
    assert crop.shape == (3, 5) and crop.offset == (1, 2) and bool(crop.mask.all())


def test_no_polariser_detected() -> None:
    stokes = _stokes()
    stokes[:, 1:] = 0.0
    assert not preprocess_capture(_capture(stokes)).has_polarisation


def test_perspective_views_and_stokes_back_in_pixel_frames() -> None:
    from polarshape.brdf.geometry import sensor_plane_stokes

    stokes = _stokes(h=8, w=8)
    probe = _capture(stokes, projection="perspective")
    view = capture_camera(probe).pixel_view_directions()
    # the sensor reports sensor-plane angles: build the capture from those, expect per-pixel back
    sensor = sensor_plane_stokes(stokes, view)
    assert float((sensor - stokes).abs().max()) > 1e-3  # off-axis pixels differ
    inp = preprocess_capture(_capture(sensor, projection="perspective"))
    torch.testing.assert_close(inp.stokes.double(), stokes, atol=3e-3, rtol=0)
    assert bool((inp.view[..., 2] < 0).all())
    torch.testing.assert_close(inp.view.norm(dim=-1), torch.ones(8, 8))


def test_perspective_views_follow_the_sample_site_and_the_distortion() -> None:
    import dataclasses

    probe = _capture(_stokes(h=8, w=8), projection="perspective")  # fx = fy = 50, (cx, cy) = (7.5, 7.5)
    k = probe.spec.camera.intrinsics
    centre = capture_camera(probe).pixel_view_directions()
    corner = capture_camera(probe, "top_left").pixel_view_directions()
    # pinhole: V ∝ −((u − cx)/fx, (v − cy)/fy, 1) at u = 2x + 0.5 (centre) or 2x (top-left site)
    expect = torch.tensor([-(2 * 3 + 0.5 - k.cx) / k.fx, -(2 * 5 + 0.5 - k.cy) / k.fy, -1.0], dtype=torch.float64)
    torch.testing.assert_close(centre[5, 3], expect / expect.norm())
    expect = torch.tensor([-(2 * 3 - k.cx) / k.fx, -(2 * 5 - k.cy) / k.fy, -1.0], dtype=torch.float64)
    torch.testing.assert_close(corner[5, 3], expect / expect.norm())
    # barrel distortion (k1 < 0) pulls image points inwards: the undistorted ray lies further out
    camera = probe.spec.camera.model_copy(update={"distortion": (-0.2, 0.0, 0.0, 0.0, 0.0)})
    distorted = dataclasses.replace(probe, spec=probe.spec.model_copy(update={"camera": camera}))
    view = capture_camera(distorted).pixel_view_directions()
    off_axis = lambda d: torch.atan2(d[..., :2].norm(dim=-1), -d[..., 2])  # noqa: E731
    assert bool((off_axis(view[0, 0]) > off_axis(centre[0, 0]) + 1e-3))
    torch.testing.assert_close(view.norm(dim=-1), torch.ones(8, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="sample_at must be one of"):
        capture_camera(probe, "middle").pixel_view_directions()


def test_point_lights_need_points() -> None:
    lights = [{"position": [0.1 * i, 0.0, -0.5]} for i in range(3)]
    cap = _capture(_stokes(k=3), lights=lights)
    with pytest.raises(ValueError, match="points"):
        preprocess_capture(cap)
    pts = np.zeros((6, 8, 3))
    pts[..., 2] = 0.5
    inp = preprocess_capture(cap, points=pts)
    assert inp.lights.shape == (3, 6, 8, 3) and inp.irradiance.shape == (3, 6, 8)
    # light 0 at distance 1 m from every point on the plane x = y = 0, z = 0.5 ... (0,0,-0.5) → 1 m
    torch.testing.assert_close(inp.irradiance[0], torch.ones(6, 8), atol=1e-5, rtol=0)


def test_bad_dark_threshold() -> None:
    with pytest.raises(ValueError, match="dark_threshold"):
        preprocess_capture(_capture(_stokes()), dark_threshold=1.5)


def test_16_bit_frames_of_a_12_bit_adc_saturate_at_65520() -> None:
    """PolarizeMono16 carries 12-bit counts × 16: its top is 4095 · 16 = 65520, not 65535."""
    import dataclasses

    cap = _capture(_stokes())
    spec = cap.spec.model_copy(update={"camera": cap.spec.camera.model_copy(update={"bit_depth": 16})})
    frames = (cap.frames.astype(np.int64) * 16).astype(np.uint16)
    frames[1, 4, 6] = 65520  # one site of super-pixel (2, 3) under light 1 at the 12-bit top
    inp = preprocess_capture(dataclasses.replace(cap, spec=spec, frames=frames), demosaic="superpixel")
    assert bool(inp.saturated[1, 2, 3]) and not bool(inp.valid[1, 2, 3])
    assert int(inp.saturated.sum()) == 1


def test_polarisation_signal_tells_noise_from_polarisation() -> None:
    """Noise alone (a camera without polariser) leaves |s1, s2| far above the quantisation; the
    coherence test still calls it unpolarised, and a weakly polarised (DoLP 2 %) smooth field
    polarised (measured ratios 0.014 and 1.04; threshold 0.25)."""
    from polarshape.recover.preprocess import POLARISATION_SIGNAL_MIN, polarisation_signal

    gen = torch.Generator().manual_seed(0)
    k, h, w = 4, 40, 40
    y, x = torch.meshgrid(torch.linspace(-1, 1, h, dtype=torch.float64), torch.linspace(-1, 1, w, dtype=torch.float64),
                          indexing="ij")
    s0 = 0.4 + 0.2 * x  # smooth shading
    valid = torch.ones(k, h, w, dtype=torch.bool)
    sigma = 0.004  # per-site noise, fraction of full scale (≈ 16 counts at 12 bits)
    for dolp, expect in ((0.0, False), (0.02, True)):
        phi = torch.atan2(y, x)  # smooth angle of polarisation
        s1, s2 = dolp * s0 * torch.cos(2 * phi), dolp * s0 * torch.sin(2 * phi)
        angles = torch.tensor([0.0, 45.0, 90.0, 135.0], dtype=torch.float64).deg2rad()
        sites = 0.5 * (s0 + s1 * torch.cos(2 * angles)[:, None, None] + s2 * torch.sin(2 * angles)[:, None, None])
        sites = sites.expand(k, 4, h, w) + sigma * torch.randn(k, 4, h, w, generator=gen, dtype=torch.float64)
        linear = torch.stack([sites[:, 0] - sites[:, 2], sites[:, 1] - sites[:, 3]], 1)  # super-pixel estimate
        assert float(linear.abs().max()) > 4 / 4095  # the old "s1 = s2 = 0" test would call both polarised
        ratio = polarisation_signal(linear, sites, valid)
        assert (ratio >= POLARISATION_SIGNAL_MIN) == expect, (dolp, ratio)
    assert polarisation_signal(torch.zeros(1, 2, 8, 8), torch.zeros(1, 4, 8, 8), torch.zeros(1, 8, 8, dtype=torch.bool)) == 0.0


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_preprocessing_streams_the_lights_and_keeps_directional_lights_as_views(projection: str) -> None:
    """One frame at a time: no copy of all K frames as int64 / float64 (numpy allocations are traced;
    one was 8 bytes per raw pixel per light, 64 here); directional L and E are zero-stride views. The
    Stokes images are those of the whole stack, demosaiced at once."""
    import tracemalloc

    from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
    from polarshape.imaging.pixels import counts_to_float
    from polarshape.recover.preprocess import superpixel_stokes

    k, h, w = 8, 32, 40
    stokes = _stokes(k, h, w)
    stokes[:, 0] += 0.1 * torch.rand(k, h, w, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    capture = _capture(stokes, projection=projection)
    tracemalloc.start()
    try:
        inp = preprocess_capture(capture)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 32 * (2 * h) * (2 * w)  # bytes: a few float64 / int64 frames, not K of them
    assert inp.lights.shape == (k, h, w, 3) and inp.lights.stride()[1:3] == (0, 0)
    assert inp.irradiance.shape == (k, h, w) and inp.irradiance.stride()[1:] == (0, 0)
    whole = superpixel_stokes(counts_to_float(capture.frames, 12, dtype=torch.float64), capture.layout)  # (K, 3, H, W)
    if projection == "perspective":
        whole = sensor_plane_stokes(whole, basis=torch.linalg.inv(sensor_plane_basis(inp.view.double())))
    torch.testing.assert_close(inp.stokes, whole.float(), rtol=0, atol=1e-6)


@pytest.mark.parametrize("black", [0.0, 64.0, 64.3])
@pytest.mark.parametrize("demosaic", ["superpixel", "bilinear"])
def test_block_resolution_counts_path_equals_the_float64_mosaic(demosaic: str, black: float) -> None:
    """A mono capture without calibration is computed at block resolution in counts (float32 when the
    black level is a multiple of 1/256 count, else float64): its Stokes vectors are the float64
    estimate of the converted mosaic rounded once to float32 (|Δ| ≤ 2⁻²⁴ |s|), and the validity,
    saturation, mask and polarisation verdict are those of the float64 run."""
    from polarshape.imaging.pixels import counts_to_float
    from polarshape.recover.preprocess import superpixel_stokes

    k, h, w = 6, 24, 30
    gen = torch.Generator().manual_seed(3)
    stokes = _stokes(k, h, w)
    stokes[:, 0] += 0.3 * torch.rand(k, h, w, generator=gen, dtype=torch.float64)
    stokes[2, 0, 5:8, 5:9] = 2.5  # clipped sites
    stokes[3, 0, 10:12, 3:6] = 0.002  # dark
    stokes[3, 1:, 10:12, 3:6] = 0.0
    capture = _capture(stokes)
    capture.spec = capture.spec.model_copy(update={"camera": capture.spec.camera.model_copy(update={"black_level": black})})
    inp32 = preprocess_capture(capture, demosaic=demosaic)
    inp64 = preprocess_capture(capture, demosaic=demosaic, dtype=torch.float64)
    reference = superpixel_stokes(counts_to_float(capture.frames, 12, black, dtype=torch.float64), capture.layout,
                                  demosaic=demosaic)  # (K, 3, H, W)
    assert inp32.stokes.dtype == torch.float32 and inp64.stokes.dtype == torch.float64
    assert float(((inp32.stokes.double() - reference).abs() - 2.0**-24 * reference.abs()).max()) <= 1e-15
    torch.testing.assert_close(inp64.stokes, reference, rtol=0, atol=1e-15)
    for name in ("valid", "saturated", "mask"):
        assert torch.equal(getattr(inp32, name), getattr(inp64, name)), name
    assert bool(inp32.saturated[2, 5:8, 5:9].all()) and not bool(inp32.valid[3, 10:12, 3:6].any())
    assert inp32.has_polarisation == inp64.has_polarisation
    assert inp32.noise.read_var == pytest.approx(inp64.noise.read_var, rel=1e-3)
    assert inp32.noise.shot_gain == pytest.approx(inp64.noise.shot_gain, rel=1e-3, abs=1e-12)


def test_counts_above_the_bit_depth_are_refused_on_the_block_path() -> None:
    capture = _capture(_stokes())
    capture.frames[1, 3, 4] = 4096  # 12 bits hold 0 … 4095
    with pytest.raises(ValueError, match="raw counts span"):
        preprocess_capture(capture)
