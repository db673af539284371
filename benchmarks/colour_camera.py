"""The colour polarisation camera (TRI050S-QC, IMX250MYR) on GigE Vision: decode cost and delivered frame rate.

Three measurements at the full 2448×2048 sensor, each against the mono TRI050S-PC in the same run:

1. decoding one raw frame (:func:`polarshape.imaging.pixel_formats.unpack_mosaic`) for every raw
   format: ``BayerRG*`` against the ``PolarizeMono*`` format of the same byte layout (median of
   ``--repeats`` runs), and that every frame round-trips bit-exactly;
2. demosaicing one full 12-bit colour frame to per-colour Stokes
   (:func:`polarshape.imaging.colour.colour_stokes_from_mosaic`) against the mono super-pixel
   Stokes estimate (:func:`polarshape.imaging.stokes_from_mosaic`);
3. with Aravis installed: frames delivered by the fake GigE Vision camera over loopback
   (:class:`~polarshape.acquisition.fake_gige.FakeGigECamera` → :class:`~polarshape.acquisition.aravis.AravisCamera`),
   free-running at ``--fps`` for ``--seconds``, colour (TRI050S-QC, BayerRG12p) against mono
   (TRI050S-PC, PolarizeMono12p); every complete frame is checked bit-exact.

Usage:
    python benchmarks/colour_camera.py [--repeats 5 --fps 24 --seconds 3 --roi 2448 2048 --no-camera]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from polarshape.imaging import MosaicLayout, stokes_from_mosaic
from polarshape.imaging.colour import colour_stokes_from_mosaic
from polarshape.imaging.pixel_formats import pack_mosaic, unpack_mosaic
from polarshape.imaging.pixels import COLOUR_PIXEL_FORMATS, MONO_PIXEL_FORMATS, bit_depth_of, counts_to_float

WIDTH, HEIGHT = 2448, 2048


def _median_s(fn, repeats: int) -> float:
    fn()  # warm-up: first-touch page faults and caches are not the format's cost
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def decode(repeats: int) -> None:
    rng = np.random.default_rng(0)
    print(f"decode one {WIDTH}x{HEIGHT} frame (median of {repeats}):")
    for colour, mono in zip(COLOUR_PIXEL_FORMATS, MONO_PIXEL_FORMATS, strict=True):
        counts = rng.integers(0, 1 << bit_depth_of(colour), size=(HEIGHT, WIDTH), dtype=np.uint16)
        data = pack_mosaic(counts, colour)
        exact = np.array_equal(unpack_mosaic(data, colour, width=WIDTH, height=HEIGHT), counts)
        t_mono = _median_s(lambda: unpack_mosaic(data, mono, width=WIDTH, height=HEIGHT), repeats)
        t_colour = _median_s(lambda: unpack_mosaic(data, colour, width=WIDTH, height=HEIGHT), repeats)
        print(f"  {colour:16s} {1e3 * t_colour:7.1f} ms   {mono:21s} {1e3 * t_mono:7.1f} ms   "
              f"ratio {t_colour / t_mono:4.2f}   bit-exact {exact}")


def demosaic(repeats: int) -> None:
    counts = np.random.default_rng(1).integers(0, 4096, size=(HEIGHT, WIDTH), dtype=np.uint16)
    mosaic = counts_to_float(counts, 12)  # (H, W) float32
    layout = MosaicLayout.imx250mzr()
    t_colour = _median_s(lambda: colour_stokes_from_mosaic(mosaic, layout, "RGGB"), repeats)
    t_mono = _median_s(lambda: stokes_from_mosaic(mosaic, layout), repeats)
    print(f"demosaic one 12-bit frame to Stokes (median of {repeats}): colour (3 colours x 3 Stokes) "
          f"{1e3 * t_colour:.0f} ms, mono super-pixel {1e3 * t_mono:.0f} ms, ratio {t_colour / t_mono:.1f}")


def delivered(fps: float, seconds: float, width: int, height: int) -> None:
    from polarshape.acquisition.aravis import AravisCamera
    from polarshape.acquisition.camera import CameraError
    from polarshape.acquisition.fake_gige import FakeGigECamera

    print(f"fake camera over loopback, {width}x{height} free-running at {fps:g} fps for {seconds:g} s "
          "(the fake generates every frame in Python, which bounds the rate at full size):")
    results = {}
    for model, pixel_format in (("TRI050S-PC", "PolarizeMono12p"), ("TRI050S-QC", "BayerRG12p")):
        with FakeGigECamera(serial=f"BENCH{model[-2:]}", model=model, width=width, height=height,
                            pixel_format=pixel_format, frame_rate_hz=fps) as fake, \
                AravisCamera(fake.address, trigger="off", packet_size=1400, max_attempts=10) as cam:
            cam.configure(pixel_format=pixel_format)
            frames, failed, exact = 0, 0, 0
            deadline = time.monotonic() + seconds
            t0 = time.monotonic()
            while time.monotonic() < deadline:
                try:
                    frame = cam.capture(timeout_s=2.0)
                except CameraError:
                    failed += 1
                    continue
                frames += 1
                exact += bool(np.array_equal(frame.image, fake.expected_image(frame)))
            rate = frames / (time.monotonic() - t0)
            stats = cam.stream_statistics()
        results[model] = rate
        print(f"  {model} {pixel_format:16s} {rate:5.1f} fps delivered, {exact}/{frames} bit-exact, "
              f"{failed} capture errors, stream {stats}")
    print(f"  ratio colour/mono {results['TRI050S-QC'] / results['TRI050S-PC']:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fps", type=float, default=24.0)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--roi", type=int, nargs=2, default=(WIDTH, HEIGHT), metavar=("W", "H"),
                        help="fake-camera frame size (default the full sensor)")
    parser.add_argument("--no-camera", action="store_true", help="skip the fake-camera measurement")
    args = parser.parse_args()
    torch.set_num_threads(1)
    decode(args.repeats)
    demosaic(args.repeats)
    if not args.no_camera:
        delivered(args.fps, args.seconds, *args.roi)


if __name__ == "__main__":
    main()
