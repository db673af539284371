"""Time of preprocessing and of the initial normals (robust Lambertian PS) on a large capture (issue 13).

    python benchmarks/preprocess.py CAPTURE_DIR [--repeat 2] [--threads 1]
    python benchmarks/preprocess.py --size 1024 --keep /tmp/cap1024   # render configs/scenes/sphere.yaml at 1024²

Prints the seconds of reading and decoding the capture (:func:`polarshape.io.capture.load_capture`, not
part of "preprocess"), then one row per repeat: seconds of
:func:`polarshape.recover.preprocess.preprocess_capture` (default settings: bilinear at the block centres;
it includes the count conversion, Stokes, dark / saturated / mixed observations, mask, noise model,
polarisation-signal verdict and the capture checks, the polarisation check among them) and of
:func:`polarshape.normals.initial_normals` (robust PS), each as wall clock and as this process's CPU time
(``time.process_time``: the steadier figure on a shared box), the number of valid PS normals and a
checksum of the normals (to compare two versions of the code on the same capture: run it with
``PYTHONPATH`` pointing at each checkout, alternately).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch
import yaml

from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.capture import load_capture
from polarshape.normals import initial_normals
from polarshape.recover.preprocess import preprocess_capture
from polarshape.scene.config import parse_scene_config

REPO = Path(__file__).resolve().parents[1]


def render(size: int, out: Path) -> Path:
    """configs/scenes/sphere.yaml at ``size``² super-pixels (the sphere as large in the frame), into ``out``."""
    scene = yaml.safe_load((REPO / "configs" / "scenes" / "sphere.yaml").read_text())
    camera = scene["camera"]
    camera["pixel_size_m"] *= camera["width"] / (2 * size)
    camera["width"] = camera["height"] = 2 * size
    with SimulatedCamera(parse_scene_config(scene)) as cam:
        cam.render_capture(out, overwrite=True, progress=False)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", nargs="?", type=Path, help="a capture folder (default: render one with --size)")
    ap.add_argument("--size", type=int, default=1024, help="super-pixels across of the rendered sphere")
    ap.add_argument("--keep", type=Path, default=None, help="where to render it (kept for later runs)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    folder = args.capture or render(args.size, args.keep or Path(f"/tmp/polarshape_bench_sphere_{args.size}"))
    t0, c0 = time.perf_counter(), time.process_time()
    capture = load_capture(folder)
    print(f"{folder}: {capture.frames.shape[0]} frames of {capture.frames.shape[2]}×{capture.frames.shape[1]} raw; "
          f"{platform.machine()}, {args.threads} thread(s); read and decoded in {time.perf_counter() - t0:.2f} s "
          f"(CPU {time.process_time() - c0:.2f} s)")
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        inputs = preprocess_capture(capture)
        t1, c1 = time.perf_counter(), time.process_time()
        ps = initial_normals(inputs)
        t2, c2 = time.perf_counter(), time.process_time()
        checksum = float(ps.normals[inputs.mask].double().sum())
        print(f"preprocess {t1 - t0:.2f} s (CPU {c1 - c0:.2f} s)   robust PS {t2 - t1:.2f} s (CPU {c2 - c1:.2f} s)   "
              f"valid {int(ps.valid.sum())}   normals checksum {checksum:.4f}")


if __name__ == "__main__":
    main()
