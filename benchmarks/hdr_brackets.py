"""Issue 16 (HDR exposure brackets): a glossy sphere whose highlight cores clip, one exposure vs three.

    python benchmarks/hdr_brackets.py                 # 80² super-pixels, 10 lights (a few minutes)
    python benchmarks/hdr_brackets.py --n 64 --lights 8
    python benchmarks/hdr_brackets.py --short         # + the shortest exposure alone (unclipped)
    python benchmarks/hdr_brackets.py --demosaic superpixel

The scene: ``configs/scenes/sphere.yaml``'s sphere (FMBRDF, μ 1.5, β 2) with α = 0.03 and a dark body
(k_b 0.18), exposed at 30 ms so that the diffuse part sits near 0.4 of full scale and the highlight
cores peak ≈ 64× full scale. Rows: the single 30 ms exposure (cores clipped), and the bracket
30 ms, 3.75 ms, 0.47 ms (×1, ×1/8, ×1/64) merged by preprocessing (``--short``: the 0.47 ms frames
alone, the unclipped reference). Each row: the recovered α, β, k_s (vs the truth; and α fitted at the
true normals, what the observations allow at this resolution), the mean normal error (degrees) over the mask pixels not in cast shadow, the named
warnings of the lobe check, and the seconds of rendering + recovery (machine named in the output).
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
import warnings
from pathlib import Path

import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from polarshape.acquisition.simulated import SimulatedCamera  # noqa: E402
from polarshape.metrics import angular_error_deg  # noqa: E402
from polarshape.normals import RecoveryOptions, recover_capture  # noqa: E402
from polarshape.recover.observations import flatten_observations  # noqa: E402
from polarshape.recover.preprocess import preprocess_capture  # noqa: E402
from polarshape.recover.reflectometry import fit_reflectance  # noqa: E402
from polarshape.recover.selfcheck import clipped_lobe  # noqa: E402
from polarshape.scene.config import parse_scene_config  # noqa: E402

ALPHA = 0.03
REFERENCE_US = 30000.0
BRACKET = (REFERENCE_US, REFERENCE_US / 8, REFERENCE_US / 64)


def scene(n: int, lights: int, exposures: tuple[float, ...] | None) -> dict:
    d = yaml.safe_load((REPO / "configs/scenes/sphere.yaml").read_text())
    raw = 2 * n
    d["camera"].update(width=raw, height=raw, pixel_size_m=1e-4 * 256 / raw, exposure_us=REFERENCE_US)
    if exposures is not None:
        d["camera"]["exposures_us"] = list(exposures)
        d["camera"]["exposure_us"] = exposures[0]
    d["objects"][0]["material"].update(alpha=ALPHA, k_b=0.18)
    d["lights"] = [{"zenith_deg": 12 + 36 * i / max(lights - 1, 1), "azimuth_deg": (137.5 * i) % 360, "intensity": 1.0}
                   for i in range(lights)]
    return d


def row(name: str, n: int, lights: int, exposures: tuple[float, ...] | None, demosaic: str = "bilinear") -> dict:
    t0 = time.perf_counter()
    capture = SimulatedCamera(parse_scene_config(scene(n, lights, exposures)), seed=0).render_capture(progress=False)
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = recover_capture(capture, RecoveryOptions(model="fmbrdf"), demosaic=demosaic)
    t_rec = time.perf_counter() - t0
    inputs = preprocess_capture(capture, demosaic=demosaic)
    gt = torch.from_numpy(capture.ground_truth["normals"]).double()
    lit = inputs.valid.sum(0) >= inputs.valid.shape[0] - 3
    m = result.mask & lit & torch.isfinite(gt).all(-1)
    err = float(angular_error_deg(result.normals.double()[m], gt[m]).mean())
    lobe = clipped_lobe(inputs, result.normals, result.params)
    pix = inputs.mask & torch.isfinite(gt).all(-1)  # the material at the true normals: what the data allow
    known = fit_reflectance(gt[pix].float(), flatten_observations(inputs, pix), fit_kappa=False, delta=0.01).params
    p = result.params
    peak = float(inputs.stokes[:, 0][inputs.valid].max())
    print(f"{name:<30} α {p['alpha']:.4f} ({100 * (p['alpha'] / ALPHA - 1):+.1f} %; at the true normals "
          f"{known.alpha:.4f}, {100 * (known.alpha / ALPHA - 1):+.1f} %)  β {p['beta']:.2f}  "
          f"k_s {p['k_s']:.3g}  normals {err:.3f}° ({int(m.sum())} px)  saturated obs "
          f"{int(inputs.saturated[:, inputs.mask].sum())}  peak s0 {peak:.1f}× FS  lobe peak clipped "
          f"under {lobe['lights_peak_clipped']} of {lobe['lights_with_core']} lights  render {t_render:.1f} s, recovery {t_rec:.1f} s")
    return {"alpha": p["alpha"], "error": err, "seconds": t_rec}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=80, help="super-pixels across")
    ap.add_argument("--lights", type=int, default=10)
    ap.add_argument("--demosaic", choices=("bilinear", "superpixel"), default="bilinear",
                    help="preprocess.demosaic (superpixel: no interpolation across the sharp lobe)")
    ap.add_argument("--short", action="store_true",
                    help="add a row: the shortest exposure alone (unclipped, the diffuse part dark)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print(f"hdr_brackets: sphere α {ALPHA}, {args.n}² super-pixels, {args.lights} lights, demosaic {args.demosaic}; "
          f"{platform.machine()}, "
          f"{torch.get_num_threads()} thread")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        single = row("single exposure (30 ms)", args.n, args.lights, None, args.demosaic)
        merged = row("bracket ×1, ×1/8, ×1/64", args.n, args.lights, BRACKET, args.demosaic)
        if args.short:
            row("single 0.47 ms (unclipped)", args.n, args.lights, BRACKET[-1:], args.demosaic)
    print(f"bracket / single recovery time: {merged['seconds'] / single['seconds']:.2f}")
    ok = abs(merged["alpha"] / ALPHA - 1) <= 0.10 and merged["error"] <= 0.5
    print(f"targets (bracket: α within ±10 %, ≤ 0.5° mean normal error): {'met' if ok else 'NOT met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
