"""Figures behind ``polarshape.recover.diagnose.POLARISATION_DOLP_MIN`` (issue 17): the statistic
:func:`~polarshape.recover.diagnose.polarisation_dolp` on raw mosaics and on the same captures with
every frame replaced by a single demosaiced or plain image.

    python benchmarks/polarisation_check.py [--width 64] [--widths 64 128]

Cases, per capture:

- ``raw`` — the mosaic as rendered (must pass);
- ``resize_I0`` — each frame replaced by its 0° polariser image (one site per block) upsampled ×2
  with OpenCV's bilinear resize: a quarter-resolution stack saved as a frame (must be refused);
- ``bilinear_I0`` — each frame replaced by the full-resolution bilinear demosaic of its 0° image
  (``polarshape.imaging.demosaic.intensities_from_mosaic``; what polanalyser's OpenCV demosaic gives);
- ``s0half`` — each frame replaced by s0 / 2 of the bilinear demosaic (a plain intensity image);
- ``equal`` — four equal sites per block (``polarshape import diligent``): DoLP 0 by design, never
  judged (``check_polarisation_signal`` returns None).

Simulated captures: configs/scenes/sphere.yaml with several materials, with and without noise;
``../shared/data`` captures when present.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.errors import CaptureError
from polarshape.imaging.demosaic import intensities_from_mosaic, stokes_from_mosaic
from polarshape.imaging.mosaic import split_mosaic
from polarshape.io.capture import Capture, load_capture
from polarshape.recover.diagnose import POLARISATION_DOLP_MIN, check_polarisation_signal, polarisation_dolp
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"

MATERIALS: dict[str, dict | None] = {
    "fmbrdf (sphere.yaml: IOR 1.5, alpha 0.25)": None,
    "fmbrdf IOR 1.5, alpha 0.8": {"model": "fmbrdf", "ior": 1.5, "k_s": 1.0, "k_b": 0.5, "alpha": 0.8, "beta": 2.0,
                                  "kappa": 0.0},
    "fmbrdf IOR 1.3, k_s 0.3, alpha 0.6": {"model": "fmbrdf", "ior": 1.3, "k_s": 0.3, "k_b": 0.8, "alpha": 0.6,
                                           "beta": 2.0, "kappa": 0.0},
    "lambertian (unpolarised)": {"model": "lambertian", "k_d": 0.7},
}


def simulate(width: int, material: dict | None, noise: bool) -> Capture:
    d = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    d["camera"]["pixel_size_m"] = d["camera"]["pixel_size_m"] * d["camera"]["width"] / width
    d["camera"]["width"] = d["camera"]["height"] = width
    if material is not None:
        d["objects"][0]["material"] = material
    if not noise:
        d["sensor"].update(shot_noise="none", read_noise_e=0.0)
    return SimulatedCamera(parse_scene_config(d), seed=0).render_capture(progress=False)


def replaced(capture: Capture, how: str) -> Capture:
    """The capture with each frame replaced (module docstring)."""
    top = 2 ** capture.bit_depth - 1
    frames = []
    for frame in capture.frames:
        m = torch.from_numpy(frame.astype(np.float64))
        if how == "bilinear_I0":
            image = intensities_from_mosaic(m, capture.layout, "bilinear")[0].numpy()
        elif how == "resize_I0":
            image = cv2.resize(split_mosaic(m, capture.layout)[0].numpy(), None, fx=2, fy=2,
                               interpolation=cv2.INTER_LINEAR)
        elif how == "s0half":
            image = stokes_from_mosaic(m, capture.layout, "bilinear")[0].numpy() / 2
        elif how == "equal":
            image = np.repeat(np.repeat(split_mosaic(m, capture.layout).mean(0).numpy(), 2, 0), 2, 1)
        else:
            raise ValueError(how)
        frames.append(np.clip(np.rint(image), 0, top).astype(np.uint16))
    return dataclasses.replace(capture, frames=np.stack(frames))


def measure(capture: Capture) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        inputs = preprocess_capture(capture, polarisation_check=False)  # measured here, not enforced
    dolp, n = polarisation_dolp(capture, inputs.valid & inputs.mask.unsqueeze(0))
    try:
        verdict = "not judged" if check_polarisation_signal(capture, inputs) is None else "pass"
    except CaptureError:
        verdict = "REFUSED"
    return f"{dolp:8.4f}  {n:7d}  {verdict}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--widths", type=int, nargs="+", default=[64, 128], help="raw mosaic widths (pixels)")
    args = parser.parse_args(argv)
    cases = ("raw", "resize_I0", "bilinear_I0", "s0half", "equal")
    print(f"threshold POLARISATION_DOLP_MIN = {POLARISATION_DOLP_MIN}")
    print(f"{'capture':58s} {'case':12s} {'DoLP p99':>8s}  {'obs':>7s}  verdict")
    captures: list[tuple[str, Capture]] = []
    for width in args.widths:
        for name, material in MATERIALS.items():
            for noise in (True, False):
                captures.append((f"sphere {width}px {name}{'' if noise else ', no noise'}",
                                 simulate(width, material, noise)))
    for name in ("mitsuba_sphere_a020", "official_sphere128"):
        if (SHARED / name).is_dir():
            captures.append((name, load_capture(SHARED / name)))
    for label, capture in captures:
        for case in cases:
            cap = capture if case == "raw" else replaced(capture, case)
            print(f"{label:58s} {case:12s} {measure(cap)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
