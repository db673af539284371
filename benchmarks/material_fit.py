"""Benchmark: single-image material fit time and parameter error per model (simulated sphere, 12 bits).

    .venv/bin/python benchmarks/material_fit.py [--width 128] [--models fmbrdf,baek,on_ts,l_ts]

Renders configs/scenes/sphere.yaml's FMBRDF sphere (μ 1.5, α 0.25, r_k 0.5) under its first light,
fits every model with the sphere's fitted normals (polarshape.measure) and prints, per model, the
fit time, the eq. 25 loss, the s0 relative RMSE and — for the FMBRDF — the parameter errors.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.capture import load_capture
from polarshape.measure import MIN_COS_VIEW, sphere_normals
from polarshape.recover.material_fit import FIT_MODELS, fit_model
from polarshape.recover.observations import flatten_observations
from polarshape.recover.preprocess import preprocess_capture

SCENE = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "sphere.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=128, help="raw image width in pixels")
    parser.add_argument("--models", default=",".join(FIT_MODELS))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene = yaml.safe_load(SCENE.read_text())
        scene["camera"].update(width=args.width, height=args.width, pixel_size_m=0.028 / args.width)
        scene["lights"] = scene["lights"][:1]
        (folder / "scene.yaml").write_text(yaml.safe_dump(scene))
        with SimulatedCamera(folder / "scene.yaml", seed=1) as camera:
            camera.render_capture(folder / "capture", progress=False)
        cap = load_capture(folder / "capture")
        normals = torch.as_tensor(sphere_normals(cap))
        inputs = preprocess_capture(cap, dtype=torch.float64)
        pixels = inputs.mask & torch.isfinite(normals).all(-1) & (-normals[..., 2] >= MIN_COS_VIEW)
        obs = flatten_observations(inputs, pixels)
        print(f"{int(pixels.sum())} pixels, 1 light, {args.width} px raw")
        for model in args.models.split(","):
            t0 = time.perf_counter()
            fit = fit_model(model, normals[pixels], obs)
            line = (f"{model:8s} {time.perf_counter() - t0:6.2f} s  loss {fit.loss:.3g}  "
                    f"s0 rel. RMSE {fit.relative_rmse:.4f}  DoLP rel. RMSE {fit.dolp_relative_rmse:.4f}")
            if model == "fmbrdf":
                p = fit.params
                line += (f"  |Δμ| {abs(p['ior'] - 1.5):.4f}  Δα {p['alpha'] / 0.25 - 1:+.1%}  "
                         f"Δr_k {p['k_b'] / p['k_s'] / 0.5 - 1:+.1%}")
            print(line)


if __name__ == "__main__":
    main()
