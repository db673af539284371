"""Acquisition sub-commands of the ``polarshape`` command line: ``capture`` and ``calibrate``."""

from __future__ import annotations

import argparse

from polarshape.cli.errors import reports_errors


@reports_errors()
def _cmd_capture(args: argparse.Namespace) -> int:
    from polarshape.acquisition.session import capture_session

    from pathlib import Path

    complete = (Path(args.out) / "capture.yaml").exists()
    path = capture_session(args.session, args.out, resume=not args.no_resume)
    print(f"{path} was already complete; nothing captured" if complete else f"wrote {path}")
    return 0


def _intrinsics(args: argparse.Namespace):  # noqa: ANN202
    from polarshape.acquisition.calibrate import Intrinsics

    vals = (args.fx, args.fy, args.cx, args.cy)
    if all(v is None for v in vals):
        return None
    if any(v is None for v in vals):
        raise ValueError("give all of --fx --fy --cx --cy (perspective camera, raw-mosaic pixels) or none (orthographic)")
    return Intrinsics(fx=args.fx, fy=args.fy, cx=args.cx, cy=args.cy)


@reports_errors()
def _cmd_calibrate_lights(args: argparse.Namespace) -> int:
    import numpy as np

    from polarshape.acquisition.calibrate import calibrate_lights_from_files

    if (args.mask is None) == (args.circle is None):
        raise ValueError("give exactly one of --mask MASK.png or --circle CU CV RADIUS (the mirror sphere)")
    dirs = calibrate_lights_from_files(
        args.images, mask_path=args.mask, circle=tuple(args.circle) if args.circle else None,
        intrinsics=_intrinsics(args), mosaic=not args.no_mosaic, capture_yaml=args.capture,
    )
    for i, d in enumerate(np.asarray(dirs)):
        print(f"light {i}: direction [{d[0]: .5f}, {d[1]: .5f}, {d[2]: .5f}]")
    if args.capture:
        print(f"updated {args.capture}")
    return 0


@reports_errors()
def _cmd_calibrate_intrinsics(args: argparse.Namespace) -> int:
    from polarshape.acquisition.calibrate import CharucoBoardSpec, calibrate_intrinsics_from_files

    board = CharucoBoardSpec(
        squares=tuple(args.squares), square_length_m=args.square_length, marker_length_m=args.marker_length, dictionary=args.dictionary
    )
    k = calibrate_intrinsics_from_files(args.images, board, mosaic=not args.no_mosaic, capture_yaml=args.capture)
    print(f"intrinsics (raw-mosaic pixels): fx={k.fx:.3f} fy={k.fy:.3f} cx={k.cx:.3f} cy={k.cy:.3f}")
    if args.capture:
        print(f"updated {args.capture}")
    return 0


def _read_angles_file(path: str) -> list[float]:
    """Numbers (degrees) of an angles file: whitespace- or comma-separated, ``#`` starts a comment."""
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"--angles-file {path}: file not found")
    values: list[float] = []
    for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
        for token in line.split("#", 1)[0].replace(",", " ").split():
            try:
                values.append(float(token))
            except ValueError:
                raise ValueError(f"--angles-file {path}, line {n}: {token!r} is not a number (one angle in degrees "
                                 "per polariser frame, whitespace- or comma-separated)") from None
    return values


