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

    cal = sub.add_parser("calibrate", help="calibrate light directions (mirror sphere) or camera intrinsics (ChArUco)")
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
