"""Tests of polarshape.recover.diagnose: captures recovery cannot use are refused (naming the cause,
decided from the counts), suspicious ones warned about, real ones pass untouched — all through
preprocess_capture, which runs the checks once."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.errors import CaptureError, SuspiciousInputWarning
from polarshape.io.capture import Capture, parse_capture_spec
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sphere() -> Capture:
    """configs/scenes/sphere.yaml at 16 × 16 super-pixels (9 distant lights, 12-bit, noise)."""
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    d["camera"]["width"] = d["camera"]["height"] = 32
    d["camera"]["pixel_size_m"] = 1e-4 * 256 / 32
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def _with(capture: Capture, frames: np.ndarray | None = None, **camera: object) -> Capture:
    data = capture.spec.model_dump(mode="json")
    data["camera"].update(camera)
    return dataclasses.replace(capture, spec=parse_capture_spec(data),
                               frames=capture.frames.copy() if frames is None else frames.astype(np.uint16))


def _quiet(capture: Capture, **kwargs: object) -> None:
    """preprocess_capture without any SuspiciousInputWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", SuspiciousInputWarning)
        preprocess_capture(capture, **kwargs)


def test_real_captures_pass(sphere: Capture) -> None:
    _quiet(sphere)
    half = sphere.frames.copy()
    half[::2] //= 64  # five of nine lights nearly off: four lit views still reach most pixels
    _quiet(_with(sphere, half))
    _quiet(sphere, demosaic="superpixel")


def test_all_dark_frames_are_refused(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match=r"no usable observations .*all frames are dark: the brightest count is 0 of "
                                           r"full scale 4095 .*lights off, lens cap, exposure too short\?"):
        preprocess_capture(_with(sphere, np.zeros_like(sphere.frames)))
    dim = np.minimum(sphere.frames, 9)  # below dark_threshold 0.005 of full scale (20 counts)
    with pytest.raises(CaptureError, match=r"all frames are dark: the brightest count is 9 of full scale 4095"):
        preprocess_capture(_with(sphere, dim))


def test_black_level_above_the_signal_is_named(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match=r"every count is at or below camera\.black_level 3500 .*black_level is in "
                                           r"counts of the declared bit_depth 12"):
        preprocess_capture(_with(sphere, black_level=3500))
    # just above the brightest counts: within the dark threshold of it
    hi = int(sphere.frames.max())
    with pytest.raises(CaptureError, match=rf"camera\.black_level {hi - 5} leaves the brightest count {hi} below "
                                           r"preprocess\.dark_threshold"):
        preprocess_capture(_with(sphere, black_level=hi - 5))


def test_all_saturated_frames_are_refused(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match=r"every observation is saturated \(a site at the top count 4095\): shorten "
                                           r"the exposure"):
        preprocess_capture(_with(sphere, np.full_like(sphere.frames, 4095)))


def test_an_oversized_saturation_margin_is_named(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match=r"saturation_margin_counts 4095 leaves no count below the saturation level "
                                           r"0 \(top count 4095\): lower it"):
        preprocess_capture(sphere, saturation_margin=4095)


def test_dark_and_saturated_mix_and_too_few_lit_views(sphere: Capture) -> None:
    mix = np.zeros_like(sphere.frames)
    mix[::2] = 4095
    with pytest.raises(CaptureError, match=r"every observation is dark \(\d+ of \d+; wholly dark: lights 1, 3, 5, 7\) or "
                                           r"saturated \(\d+ of \d+; wholly saturated: lights 0, 2, 4, 6, 8\)"):
        preprocess_capture(_with(sphere, mix))
    two = sphere.frames.copy()
    two[2:] = 0  # two lit views per pixel at most
    with pytest.raises(CaptureError, match=r"no mask pixel has 3 .*every pixel needs 3 lights"):
        preprocess_capture(_with(sphere, two))


