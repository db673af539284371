"""Benchmark: the albedo-edge detector (polarshape.recover.edges) — false positives on a plain object, recall
on a textured one, and the preprocessing time.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/albedo_edges.py [--textured-sizes 128,256] [--plain CAPTURE ...]

- **textured**: ``configs/scenes/textured.yaml`` (a ×0.2 / ×1.0 checker on a glossy sphere, 4 point lights)
  rendered at each size (super-pixels across, as ``benchmarks/nearfield.py`` does). The true albedo steps come
  from the simulator's albedo map (raw pixels, the sphere only): a block is **on** a step when its own four
  sites see two albedos, **near** one when the 4 × 4 raw window the bilinear demosaic reads for it (its sites
  and one pixel around) does. Recall: the share of the near blocks (resp. on) that the detector flags
  (``adjacent`` or ``on_edge``; resp. ``on_edge``), over the blocks in the mask that ≥ 2 lights see; false: the
  flagged blocks with no step in their 3 × 3 blocks (6 × 6 raw pixels).
- **plain**: each capture given (an untextured object, e.g. ``benchmarks/scaling.py --render-only``'s sphere):
  every flagged block is a false positive.

Prints a Markdown table: blocks in the mask, flagged adjacent / on the edge, recall, false flags, the detector's
CPU seconds and the whole preprocessing's (``preprocess_capture``, the same call ``polarshape run`` makes; CPU
time of this process, one thread: steadier than the wall clock on a loaded machine). Run it with ``PYTHONPATH`` at
two checkouts to compare them (the counts are deterministic).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import polarshape.recover.preprocess as preprocess
from polarshape.acquisition.simulated import SimulatedCamera
from polarshape.io.capture import load_capture
from polarshape.scene.render import albedo_scale_map

sys.path.insert(0, str(Path(__file__).resolve().parent))
from nearfield import render  # noqa: E402 (benchmarks/ is a folder of scripts)


def _detect(capture_path: Path) -> tuple[dict, float]:
    """Preprocess the capture, keeping the detector's inputs and answer; returns them and the seconds (point
    lights: the surface points from the capture's true depth, where ``polarshape run`` would place a guess)."""
    capture = load_capture(capture_path)
    points = None
    if any(light.position is not None for light in capture.spec.lights):
        depth = np.load(capture_path / "ground_truth" / "depth.npy")  # (H, W) z, NaN off the object
        z = np.nan_to_num(depth, nan=float(np.nanmedian(depth)))
        points = np.stack([np.zeros_like(z), np.zeros_like(z), z], -1)  # the light directions do not matter here
    seen: dict = {}
    find = preprocess.find_albedo_edges

    def spy(block_s0: torch.Tensor, usable: torch.Tensor, **kwargs: object):
        t0 = time.process_time()
        edges = find(block_s0, usable, **kwargs)
        seen.update(edges=edges, usable=usable, seconds=time.process_time() - t0)
        return edges

    preprocess.find_albedo_edges = spy
    try:
        t0 = time.process_time()
        inputs = preprocess.preprocess_capture(capture, points=points, polarisation_check=False)
        seconds = time.process_time() - t0
    finally:
        preprocess.find_albedo_edges = find
    seen["mask"] = inputs.mask
    return seen, seconds


def _truth(folder: Path, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(H, W) bool blocks on, near and within a block of a true albedo step of the scene's first object (module
    docstring)."""
    with SimulatedCamera(folder / f"{name}.yaml") as cam:
        albedo = albedo_scale_map(cam.scene, cam.geometry).to(torch.float64)  # (2H, 2W)
        albedo = torch.where(cam.geometry.object_index == 0, albedo, torch.full_like(albedo, torch.nan))
    h2, w2 = albedo.shape
    hi = albedo.nan_to_num(-torch.inf)
    lo = albedo.nan_to_num(torch.inf)
    pool = torch.nn.functional.max_pool2d

    def spread(size: int, pad: int) -> torch.Tensor:
        big = pool(hi[None, None], size, stride=2, padding=pad)[0, 0]
        small = -pool(-lo[None, None], size, stride=2, padding=pad)[0, 0]
        return big > small * 1.01

    on = spread(2, 0)
    near = spread(4, 1)[: h2 // 2, : w2 // 2]
    around = spread(6, 2)
    return on, near, around


def _row(label: str, seen: dict, seconds: float, truth: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None) -> str:
    edges, mask = seen["edges"], seen["mask"]
    seen_by_two = (seen["usable"].sum(0) >= 2) & mask
    adjacent, on_edge = edges.adjacent & mask, edges.on_edge & mask
    flagged = adjacent | on_edge
    if truth is None:
        recall, false = "–", int(flagged.sum())
    else:
        on, near = (t & seen_by_two for t in truth[:2])
        found = int((flagged & near).sum())
        recall = (f"{found}/{int(near.sum())} ({100 * found / max(int(near.sum()), 1):.1f} %), "
                  f"on {int((on_edge & on).sum())}/{int(on.sum())}")
        false = int((flagged & ~truth[2]).sum())
    return (f"| {label} | {int(mask.sum())} | {int(adjacent.sum())} | {int(on_edge.sum())} | {recall} | {false} "
            f"| {seen['seconds']:.2f} | {seconds:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--textured-sizes", default="128,256", help="super-pixels across (default 128,256)")
    parser.add_argument("--plain", nargs="*", default=[], help="captures of untextured objects")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| capture | blocks in mask | adjacent | on the edge | recall near (on) | false flags | detector CPU s "
          "| preprocessing CPU s |")
    print("|---|---|---|---|---|---|---|---|")
    for path in args.plain:
        seen, seconds = _detect(Path(path))
        print(_row(f"plain {Path(path).name}", seen, seconds, None), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for size in (int(s) for s in args.textured_sizes.split(",") if s):
            folder = Path(tmp) / str(size)
            folder.mkdir()
            capture, _ = render(folder, "textured", size)
            seen, seconds = _detect(capture)
            print(_row(f"textured {size}²", seen, seconds, _truth(folder, "textured")), flush=True)


if __name__ == "__main__":
    main()
