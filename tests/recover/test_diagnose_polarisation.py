"""polarshape.recover.diagnose.check_polarisation_signal: a single demosaiced (or plain) image saved
as a frame is refused, naming the measured DoLP and the fix; raw mosaics of polarising objects and
plain captures of four equal sites pass; ``preprocess.polarisation_check: false`` lets it through."""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from polarshape.config import PreprocessConfig, load_run_config
from polarshape.errors import CaptureError
from polarshape.imaging.demosaic import stokes_from_mosaic
from polarshape.imaging.mosaic import split_mosaic
from polarshape.io.capture import Capture, load_capture, write_capture
from polarshape.pipeline import run_pipeline
from polarshape.recover.diagnose import POLARISATION_DOLP_MIN, check_polarisation_signal, polarisation_dolp
from polarshape.recover.preprocess import preprocess_capture

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Capture:
    """The shipped polarising sphere, 64×64 raw pixels, 8 lights, 12-bit with noise."""
    return load_capture(render_sphere(tmp_path_factory.mktemp("sphere"), width=64, pixel_size_m=4.4e-4, lights=8,
                                      seed=3))


def _frames_from(capture: Capture, image_of: Callable[[torch.Tensor], np.ndarray]) -> Capture:
    """The capture with every frame replaced by ``image_of(frame (2H, 2W) float64)``, rounded to counts."""
    top = 2 ** capture.bit_depth - 1
    frames = [np.clip(np.rint(image_of(torch.from_numpy(f.astype(np.float64)))), 0, top) for f in capture.frames]
    return dataclasses.replace(capture, frames=np.stack(frames).astype(np.uint16))


def _upsampled_polariser_image(capture: Capture) -> Capture:
    """Each frame → its 0° polariser image (one site per block) upsampled ×2 by OpenCV (bilinear)."""
    return _frames_from(capture, lambda m: cv2.resize(split_mosaic(m, capture.layout)[0].numpy(), None, fx=2, fy=2,
                                                      interpolation=cv2.INTER_LINEAR))


def _plain_image(capture: Capture) -> Capture:
    """Each frame → s0 / 2 of the bilinear demosaic at full resolution: a plain intensity image."""
    return _frames_from(capture, lambda m: stokes_from_mosaic(m, capture.layout, "bilinear")[0].numpy() / 2)


def _four_equal_sites(capture: Capture) -> Capture:
    """Each block's four sites set to their mean: what ``polarshape import diligent`` stores."""
    return _frames_from(capture, lambda m: np.repeat(np.repeat(split_mosaic(m, capture.layout).mean(0).numpy(), 2, 0),
                                                     2, 1))


def _check(capture: Capture) -> float | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        inputs = preprocess_capture(capture)
    return check_polarisation_signal(capture, inputs)


def test_a_raw_mosaic_of_a_polarising_sphere_passes(sphere: Capture) -> None:
    dolp = _check(sphere)
    assert dolp is not None and dolp > 3 * POLARISATION_DOLP_MIN  # measured 0.098


@pytest.mark.parametrize("make", [_upsampled_polariser_image, _plain_image])
def test_a_demosaiced_or_plain_image_read_as_a_mosaic_is_refused(sphere: Capture, make) -> None:  # noqa: ANN001
    capture = make(sphere)
    with pytest.raises(CaptureError, match=r"no polarisation signal: the 99th percentile of the degree of linear "
                                           r"polarisation over its \d+ usable object observations is 0\.00\d\d .*"
                                           r"`polarshape import stack`.*`polarshape import diligent`.*"
                                           r"preprocess\.polarisation_check: false"):
        _check(capture)


def test_four_equal_sites_are_plain_intensity_and_pass(sphere: Capture) -> None:
    plain = _four_equal_sites(sphere)
    assert _check(plain) is None
    inputs = preprocess_capture(plain, demosaic="superpixel")
    assert not inputs.has_polarisation  # DoLP exactly 0 in the 2×2 estimate
    # one block in the mask that is not plain: judged again (the bilinear demosaic of four equal sites
    # is a staircase, whose steps it takes for polarisation: measured DoLP 0.11, so it passes)
    frames = plain.frames.copy()
    y, x = np.argwhere(plain.mask)[len(np.argwhere(plain.mask)) // 2]
    frames[:, 2 * y, 2 * x] += 1
    assert _check(dataclasses.replace(plain, frames=frames)) > POLARISATION_DOLP_MIN
    outside = plain.frames.copy()
    outside[:, 0, 0] += 1  # outside the mask: still plain where the object is
    assert _check(dataclasses.replace(plain, frames=outside)) is None


def test_the_statistic_sees_through_noise_and_needs_observations(sphere: Capture) -> None:
    inputs = preprocess_capture(sphere)
    dolp, n = polarisation_dolp(sphere, inputs.valid)
    assert n > 1000 and 0.05 < dolp < 0.5
    # preprocessing's own bilinear block-centre Stokes give the same statistic without a second demosaic
    reused, n_reused = polarisation_dolp(sphere, inputs.valid, inputs.stokes)
    assert n_reused == n and abs(reused - dolp) < 1e-4 * dolp
    assert polarisation_dolp(sphere, torch.zeros_like(inputs.valid)) == (0.0, 0)
    demosaiced = _upsampled_polariser_image(sphere)
    few = torch.zeros_like(inputs.valid)
    few[0, 10:14, 16] = True  # 4 usable observations: too few to judge, not refused
    assert check_polarisation_signal(demosaiced, dataclasses.replace(inputs, valid=few)) is None
    few[:, 8:24, 16] = True  # 128 (less the dim ones): judged
    with pytest.raises(CaptureError, match=r"over its 1[0-2]\d usable object observations"):
        check_polarisation_signal(demosaiced, dataclasses.replace(inputs, valid=few))


@pytest.mark.parametrize("name", ["official_sphere128", "mitsuba_sphere_a020"])
def test_shared_captures_pass_and_their_demosaiced_frames_do_not(name: str) -> None:
    if not (SHARED / name / "capture.yaml").is_file():
        pytest.skip(f"{SHARED / name} not present")
    capture = load_capture(SHARED / name)
    assert _check(capture) > 10 * POLARISATION_DOLP_MIN  # measured 0.144 and 0.209
    with pytest.raises(CaptureError, match="no polarisation signal"):
        _check(_upsampled_polariser_image(capture))


def test_polarisation_check_option_and_pipeline(sphere: Capture, tmp_path: Path) -> None:
    assert PreprocessConfig().polarisation_check is True and PreprocessConfig(polarisation_check=False)
    write_capture(tmp_path / "demosaiced", _upsampled_polariser_image(sphere))

    def config(**preprocess: object) -> Path:
        path = tmp_path / "run.yaml"
        path.write_text(yaml.safe_dump({
            "input": {"type": "capture", "path": str(tmp_path / "demosaiced")}, "progress": False,
            "recovery": {"model": "lambertian"}, "mesh": {"poisson": False}, "report": {"enabled": False},
            "preprocess": preprocess}))
        return path

    with pytest.raises(CaptureError, match="no polarisation signal"):
        run_pipeline(load_run_config(config()), tmp_path / "refused")
    assert not (tmp_path / "refused").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_pipeline(load_run_config(config(polarisation_check=False)), tmp_path / "result")
    assert (result.out_dir / "normals.npy").is_file()
    assert "preprocess: polarisation check off (preprocess.polarisation_check: false)" in result.params["skipped"]