def test_frames_that_do_not_change_with_the_light_are_refused(sphere: Capture) -> None:
    with pytest.raises(CaptureError, match=r"the frames do not change with the light: .*at most 0\.0 quantisation "
                                           r"steps .*same frame written 9 times\? light rig not switching\?"):
        preprocess_capture(_with(sphere, np.full_like(sphere.frames, 2000)))
    same = np.repeat(sphere.frames[4:5], 9, axis=0)  # one real frame saved under every light
    with pytest.raises(CaptureError, match=r"do not change with the light"):
        preprocess_capture(_with(sphere, same))


def test_duplicate_lights_and_identical_frames_are_warned(sphere: Capture) -> None:
    data = sphere.spec.model_dump(mode="json")
    data["lights"][5]["direction"] = data["lights"][3]["direction"]
    frames = sphere.frames.copy()
    frames[5] = frames[3]
    frames[6:8] = 0  # two lights that did not fire
    copied = dataclasses.replace(sphere, spec=parse_capture_spec(data), frames=frames)
    with pytest.warns(SuspiciousInputWarning) as record:
        preprocess_capture(copied)
    text = [str(w.message) for w in record]
    assert any("lights 3 and 5 (frames/003.png, frames/005.png) have the same direction (0.00° apart)" in t
               and "the second adds no shape information — a copied entry?" in t for t in text), text
    assert any("lights[3].frame frames/003.png, lights[5].frame frames/005.png: 2 frames are bit-identical" in t
               for t in text), text
    assert any("lights[6].frame frames/006.png, lights[7].frame frames/007.png: 2 frames are bit-identical — every "
               "count is 0: lights that did not fire, a lens cap?" in t for t in text), text


def test_point_lights_at_one_position_are_warned(sphere: Capture) -> None:
    data = sphere.spec.model_dump(mode="json")
    for k, light in enumerate(data["lights"]):
        del light["direction"]
        light["position"] = [0.05 * np.cos(k), 0.05 * np.sin(k), 0.1]
    data["lights"][7]["position"] = [data["lights"][2]["position"][0] + 2e-4, *data["lights"][2]["position"][1:]]
    points = np.zeros((16, 16, 3))
    points[..., 2] = 0.5
    with pytest.warns(SuspiciousInputWarning, match=r"lights 2 and 7 .*the same position \(0\.20 mm apart\)"):
        preprocess_capture(dataclasses.replace(sphere, spec=parse_capture_spec(data)), points=points)


def test_a_point_light_behind_the_surface_is_refused(sphere: Capture) -> None:
    data = sphere.spec.model_dump(mode="json")
    for k, light in enumerate(data["lights"]):
        del light["direction"]
        light["position"] = [0.05 * np.cos(k), 0.05 * np.sin(k), 0.1]
    data["lights"][4]["position"][2] = 0.6  # further from the camera than the surface at 0.5 m
    points = np.zeros((16, 16, 3))
    points[..., 2] = 0.5
    with pytest.raises(CaptureError, match=r"lights\[4\]\.position z = 0\.6 m is at or beyond the surface's median "
                                           r"depth 0\.5 m: behind the object seen from the camera: z is forward, away "
                                           r"from the camera"):
        preprocess_capture(dataclasses.replace(sphere, spec=parse_capture_spec(data)), points=points)
    data["lights"][4]["position"][2] = 0.45  # in front: accepted
    preprocess_capture(dataclasses.replace(sphere, spec=parse_capture_spec(data)), points=points)


def test_low_bit_data_declared_16_bit_is_warned(sphere: Capture) -> None:
    hi = int(sphere.frames.max())
    with pytest.warns(SuspiciousInputWarning, match=rf"camera\.bit_depth: the brightest count {hi} is below 1/16 of "
                                                    r"full scale 65535: 12-bit data declared bit_depth 16\?"):
        preprocess_capture(_with(sphere, bit_depth=16))
    _quiet(_with(sphere, sphere.frames * 16, bit_depth=16))  # 12-bit counts high-bit aligned: fine