@reports_errors()
def _cmd_calibrate_polarisation(args: argparse.Namespace) -> int:
    import logging

    from polarshape.acquisition.polarimetric import (
        estimate_polarimetric_calibration_from_files, summarise_polarimetric_calibration,
    )
    from polarshape.errors import OutputExistsError
    from polarshape.cli.options import layout_from_flag
    from polarshape.io.polarimetric import write_polarimetric_calibration

    from pathlib import Path

    if (args.angles is None) == (args.angles_file is None):
        raise ValueError("give the polariser angles with exactly one of --angles A… or --angles-file FILE (degrees, "
                         "one per --polariser frame, in order)")
    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ValueError(f"--out {out}: a polarimetric calibration is a .npz file; name it e.g. polcal.npz")
    if out.exists() and not args.overwrite:  # refused before the frames are read
        raise OutputExistsError(f"{out} already exists; refusing to overwrite it (pass --overwrite or another --out)")
    angles = args.angles if args.angles is not None else _read_angles_file(args.angles_file)
    layout = layout_from_flag(args.layout, args.layout_angles)
    calibration = estimate_polarimetric_calibration_from_files(
        polariser=args.polariser, angles_deg=angles, angle_convention=args.angle_convention, layout=layout,
        bit_depth=args.bit_depth, flat=args.flat or (), dark=args.dark or (), black_level=args.black_level,
        absolute_angles=args.absolute_angles,
    )
    path = write_polarimetric_calibration(out, calibration, overwrite=args.overwrite)
    logging.getLogger(__name__).info("wrote %s", path)
    print(summarise_polarimetric_calibration(calibration))
    print(f"wrote {path}; reference it from capture.yaml as camera.polarimetric_calibration: {path.name} "
          "(relative to the capture folder, or an absolute path)")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``capture`` and ``calibrate`` on the top-level sub-parser."""
    cap = sub.add_parser(
        "capture",
        help="capture one raw mosaic per light (camera + light rig) into a capture folder",
        description="Run the capture session SESSION.yaml (camera backend aravis|simulated|fake_gige, light rig "
        "simulated|manual|serial, lights): for each light switch it on, capture (optionally averaging frames and "
        "bracketing exposure), and save each frame as soon as it is captured; finally write capture.yaml. An "
        "interrupted session resumes where it stopped.",
    )
    cap.add_argument("session", help="session YAML file (see configs/sessions/)")
    cap.add_argument("--out", required=True, help="capture folder to write")
    cap.add_argument("--no-resume", action="store_true", help="do not reuse frames already in --out")
    # Ctrl-C keeps the frames saved so far, on purpose: the same command resumes
    cap.set_defaults(handler=_cmd_capture, interrupted="error: interrupted (Ctrl-C); the frames captured so far are "
                     "kept: run the same command again to capture the rest")

    cal = sub.add_parser("calibrate", help="calibrate light directions (mirror sphere), camera intrinsics (ChArUco) "
                         "or the sensor's analysers (polariser series)")
    cal_sub = cal.add_subparsers(dest="what", required=True, metavar="WHAT")
    lights = cal_sub.add_parser(
        "lights",
        help="light directions from images of a mirror sphere, one image per light",
        description="Find the mirror sphere and its highlight in each image and reflect the view ray about the "
        "sphere normal there: the light direction (camera frame).",
    )
    lights.add_argument("images", nargs="+", help="one image per light, in light order")
    lights.add_argument("--mask", help="sphere mask image (non-zero = sphere)")
    lights.add_argument("--circle", type=float, nargs=3, metavar=("CU", "CV", "RADIUS"), help="sphere outline in pixels")
    for name in ("fx", "fy", "cx", "cy"):
        lights.add_argument(f"--{name}", type=float, help="perspective intrinsics (raw-mosaic pixels)")
    lights.add_argument("--no-mosaic", action="store_true", help="images are plain intensity, not raw polarisation mosaics")
    lights.add_argument("--capture", help="write the directions into this capture folder / capture.yaml")
    lights.set_defaults(handler=_cmd_calibrate_lights)

    intr = cal_sub.add_parser(
        "intrinsics",
        help="camera intrinsics from ChArUco board images",
        description="Detect the ChArUco board (OpenCV contrib aruco) in each image and calibrate the pinhole camera.",
    )
    intr.add_argument("images", nargs="+", help="board images from several viewpoints")
    intr.add_argument("--squares", type=int, nargs=2, default=(7, 5), metavar=("COLS", "ROWS"))
    intr.add_argument("--square-length", type=float, default=0.04, help="square side, metres")
    intr.add_argument("--marker-length", type=float, default=0.03, help="marker side, metres")
    intr.add_argument("--dictionary", default="DICT_5X5_100", help="OpenCV ArUco dictionary name")
    intr.add_argument("--no-mosaic", action="store_true", help="images are plain intensity, not raw polarisation mosaics")
    intr.add_argument("--capture", help="write the intrinsics into this capture folder / capture.yaml")
    intr.set_defaults(handler=_cmd_calibrate_intrinsics)

    pol = cal_sub.add_parser(
        "polarisation",
        help="per-pixel analyser angle, extinction ratio, gain, black level and defects from bench frames",
        description="From frames of a linear polariser in front of a uniform source at several known angles "
        "(--polariser, --angles), optionally of the uniform source without polariser (--flat) and with the lens "
        "capped (--dark), estimate every pixel's analyser angle, diattenuation (extinction ratio), gain, black "
        "level and the hot/dead pixels; write a calibration file that capture.yaml references as "
        "camera.polarimetric_calibration.",
    )
    pol.add_argument("--polariser", nargs="+", required=True, metavar="FRAME",
                     help="raw mosaics (PNG/TIFF) of the polariser in front of the uniform source, one per angle (≥ 3)")
    pol.add_argument("--angles", type=float, nargs="+", metavar="A", help="the polariser angle of each --polariser "
                     "frame, degrees, in order (its mount's scale: the zero may be anywhere)")
    pol.add_argument("--angles-file", metavar="F", help="file of the angles instead of --angles (one per line or "
                     "whitespace/comma separated; e.g. polariser/angles.txt of `polarshape simulate calibration`)")
    # polarshape.imaging.mosaic.MAKER_ANGLES, written out so that parsing does not import torch
    conventions = ["counterclockwise_on_screen", "clockwise_on_screen", "polanalyser"]
    pol.add_argument("--angle-convention", default="counterclockwise_on_screen", choices=conventions,
                     help="the direction in which the polariser angles increase: counter-clockwise as seen on screen "
                     "(the makers', default), clockwise on screen (ours, image y down), or polanalyser's (the makers')")
    pol.add_argument("--absolute-angles", action="store_true", help="the angles are measured from the sensor's x axis: "
                     "keep the global offset instead of removing the mount's zero")
    pol.add_argument("--flat", nargs="+", metavar="FRAME", help="raw mosaics of the uniform unpolarised source (no "
                     "polariser): per-pixel gain and dead pixels")
    pol.add_argument("--dark", nargs="+", metavar="FRAME", help="raw mosaics with the lens capped: per-pixel black "
                     "level and hot pixels")
    pol.add_argument("--bit-depth", type=int, required=True, help="significant bits of the counts (8, 10, 12, 16)")
    pol.add_argument("--black-level", type=float, default=0.0, help="black level, counts, when there are no --dark "
                     "frames (default 0)")
    pol.add_argument("--layout", type=int, nargs=4, metavar=("TL", "TR", "BL", "BR"),
                     help="maker's polariser labels of the 2x2 block (default 90 45 135 0, the IMX250MZR)")
    pol.add_argument("--layout-angles", default="counterclockwise_on_screen", choices=conventions,
                     help="how the --layout labels are measured (camera.mosaic.angles; default the makers')")
    pol.add_argument("--out", required=True, help="calibration file to write (.npz, e.g. polcal.npz)")
    pol.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    pol.set_defaults(handler=_cmd_calibrate_polarisation)
