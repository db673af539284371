"""Import sub-commands of the ``polarshape`` command line: data users already have → captures.

* ``import diligent SRC --out CAPTURE [--overwrite] [--light-frame diligent|opencv] [--rgb-weights R G B]``
  — a DiLiGenT-style folder → a capture folder (:func:`polarshape.io.importers.import_diligent`);
* ``import lights FILE --frame opencv|diligent --capture CAPTURE`` — a light file (``x y z`` per
  line, or RTI ``.lp``) → the light directions of an existing capture's ``capture.yaml``
  (:func:`polarshape.io.importers.set_capture_light_directions`);
* ``import stack SRC --out CAPTURE --lights FILE --light-frame opencv|diligent [--angles ...]
  [--bit-depth N] [--intensities FILE] [--overwrite]`` — demosaiced polariser images (0/45/90/135
  per light) → a capture folder (:func:`polarshape.io.importers.import_stack`);
* ``import arena FRAMES... --out CAPTURE --lights FILE --light-frame opencv|diligent
  [--pixel-format F] [--width W --height H] [--black-level N] [--overwrite]`` — frames saved by
  Lucid's Arena SDK / ArenaView (``.raw``, 16-bit TIFF/PNG) → a capture folder
  (:func:`polarshape.io.importers.import_arena`).

Exit status as every command (:mod:`polarshape.cli.errors`): 0 success, 1 refused (``--out``
exists, or is the source), 2 invalid input (a malformed file, a count mismatch).
"""

from __future__ import annotations

import argparse
from typing import Any

from polarshape.cli.errors import reports_errors

_FRAMES = ("opencv", "diligent")
_FRAME_HELP = ("opencv: x right, y down, z into the scene (polarshape's); diligent: x right, y up, z toward the "
               "viewer (DiLiGenT, most photometric-stereo code). Never guessed")


@reports_errors()
def _cmd_import_diligent(args: argparse.Namespace) -> int:
    from polarshape.io.importers import DEFAULT_RGB_WEIGHTS, import_diligent

    weights = DEFAULT_RGB_WEIGHTS if args.rgb_weights is None else tuple(args.rgb_weights)
    capture = import_diligent(args.src, args.out, light_frame=args.light_frame, rgb_weights=weights,
                              overwrite=args.overwrite)
    k, h, w = capture.frames.shape
    extras = [name for name, there in (("mask", capture.mask is not None),
                                       ("ground-truth normals", "normals" in capture.ground_truth)) if there]
    print(f"wrote {args.out} ({k} frames, {w // 2}x{h // 2} pixels, plain intensity, no polarisation"
          f"{', ' + ' and '.join(extras) if extras else ''}); run it with preprocess.demosaic: superpixel")
    return 0


@reports_errors()
def _cmd_import_lights(args: argparse.Namespace) -> int:
    from polarshape.io.importers import read_light_file, set_capture_light_directions

    lights = read_light_file(args.file, frame=args.frame, format=args.format)
    path = set_capture_light_directions(args.capture, lights)
    print(f"wrote {len(lights)} light directions from {args.file} ({args.frame} frame) into {path}")
    return 0


@reports_errors()
def _cmd_import_stack(args: argparse.Namespace) -> int:
    from polarshape.io.importers import import_stack

    capture = import_stack(args.src, args.out, lights=args.lights, light_frame=args.light_frame,
                           light_format=args.light_format, intensities=args.intensities, angles=args.angles,
                           bit_depth=args.bit_depth, overwrite=args.overwrite)
    k, h, w = capture.frames.shape
    print(f"wrote {args.out} ({k} lights, {w // 2}x{h // 2} pixels, {capture.bit_depth}-bit, labels {args.angles}"
          f"{', mask' if capture.mask is not None else ''}); run it with preprocess.demosaic: superpixel")
    return 0


