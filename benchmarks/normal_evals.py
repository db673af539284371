"""Where ``polarshape run`` spends its model evaluations: pixel evaluations per level and call site (issue 13).

Counts every call of :func:`polarshape.recover.reflectometry.render_parts` (the forward model behind
``NormalProblem.residual``, the material fits, the outputs' renders) during ``polarshape run`` on one capture,
with the pixels it rendered and its seconds, grouped by pyramid level (the ``level`` of the enclosing
``fit_level``; ``-`` outside one) and call site (the innermost solver function above it: ``jacobian`` =
the forward-difference columns of :func:`normal_jacobian`, ``lm_trial`` = Levenberg–Marquardt's trial and
start, ``neighbour_try`` / ``polish`` = :func:`propagate_normals`, …). "evals / px" is pixel evaluations over
the level's pixels.

Usage (a capture of ``benchmarks/scaling.py``, rendered with ``--render-only``)::

    OMP_NUM_THREADS=1 python benchmarks/normal_evals.py /tmp/scaling/capture_256x256@12 [--out DIR]

The run is scaling.py's configuration (float32, no held-out validation, no report).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import polarshape.recover.reflectometry as reflectometry  # noqa: E402

#: call sites, innermost first: the first of these names on the stack above render_parts names the call
SITES = (
    ("normal_jacobian", "jacobian"), ("_jacobian_and_albedo", "jacobian"), ("_try_neighbour", "neighbour_try"), ("propagate_normals", "polish"),
    ("normal_information", "information"), ("_refine_chunk", "lm_trial"), ("profile_alpha", "profile_alpha"),
    ("joint_solve", "joint"), ("nested_kappa", "joint"), ("fit_reflectance", "material_fit"),
    ("objective", "material_fit"), ("fit_albedo_scale", "albedo_scale"), ("fit_level", "level_other"),
    ("solve_materials", "materials"), ("_render_fmbrdf", "output_render"), ("smooth_normals", "smoothing"),
    ("colour_albedo", "colour"), ("validate_holdout", "validation"), ("run_checks", "checks"),
)


def _site() -> tuple[str, str]:
    frame = sys._getframe(2)
    names, level = [], "-"
    while frame is not None:
        names.append(frame.f_code.co_name)
        if frame.f_code.co_name == "fit_level" and level == "-":
            level = str(frame.f_locals.get("level", "-"))
        frame = frame.f_back
    for name, site in SITES:
        if name in names:
            return level, site
    return level, "other:" + "<".join(names[:3])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="result folder (default: a temporary one)")
    args = parser.parse_args(argv)

    import torch

    from scaling import run_case

    stats: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0, 0, 0.0])
    level_px: dict[str, int] = {}
    original = reflectometry.render_parts

    def counted(tables, normals, obs, *a, **k):
        t0 = time.process_time()
        out = original(tables, normals, obs, *a, **k)
        key = _site()
        s = stats[key]
        s[0] += 1
        s[1] += int(normals.shape[0])
        s[2] += time.process_time() - t0
        return out

    import polarshape.recover.coarse_to_fine as c2f
    import polarshape.pipeline  # noqa: F401  (every module that imports render_parts)
    modules = [m for name, m in list(sys.modules.items()) if name.startswith("polarshape")]
    for m in modules:
        if getattr(m, "render_parts", None) is original:
            m.render_parts = counted
    fit_level = c2f.fit_level

    def fit_level_counted(inputs, *a, **k):
        level_px[str(k["level"])] = int(inputs.mask.sum())
        return fit_level(inputs, *a, **k)

    c2f.fit_level = fit_level_counted
    with tempfile.TemporaryDirectory() as tmp:
        case = run_case(args.capture, args.out or Path(tmp) / "result", "cpu", None, None)
    k = case["lights"]
    print(f"{args.capture.name}: {case['mask_px']:,} object px, {k} lights, recovery {case['stages']['recovery']:.1f} s, "
          f"mean error {case['mean_err_deg']:.3f}°, torch {torch.__version__}, {torch.get_num_threads()} thread(s)")
    print("| level | level px | call site | calls | pixel evals | evals / px | render CPU s |")
    print("|---|---:|---|---:|---:|---:|---:|")
    total = [0, 0.0]
    for (level, site), (calls, px, sec) in sorted(stats.items(), key=lambda kv: (kv[0][0], -kv[1][1])):
        lp = level_px.get(level)
        per = f"{px / lp:.1f}" if lp else ""
        print(f"| {level} | {lp or ''} | {site} | {calls} | {px:,} | {per} | {sec:.2f} |")
        total[0] += px
        total[1] += sec
    print(f"| all | | | | {total[0]:,} | {total[0] / case['mask_px']:.1f} per object px | {total[1]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
