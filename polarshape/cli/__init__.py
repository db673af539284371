"""The ``polarshape`` command line.

Sub-commands (one ``_cmd_<name>(args) -> int`` each, registered in :func:`build_parser`):

* ``simulate SCENE.yaml --out CAPTURE_DIR [--overwrite]`` — render a capture folder
  (capture-format.md) with the simulated camera, ground truth included;
  ``simulate calibration SCENE.yaml --out DIR`` — that camera's bench calibration frames
  (``flat/``, ``polariser/`` with ``angles.txt``, ``dark/``, ``truth.json``, ``truth_polcal.npz``).
* ``demo --out DIR [--overwrite]`` — the forward-model demo (a sphere under one light).
* ``inspect FRAME`` — DoLP and AoLP of one raw mosaic.
* ``run``, ``capture``, ``calibrate``, ``import``, ``material``, ``batch`` — see :mod:`polarshape.cli.run`,
  :mod:`polarshape.cli.acquisition`, :mod:`polarshape.cli.importing`, :mod:`polarshape.cli.material` and
  :mod:`polarshape.cli.batch`.

Every command takes ``-v``/``--verbose`` (count: ``-vv`` is debug) and ``-q``/``--quiet`` (no
progress bars) before or after its name, and the counts add up (``polarshape -v run cfg.yaml -v``
is ``-vv``): :func:`add_output_options` puts them on every parser of the tree
(:func:`iter_commands`), and :func:`output_options` reads them back.

Handlers do not catch errors: :func:`polarshape.cli.errors.reports_errors` turns every error a user
can cause into ``error: <message>`` and the exit status (0 success, 1 refused, 2 invalid input, 3
cannot run, 130 Ctrl-C, 143 SIGTERM; the table ends every ``--help``). Ctrl-C in any command is
one line on stderr (the command's ``interrupted`` default, else :data:`INTERRUPTED_MESSAGE`).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
import textwrap
import threading
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

from polarshape import __version__
from polarshape.cli.errors import EXIT_STATUS_HELP, reports_errors
from polarshape.errors import PolarshapeWarning

__all__ = ["INTERRUPTED_MESSAGE", "add_output_options", "build_parser", "iter_commands", "main", "output_options"]

logger = logging.getLogger(__name__)

#: What Ctrl-C prints (exit status 130) unless the command sets its own ``interrupted`` default.
INTERRUPTED_MESSAGE = "error: interrupted (Ctrl-C); nothing half-written was kept"

#: Destination of the ``-v`` count given at depth ``N`` of the command tree (``polarshape`` is 0,
#: ``run`` 1, ``calibrate lights`` 2): a sub-parser parses into a namespace of its own and copies it
#: over its parent's, so one shared destination would keep only the innermost count.
_VERBOSE_DEST = "verbose_given_at_depth_{}"


@reports_errors()
def _cmd_simulate(args: argparse.Namespace) -> int:
    from polarshape.imaging.pixels import PIXEL_FORMATS
    from polarshape.acquisition.simulated import SimulatedCamera
    from polarshape.checks import resolve_device
    from polarshape.errors import CameraError, OutputExistsError
    from polarshape.scene.config import load_scene_config

    device = resolve_device(args.device, "--device")  # before anything is loaded or rendered
    out = Path(args.out)
    # Refused before the scene is even loaded, with the command-line fix in the message.
    if out.exists() and not args.overwrite:
        raise OutputExistsError(f"{out} already exists; refusing to overwrite it (pass --overwrite or another --out)")
    calibration = args.scene == "calibration" and args.calibration_scene is not None
    if args.calibration_scene is not None and not calibration:
        raise CameraError(f"unexpected argument {args.calibration_scene!r}; use `simulate SCENE` or `simulate calibration SCENE`")
    config = load_scene_config(args.calibration_scene if calibration else args.scene)
    if args.pixel_format is not None and args.pixel_format not in PIXEL_FORMATS:
        raise CameraError(f"--pixel-format {args.pixel_format!r} is not one of {sorted(PIXEL_FORMATS)}")
    with SimulatedCamera(config, device=device, seed=args.seed) as camera:
        camera.configure(exposure_us=args.exposure_us, gain_db=args.gain_db, pixel_format=args.pixel_format)
        if calibration:  # bench frames of this camera (issue 16): flat/, polariser/ (+ angles.txt), dark/
            camera.render_calibration_frames(
                out, angles_deg=args.angles if args.angles else tuple(float(a) for a in range(0, 180, 10)),
                n_flat=args.n_flat, n_dark=args.n_dark, mount_offset_deg=args.mount_offset_deg, overwrite=args.overwrite,
            )
            print(f"wrote {out} (calibration frames: flat/, polariser/, dark/)")
            return 0
        capture = camera.render_capture(out, overwrite=args.overwrite, progress=not args.quiet)
    mask = capture.mask
    logger.info(
        "wrote %s: %d frames of %dx%d, %d-bit, %d object super-pixels",
        out, capture.num_lights, capture.frames.shape[2], capture.frames.shape[1], capture.bit_depth,
        int(mask.sum()) if mask is not None else 0,
    )
    bracket = f" × {capture.spec.bracket_size} exposures" if capture.has_brackets else ""
    print(f"wrote {out} ({capture.num_lights} frames{bracket})")  # the one-line result, with -q too
    return 0


@reports_errors()
def _cmd_demo(args: argparse.Namespace) -> int:
    from polarshape.demo import run_demo

    summary = run_demo(args.out, size=args.size, overwrite=args.overwrite)
    print(
        f"wrote {summary['out']}: intensity.png, dolp.png, aolp.png, mosaic.png, stokes.npy "
        f"({summary['size']}x{summary['size']} sphere, max DoLP {summary['max_dolp']:.3f}, {summary['render_seconds']:.2f} s)"
    )
    return 0


@reports_errors()
def _cmd_inspect(args: argparse.Namespace) -> int:
    from polarshape.cli.options import layout_from_flag
    from polarshape.inspect_frame import frame_stats

    layout = layout_from_flag(args.layout, args.angles)
    st = frame_stats(args.frame, bit_depth=args.bit_depth, black_level=args.black_level, layout=layout, roi=args.roi)
    print(
        f"{args.frame}: mean s0 {st.mean_s0:.4f} of full scale, DoLP {st.mean_dolp:.4f}, AoLP {st.aolp_deg:+.2f} deg "
        f"(from image x toward y), {100 * st.saturated_fraction:.2f} % saturated, {st.n_superpixels} super-pixels"
    )
    return 0


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, except that an indented line of a description or epilog is kept as it
    is: the exit-status table keeps its rows (argparse would run them into one paragraph)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n".join(
            indent + line if line.startswith(" ") else textwrap.fill(" ".join(line.split()), width,
                                                                     initial_indent=indent, subsequent_indent=indent)
            for line in text.splitlines()
        )


def iter_commands(parser: argparse.ArgumentParser) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """Every parser of the command tree, each once, parents before children: ``((), top)``,
    ``(("run",), run)``, …, ``(("calibrate", "lights"), lights)``."""
    seen: set[int] = set()

    def walk(path: tuple[str, ...], current: argparse.ArgumentParser) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
        if id(current) in seen:  # an alias names a parser already listed
            return
        seen.add(id(current))
        yield path, current
        for action in current._actions:  # noqa: SLF001 - argparse keeps its sub-parsers there
            if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
                for name, sub in action.choices.items():
                    yield from walk((*path, name), sub)

    yield from walk((), parser)


def add_output_options(parser: argparse.ArgumentParser, depth: int) -> None:
    """Give ``parser`` (at ``depth`` in the command tree: 0 for ``polarshape`` itself) ``-v/--verbose``
    and ``-q/--quiet``. Both default to ``argparse.SUPPRESS``: given nowhere, they leave no value, so
    an inner parser never resets what an outer one set; :func:`output_options` combines them.
    A parser that has them already (a sub-command module may add them itself) is left as it is."""
    if getattr(parser, "polarshape_output_options", False):
        return
    parser.polarshape_output_options = True  # type: ignore[attr-defined]
    group = parser.add_argument_group("output")
    where = "" if depth == 0 else "; also accepted before the command"
    group.add_argument("-v", "--verbose", action="count", dest=_VERBOSE_DEST.format(depth), default=argparse.SUPPRESS,
                       help=f"more log output: -v info, -vv debug (counts add up wherever given{where})")
    group.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help=f"no progress bars; errors, warnings and the one-line result are still printed{where}")


def output_options(args: argparse.Namespace) -> tuple[int, bool]:
    """The ``-v`` count (summed over every place it was given) and whether ``-q`` was given anywhere."""
    prefix = _VERBOSE_DEST.format("")
    verbose = sum(int(value) for name, value in vars(args).items() if name.startswith(prefix))
    return verbose, bool(getattr(args, "quiet", False))


def _with_exit_status_help(parser: argparse.ArgumentParser) -> None:
    """End ``parser``'s help, and every sub-command's, with the exit-status table."""
    for _, each in iter_commands(parser):
        each.epilog = EXIT_STATUS_HELP
        each.formatter_class = _HelpFormatter


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command (each ``--help`` ends with the exit-status table)."""
    parser = argparse.ArgumentParser(
        prog="polarshape",
        description="Shape and reflectance from polarisation images. Start with: polarshape run configs/default.yaml",
    )
    parser.add_argument("--version", action="version", version=f"polarshape {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    from polarshape.cli.run import add_parsers as add_run_parsers

    add_run_parsers(sub)  # the main command first

    sim = sub.add_parser(
        "simulate",
        help="render a capture folder of a scene file with the simulated polarisation camera",
        description="Render one raw polarisation mosaic per light of SCENE (see configs/scenes/*.yaml) into a "
        "capture folder, with ground_truth/normals.npy, depth.npy and mask.png.",
    )
    sim.add_argument("scene", help="scene YAML file (or the word `calibration` followed by the scene file: bench "
                     "calibration frames flat/, polariser/ with angles.txt, dark/ of that scene's camera)")
    sim.add_argument("calibration_scene", nargs="?", default=None, metavar="CALIBRATION_SCENE", help=argparse.SUPPRESS)
    sim.add_argument("--angles", type=float, nargs="+", default=None,
                     help="calibration: polariser dial readings, degrees, maker's convention (default 0 10 ... 170)")
    sim.add_argument("--n-flat", type=int, default=16, help="calibration: number of flat frames (default 16)")
    sim.add_argument("--n-dark", type=int, default=16, help="calibration: number of dark frames (default 16)")
    sim.add_argument("--mount-offset-deg", type=float, default=3.7,
                     help="calibration: the polariser mount's unknown zero, degrees (true axis = reading + this; "
                     "recorded in truth.json; default 3.7)")
    sim.add_argument("--out", required=True, help="capture folder to create (must not exist unless --overwrite)")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    sim.add_argument("--seed", type=int, default=None, help="noise seed (default: sensor.seed of the scene)")
    sim.add_argument("--exposure-us", type=float, default=None, help="exposure time, µs (default: the scene's)")
    sim.add_argument("--gain-db", type=float, default=None, help="analogue gain, dB (default: the scene's)")
    sim.add_argument("--pixel-format", default=None, help="e.g. PolarizeMono8, PolarizeMono12, PolarizeMono16")
    sim.add_argument("--device", default="cpu", help="torch device for rendering (cpu, cuda, ...)")
    sim.set_defaults(handler=_cmd_simulate)

    demo = sub.add_parser(
        "demo",
        help="render a sphere with the FMBRDF forward model (intensity, DoLP, AoLP, raw mosaic)",
        description="Render an orthographic sphere under one light with the Fresnel Microfacet BRDF and write "
        "intensity.png, dolp.png, aolp.png, mosaic.png (raw IMX250MZR mosaic), stokes.npy and demo.json.",
    )
    demo.add_argument("--out", required=True, help="folder to create (must not exist unless --overwrite)")
    demo.add_argument("--size", type=int, default=256, help="image size in pixels (default 256)")
    demo.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    demo.set_defaults(handler=_cmd_demo)

    insp = sub.add_parser(
        "inspect",
        help="mean intensity, DoLP and AoLP of a raw mosaic (e.g. to check the polariser angle convention)",
        description="Demosaic FRAME (super-pixel) and print the DoLP and AoLP of its mean Stokes vector, in our "
        "convention (AoLP from image x toward image y, i.e. clockwise on screen).",
    )
    insp.add_argument("frame", help="raw mosaic image (PNG/TIFF, sensor counts)")
    insp.add_argument("--bit-depth", type=int, default=12, help="significant bits (8, 10, 12, 16; default 12)")
    insp.add_argument("--black-level", type=float, default=0.0, help="black level, counts")
    insp.add_argument("--roi", type=int, nargs=4, metavar=("X", "Y", "W", "H"), help="region in mosaic pixels")
    insp.add_argument("--layout", type=int, nargs=4, metavar=("TL", "TR", "BL", "BR"),
                      help="maker's polariser labels of the 2x2 block (default 90 45 135 0, the IMX250MZR)")
    # polarshape.imaging.mosaic.MAKER_ANGLES, written out so that parsing does not import torch
    insp.add_argument("--angles", default="counterclockwise_on_screen",
                      choices=["counterclockwise_on_screen", "clockwise_on_screen", "polanalyser"],
                      help="how the labels are measured: the maker's direction (default), ours (y down), or as "
                      "the polanalyser library labels them (the maker's)")
    insp.set_defaults(handler=_cmd_inspect)

    from polarshape.cli.acquisition import add_parsers as add_acquisition_parsers

    add_acquisition_parsers(sub)
    from polarshape.cli.importing import add_parsers as add_importing_parsers

    add_importing_parsers(sub)
    from polarshape.cli.material import add_parsers as add_material_parsers

    add_material_parsers(sub)
    from polarshape.cli.batch import add_parsers as add_batch_parsers

    add_batch_parsers(sub)
    for path, each in iter_commands(parser):
        add_output_options(each, len(path))
    _with_exit_status_help(parser)
    return parser


@contextlib.contextmanager
def _exit_on_sigterm() -> Iterator[None]:
    """While the command runs, SIGTERM (``kill``, ``timeout``) ends it like Ctrl-C does: through the
    ``finally`` blocks, so a half-written result folder is removed (exit status 143 = 128 + SIGTERM).
    The previous handler is restored afterwards (``main`` may be called in-process)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _terminate(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def _warnings_as_messages() -> Iterator[None]:
    """While the command runs, a :class:`~polarshape.errors.PolarshapeWarning` is printed as one line,
    ``warning: <Kind>: <message>`` on stderr (not Python's ``file:line:`` form); other warnings as usual."""
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def show(message: Warning | str, category: type[Warning], *args: object, **kwargs: object) -> None:
            if issubclass(category, PolarshapeWarning):
                print(f"warning: {category.__name__}: {message}", file=sys.stderr)
            else:
                shown(message, category, *args, **kwargs)  # type: ignore[arg-type]

        warnings.showwarning = show
        yield


@contextlib.contextmanager
def _log_level(verbose: int) -> Iterator[None]:
    """While the command runs, polarshape's loggers show warnings (default), info (``-v``) or debug
    (``-vv``); other libraries' stay at warning. The level is restored afterwards (``main`` may be
    called in-process, e.g. by the tests)."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    package = logging.getLogger("polarshape")
    previous = package.level
    package.setLevel(logging.WARNING - 10 * min(verbose, 2))
    try:
        yield
    finally:
        package.setLevel(previous)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status (0 = success, 1 = refused, 2 = invalid
    input, 3 = cannot run (a stage failed, the disk is full or not writable, no CUDA), 130 =
    interrupted by Ctrl-C, 143 = by SIGTERM; see :mod:`polarshape.cli.errors`)."""
    args: argparse.Namespace | None = None
    try:  # Ctrl-C while the parser is built (it imports the sub-command modules) is one line too
        args = build_parser().parse_args(argv)
        args.verbose, args.quiet = output_options(args)
        with _log_level(args.verbose), _exit_on_sigterm(), _warnings_as_messages():
            return int(args.handler(args))
    except KeyboardInterrupt:
        # the finally blocks have run: no half-written output is left; a message, not a traceback
        print(getattr(args, "interrupted", INTERRUPTED_MESSAGE), file=sys.stderr)
        return 130