@reports_errors()
def _cmd_import_arena(args: argparse.Namespace) -> int:
    from polarshape.io.importers import import_arena

    frames = args.frames[0] if len(args.frames) == 1 else args.frames
    capture = import_arena(frames, args.out, lights=args.lights, light_frame=args.light_frame,
                           light_format=args.light_format, intensities=args.intensities,
                           pixel_format=args.pixel_format, width=args.width, height=args.height,
                           black_level=args.black_level,
                           intrinsics=None if args.intrinsics is None else tuple(args.intrinsics),
                           overwrite=args.overwrite)
    for note in capture.ground_truth["source"]["notes"]:
        print(f"note: {note}")
    k, h, w = capture.frames.shape
    print(f"wrote {args.out} ({k} frames, {w}x{h} raw pixels, {capture.bit_depth}-bit, "
          f"{capture.spec.camera.projection})")
    return 0


def _add_light_options(parser: argparse.ArgumentParser, *, order: str, named: str) -> None:
    """--lights, --light-frame, --light-format, --intensities of an importer that reads images and a light file."""
    parser.add_argument("--lights", required=True, metavar="FILE",
                        help=f"light file: one 'x y z' per line in {order}, or RTI .lp naming each {named}")
    parser.add_argument("--light-frame", choices=_FRAMES, required=True,
                        help=f"frame of the light file. {_FRAME_HELP}")
    parser.add_argument("--light-format", choices=("auto", "xyz", "lp"), default="auto",
                        help="light file format (default auto: .lp -> lp, else xyz)")
    parser.add_argument("--intensities", metavar="FILE", default=None,
                        help="light intensities, one value (or 'r g b') per line in the light file's order "
                        "(default: all 1)")


