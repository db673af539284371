"""Import sub-commands of the ``polarshape`` command line: data users already have → captures.

* ``import diligent SRC --out CAPTURE [--overwrite] [--light-frame diligent|opencv] [--rgb-weights R G B]``
  — a DiLiGenT-style folder → a capture folder (:func:`polarshape.io.importers.import_diligent`);
* ``import lights FILE --frame opencv|diligent --capture CAPTURE`` — a light file (``x y z`` per
  line, or RTI ``.lp``) → the light directions of an existing capture's ``capture.yaml``
  (:func:`polarshape.io.importers.set_capture_light_directions`).

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


def add_parsers(sub: Any) -> None:
    """Register ``import`` (``diligent``, ``lights``) on the top-level sub-parsers."""
    imp = sub.add_parser(
        "import",
        help="convert data you already have (DiLiGenT-style folders, light files) into a capture",
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