def add_parsers(sub: Any) -> None:
    """Register ``import`` (``diligent``, ``lights``, ``stack``, ``arena``) on the top-level sub-parsers."""
    imp = sub.add_parser(
        "import",
        help="convert data you already have (DiLiGenT folders, light files, polariser stacks, Arena saves) into a capture",
        description="Convert photometric-stereo data into polarshape's capture format. Nothing is written over "
        "the source; a capture folder is written atomically and never replaces an existing one without --overwrite.",
    )
    kinds = imp.add_subparsers(dest="kind", required=True, metavar="KIND")

    dil = kinds.add_parser(
        "diligent",
        help="a DiLiGenT-style folder (NNN.png, light_directions.txt, ...) -> a capture folder",
        description="Read SRC (images, filenames.txt, light_directions.txt, light_intensities.txt, mask.png, "
        "Normal_gt.mat/.npy) and write a capture folder: lights and normals converted to the camera frame, RGB "
        "made mono (Rec. 709 weights unless --rgb-weights), each pixel stored as a 2x2 super-pixel of four equal "
        "sites (plain intensity, DoLP 0). Run the capture with preprocess.demosaic: superpixel.",
    )
    dil.add_argument("src", help="the DiLiGenT-style folder (read only)")
    dil.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to create")
    dil.add_argument("--overwrite", action="store_true", help="replace an existing --out folder (never the source)")
    dil.add_argument("--light-frame", choices=_FRAMES, default="diligent",
                     help=f"frame of light_directions.txt and the normals (default diligent). {_FRAME_HELP}")
    dil.add_argument("--rgb-weights", type=float, nargs=3, metavar=("R", "G", "B"), default=None,
                     help="weights of R, G, B for the mono images and light intensities (default Rec. 709 "
                     "luminance 0.2126 0.7152 0.0722)")
    dil.set_defaults(handler=_cmd_import_diligent)

    lig = kinds.add_parser(
        "lights",
        help="a light file (x y z per line, or RTI .lp) -> the light directions of a capture",
        description="Read FILE (one 'x y z' per line: DiLiGenT light_directions.txt, RobustPhotometricStereo "
        "lights.txt; or an RTI .lp file: N, then 'filename x y z' per line) in the frame given, and write the "
        "directions into CAPTURE's capture.yaml (atomically; intensities kept). One light per frame, in frame "
        "order (an .lp file naming every frame goes by name); a count mismatch is refused.",
    )
    lig.add_argument("file", help="the light file (.txt: x y z lines; .lp: RTI)")
    lig.add_argument("--frame", "--light-frame", dest="frame", choices=_FRAMES, required=True,
                     help=f"the frame the file is written in. {_FRAME_HELP}")
    lig.add_argument("--capture", required=True, help="existing capture folder (or its capture.yaml) to update")
    lig.add_argument("--format", choices=("auto", "xyz", "lp"), default="auto",
                     help="file format (default auto: .lp -> lp, else xyz)")
    lig.set_defaults(handler=_cmd_import_lights)

    stk = kinds.add_parser(
        "stack",
        help="demosaiced polariser images (0/45/90/135 per light) + a light file -> a capture folder",
        description="Read SRC, per light either four single-channel images <light>_0.png <light>_45.png "
        "<light>_90.png <light>_135.png (.tif/.tiff too; angle may be zero-padded, separator _ or -) or one "
        "<light>.npy ((4, H, W) or (H, W, 4), angles 0, 45, 90, 135) or 4-page <light>.tif; optional mask.png. "
        "Lights in natural order of <light>. Each pixel becomes one 2x2 super-pixel of the default mosaic "
        "(IMX250MZR layout), so preprocess.demosaic: superpixel gives back the four values exactly.",
    )
    stk.add_argument("src", help="the folder of polariser images (read only)")
    stk.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to create")
    _add_light_options(stk, order="light order", named="<light>")
    stk.add_argument("--angles", choices=("counterclockwise_on_screen", "clockwise_on_screen", "polanalyser"),
                     default="counterclockwise_on_screen",
                     help="convention of the labels 0/45/90/135: counterclockwise_on_screen (default; the sensor "
                     "maker's, camera SDKs'), polanalyser (polanalyser's demosaicing outputs: the maker's "
                     "direction), clockwise_on_screen (polarshape's: from image x toward image y, down)")
    stk.add_argument("--bit-depth", type=int, default=None, metavar="N",
                     help="significant bits of the counts (default 8 or 16 by the files' type; required for "
                     "float .npy in [0, 1])")
    stk.add_argument("--overwrite", action="store_true", help="replace an existing --out folder (never the source)")
    stk.set_defaults(handler=_cmd_import_stack)

    arn = kinds.add_parser(
        "arena",
        help="frames saved by Lucid's Arena SDK / ArenaView (.raw, 16-bit TIFF/PNG) + a light file -> a capture",
        description="Read FRAMES (one folder, its .raw/.tif/.tiff/.png files sorted by name with numbers in "
        "numeric order, or the frame files in light order) and write a capture folder. .raw files have no header: "
        "give --pixel-format, --width and --height (the camera's PixelFormat, Width, Height). 16-bit images whose "
        "counts are all multiples of 16 (largest above 4095) hold 12-bit counts left-shifted by 4: they are "
        "shifted back and the capture records it. BMP/JPEG and colour images (ArenaView display images) are "
        "refused, and 8-bit PNG/TIFF unless --pixel-format PolarizeMono8.",
    )
    arn.add_argument("frames", nargs="+", metavar="FRAMES", help="a folder of Arena saves, or the frame files")
    arn.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to create")
    _add_light_options(arn, order="frame order", named="frame")
    arn.add_argument("--pixel-format", default=None,
                     choices=("PolarizeMono8", "PolarizeMono12", "PolarizeMono12p", "PolarizeMono12Packed",
                              "PolarizeMono16", "BayerRG8", "BayerRG12", "BayerRG12p", "BayerRG12Packed", "BayerRG16"),
                     help="the camera's PixelFormat: required for .raw; for images, PolarizeMono8 accepts an 8-bit "
                     "save and PolarizeMono12 says 16-bit values are 12-bit counts; BayerRG* (a colour TRI050S-QC) "
                     "records camera.mosaic.bayer RGGB")
    arn.add_argument("--width", type=int, default=None, metavar="W", help="frame width in pixels (.raw)")
    arn.add_argument("--height", type=int, default=None, metavar="H", help="frame height in pixels (.raw)")
    arn.add_argument("--black-level", type=float, default=0.0, metavar="N",
                     help="dark counts, in counts of the imported bit depth (after any shift; default 0)")
    arn.add_argument("--intrinsics", type=float, nargs=4, default=None, metavar=("FX", "FY", "CX", "CY"),
                     help="pinhole intrinsics in raw-mosaic pixels (perspective camera; default orthographic)")
    arn.add_argument("--overwrite", action="store_true", help="replace an existing --out folder (never a source)")
    arn.set_defaults(handler=_cmd_import_arena)
