"""Arena SDK / ArenaView saves: the simulated sphere written in every Arena form (.raw in each
PolarizeMono format, left-shifted 16-bit PNG/TIFF, 8-bit), imported with a light file, gives the
same counts and the same normals; refusals name the file and the fix; the left-shift warning of
capture loading fires on shifted data only."""

from __future__ import annotations

import dataclasses
import json
import warnings
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.errors import CaptureError, OutputExistsError, SuspiciousInputWarning
from polarshape.io.capture import Capture, CaptureSpec, load_capture, write_capture
from polarshape.io.importers import ARENA_PIXEL_FORMATS, import_arena, read_arena_frame
from polarshape.metrics import angular_error_deg
from polarshape.normals import recover_normals
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import preprocess_capture

#: DiLiGenT (x right, y up, z toward the viewer) → ours, written out here so that a wrong
#: conversion in the package cannot cancel out.
FLIP = np.array([1.0, -1.0, -1.0])
LAMBERTIAN = RecoveryOptions(model="lambertian")


# --- the byte layouts, written out from the GenICam PFNC / GigE Vision texts (not the package's) ---


def _pack12p(counts: np.ndarray) -> bytes:
    """PFNC Mono12p: an LSB-first bit stream; pixels a, b → a[7:0], b[3:0]a[11:8], b[11:4]."""
    a, b = counts.reshape(-1)[0::2].astype(np.uint16), counts.reshape(-1)[1::2].astype(np.uint16)
    return np.stack([a & 0xFF, (a >> 8) | ((b & 0xF) << 4), b >> 4], axis=1).astype(np.uint8).tobytes()


def _pack12_gev(counts: np.ndarray) -> bytes:
    """GigE Vision Mono12Packed: pixels a, b → a[11:4], b[3:0]a[3:0], b[11:4]."""
    a, b = counts.reshape(-1)[0::2].astype(np.uint16), counts.reshape(-1)[1::2].astype(np.uint16)
    return np.stack([a >> 4, (a & 0xF) | ((b & 0xF) << 4), b >> 4], axis=1).astype(np.uint8).tobytes()


def _raw_bytes(counts: np.ndarray, pixel_format: str) -> bytes:
    """One frame as an Arena .raw save holds it (the IMX250MZR's PolarizeMono16: 12-bit counts << 4)."""
    if pixel_format == "PolarizeMono8":
        return counts.astype(np.uint8).tobytes()
    if pixel_format == "PolarizeMono12":
        return counts.astype("<u2").tobytes()
    if pixel_format == "PolarizeMono16":
        return (counts.astype(np.uint16) << 4).astype("<u2").tobytes()
    return _pack12p(counts) if pixel_format == "PolarizeMono12p" else _pack12_gev(counts)


def test_packed_layouts_on_a_known_pair(tmp_path: Path) -> None:
    """0x123, 0xABC in both 12-bit packings (bytes from the standards' tables)."""
    for pixel_format, hex_bytes in (("PolarizeMono12p", "23c1ab"), ("PolarizeMono12Packed", "12c3ab")):
        path = tmp_path / f"{pixel_format}.raw"
        path.write_bytes(bytes.fromhex(hex_bytes))
        frame = read_arena_frame(path, pixel_format=pixel_format, width=2, height=1)
        assert frame.counts.tolist() == [[0x123, 0xABC]] and frame.bit_depth == 12 and frame.shift == 0


# --- the sphere in every Arena form --------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Capture:
    """The shipped sphere, 64×64 raw pixels, 8 lights; 12-bit (PolarizeMono12), mask dropped (an
    Arena import has none, so both recover on the same pixels)."""
    capture = load_capture(render_sphere(tmp_path_factory.mktemp("sphere"), width=64, pixel_size_m=4.4e-4, lights=8,
                                         seed=3))
    assert capture.bit_depth == 12 and capture.frames.max() > 255
    return dataclasses.replace(capture, mask=None)


@pytest.fixture(scope="module")
def sphere8(sphere: Capture, tmp_path_factory: pytest.TempPathFactory) -> Capture:
    """The sphere as an 8-bit camera would give it (counts >> 4), a capture of its own."""
    camera = sphere.spec.camera.model_copy(update={"bit_depth": 8})
    capture = Capture(spec=sphere.spec.model_copy(update={"camera": camera}), frames=sphere.frames >> 4)
    return load_capture(write_capture(tmp_path_factory.mktemp("sphere8") / "capture", capture))


def _light_file(path: Path, capture: Capture) -> Path:
    """The capture's lights in DiLiGenT's frame, one 'x y z' per line."""
    rows = [np.asarray(light.direction) * FLIP for light in capture.spec.lights]
    path.write_text("\n".join(" ".join(f"{v:.12f}" for v in row) for row in rows) + "\n")
    return path


def _write_frames(folder: Path, capture: Capture, form: str) -> list[Path]:
    """The capture's frames as Arena saves: ``raw:<format>``, ``png16-shifted``, ``tiff16-shifted``,
    ``tiff16-low``, ``png8``; names frame_1 … frame_K (natural order differs from string order)."""
    folder.mkdir(parents=True)
    paths = []
    for k, counts in enumerate(capture.frames, start=1):
        if form.startswith("raw:"):
            path = folder / f"frame_{k}.raw"
            path.write_bytes(_raw_bytes(counts, form[4:]))
        else:
            suffix = ".png" if form.startswith("png") else ".tif"
            path = folder / f"frame_{k}{suffix}"
            image = {"png16-shifted": lambda c: c << 4, "tiff16-shifted": lambda c: c << 4,
                     "tiff16-low": lambda c: c, "png8": lambda c: c.astype(np.uint8)}[form](counts)
            assert cv2.imwrite(str(path), image)
        paths.append(path)
    return paths


def _normals(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
    result = recover_normals(preprocess_capture(capture, demosaic="superpixel", mixed_sigma=None), LAMBERTIAN)
    return result.normals.numpy(), result.mask.numpy()


@pytest.fixture(scope="module")
def sphere_normals(sphere: Capture) -> tuple[np.ndarray, np.ndarray]:
    return _normals(sphere)


FORMS_12BIT = [
    ("raw:PolarizeMono12", {"pixel_format": "PolarizeMono12"}, 0),
    ("raw:PolarizeMono12p", {"pixel_format": "PolarizeMono12p"}, 0),
    ("raw:PolarizeMono12Packed", {"pixel_format": "PolarizeMono12Packed"}, 0),
    ("raw:PolarizeMono16", {"pixel_format": "PolarizeMono16"}, 4),
    ("png16-shifted", {}, 4),
    ("tiff16-shifted", {}, 4),
    ("tiff16-low", {"pixel_format": "PolarizeMono12"}, 0),
]


@pytest.mark.parametrize("form, options, shift", FORMS_12BIT, ids=[f[0] for f in FORMS_12BIT])
def test_round_trip_gives_the_same_counts_and_normals(tmp_path: Path, sphere: Capture, form: str, options: dict,
                                                      shift: int,
                                                      sphere_normals: tuple[np.ndarray, np.ndarray]) -> None:
    _write_frames(tmp_path / "arena", sphere, form)
    size = {"width": 64, "height": 64} if form.startswith("raw:") else {}
    with warnings.catch_warnings():
        warnings.simplefilter("error", SuspiciousInputWarning)  # a shifted capture would warn on write/load
        import_arena(tmp_path / "arena", tmp_path / "capture", lights=_light_file(tmp_path / "lights.txt", sphere),
                     light_frame="diligent", **options, **size)
        capture = load_capture(tmp_path / "capture")
    assert capture.bit_depth == 12 and np.array_equal(capture.frames, sphere.frames)
    assert np.allclose([l.direction for l in capture.spec.lights], [l.direction for l in sphere.spec.lights], atol=1e-9)
    source = capture.ground_truth["source"]
    assert source["left_shift"] == shift and source["importer"] == "arena"
    assert [Path(f).name for f in source["frames"]][:3] == ["frame_1" + Path(source["frames"][0]).suffix,
                                                            "frame_2" + Path(source["frames"][0]).suffix,
                                                            "frame_3" + Path(source["frames"][0]).suffix]
    if shift:  # said, never silent: in the notes and in camera.model
        assert "left-shifted by 4" in source["notes"][0] and "left-shifted by 4" in capture.spec.camera.model
    else:
        assert source["notes"] == [] and "shift" not in capture.spec.camera.model
    n0, m0 = sphere_normals
    n1, m1 = _normals(capture)
    assert (m0 == m1).all() and m0.sum() > 400
    assert np.nanmean(angular_error_deg(n0, n1, m0 & m1)) < 0.05


@pytest.mark.parametrize("form, size", [("raw:PolarizeMono8", {"width": 64, "height": 64}), ("png8", {})])
def test_eight_bit_round_trip(tmp_path: Path, sphere8: Capture, form: str, size: dict) -> None:
    _write_frames(tmp_path / "arena", sphere8, form)
    capture = import_arena(tmp_path / "arena", tmp_path / "capture", lights=_light_file(tmp_path / "l.txt", sphere8),
                           light_frame="diligent", pixel_format="PolarizeMono8", **size)
    assert capture.bit_depth == 8 and np.array_equal(load_capture(tmp_path / "capture").frames, sphere8.frames)
    (n0, m0), (n1, m1) = _normals(sphere8), _normals(capture)
    assert (m0 == m1).all() and np.nanmean(angular_error_deg(n0, n1, m0 & m1)) < 0.05


def test_ten_bit_shifted_by_six_is_found(tmp_path: Path) -> None:
    counts = np.random.default_rng(0).integers(0, 1024, size=(8, 8), dtype=np.uint16)
    counts[0, 0] = 1000
    assert cv2.imwrite(str(tmp_path / "f.png"), counts << 6)
    frame = read_arena_frame(tmp_path / "f.png")
    assert frame.bit_depth == 10 and frame.shift == 6 and np.array_equal(frame.counts, counts)
    assert "multiple of 64" in frame.notes[0]


def test_true_sixteen_bit_and_low_counts_are_kept(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    full = rng.integers(0, 65536, size=(8, 8), dtype=np.uint16)
    assert cv2.imwrite(str(tmp_path / "full.tif"), full)
    frame = read_arena_frame(tmp_path / "full.tif")
    assert frame.bit_depth == 16 and frame.shift == 0 and frame.notes == () and np.array_equal(frame.counts, full)
    low = rng.integers(0, 4096, size=(8, 8), dtype=np.uint16)
    assert cv2.imwrite(str(tmp_path / "low.png"), low)
    frame = read_arena_frame(tmp_path / "low.png")  # not guessed: kept 16-bit, and the note says what to pass
    assert frame.bit_depth == 16 and "--pixel-format PolarizeMono12" in frame.notes[0]
    assert read_arena_frame(tmp_path / "low.png", pixel_format="PolarizeMono12").bit_depth == 12


# --- lights --------------------------------------------------------------------------------------


def test_lp_lights_go_by_frame_name_with_intensities(tmp_path: Path, sphere: Capture) -> None:
    paths = _write_frames(tmp_path / "arena", sphere, "png16-shifted")
    rows = [(p.name, np.asarray(l.direction) * FLIP) for p, l in zip(paths, sphere.spec.lights)][::-1]
    (tmp_path / "lights.lp").write_text(f"{len(rows)}\n" + "".join(f"{n} {d[0]:.12f} {d[1]:.12f} {d[2]:.12f}\n"
                                                                 for n, d in rows))
    (tmp_path / "intensities.txt").write_text("".join(f"{k + 1}\n" for k in range(len(rows))))  # in .lp order
    capture = import_arena(paths, tmp_path / "capture", lights=tmp_path / "lights.lp", light_frame="diligent",
                           intensities=tmp_path / "intensities.txt", black_level=3,
                           intrinsics=(900.0, 900.0, 31.5, 31.5))
    assert np.allclose([l.direction for l in capture.spec.lights], [l.direction for l in sphere.spec.lights], atol=1e-9)
    assert [l.intensity for l in capture.spec.lights] == list(range(len(rows), 0, -1))
    assert capture.spec.camera.projection == "perspective" and capture.spec.camera.black_level == 3


def test_lights_in_the_wrong_frame_are_refused(tmp_path: Path, sphere: Capture) -> None:
    _write_frames(tmp_path / "arena", sphere, "png16-shifted")
    with pytest.raises(CaptureError, match=r"lights\.txt:1: .*behind the object.*frame 'diligent'"):
        import_arena(tmp_path / "arena", tmp_path / "c", lights=_light_file(tmp_path / "lights.txt", sphere),
                     light_frame="opencv")
    (tmp_path / "two.txt").write_text("0 0 1\n0 0.6 0.8\n")
    with pytest.raises(CaptureError, match=r"two\.txt: 2 light\(s\) for the 8 frame\(s\)"):
        import_arena(tmp_path / "arena", tmp_path / "c", lights=tmp_path / "two.txt", light_frame="diligent")
    assert not (tmp_path / "c").exists()


# --- refusals ------------------------------------------------------------------------------------


def _one_light(tmp_path: Path) -> Path:
    path = tmp_path / "one.txt"
    path.write_text("0 0 1\n")
    return path


def test_raw_needs_its_format_and_size(tmp_path: Path) -> None:
    path = tmp_path / "f.raw"
    path.write_bytes(bytes(64 * 64 * 3 // 2))
    with pytest.raises(CaptureError, match=r"f\.raw: a \.raw save has no header.*missing --width, --height"):
        read_arena_frame(path, pixel_format="PolarizeMono12p")
    with pytest.raises(CaptureError, match=r"f\.raw: .*missing --pixel-format"):
        import_arena([path], tmp_path / "c", lights=_one_light(tmp_path), light_frame="diligent", width=64, height=64)
    with pytest.raises(CaptureError, match=r"f\.raw: pixel format 'Mono12' is not one of"):
        read_arena_frame(path, pixel_format="Mono12", width=64, height=64)


def test_raw_size_mismatch_says_what_would_fit(tmp_path: Path) -> None:
    path = tmp_path / "f.raw"
    path.write_bytes(bytes(64 * 64 * 3 // 2))  # a 64x64 12-bit packed frame
    with pytest.raises(CaptureError, match=r"f\.raw: is 6144 bytes, but one PolarizeMono16 frame of 64x64 is 8192 "
                                           r"bytes.*would fit PolarizeMono12p at 64x64 or PolarizeMono12Packed at "
                                           r"64x64 or PolarizeMono16 at 64x48"):
        read_arena_frame(path, pixel_format="PolarizeMono16", width=64, height=64)
    path.write_bytes(bytes(2448 * 2048 * 2 + 10))
    with pytest.raises(CaptureError, match=r"none of the pixel formats"):
        read_arena_frame(path, pixel_format="PolarizeMono16", width=2448, height=2048)


def test_raw_mono12_above_4095_points_to_mono16(tmp_path: Path) -> None:
    path = tmp_path / "f.raw"
    path.write_bytes(np.full((2, 2), 4096, "<u2").tobytes())
    with pytest.raises(CaptureError, match=r"f\.raw: .*above 4095.*--pixel-format PolarizeMono16"):
        read_arena_frame(path, pixel_format="PolarizeMono12", width=2, height=2)


@pytest.mark.parametrize("name, image, options, match", [
    ("preview.bmp", np.zeros((4, 4), np.uint8), {},
     r"preview\.bmp: a \.bmp file is a display image.*save the frames as \.raw"),
    ("preview.jpg", np.zeros((4, 4), np.uint8), {"pixel_format": "PolarizeMono8"},
     r"preview\.jpg: a \.jpg file is a display"),
    ("rgb.png", np.zeros((4, 4, 3), np.uint16), {}, r"rgb\.png: has 3 channels: a display image.*one channel"),
    ("rgb8.tif", np.zeros((4, 4, 3), np.uint8), {"pixel_format": "PolarizeMono8"}, r"rgb8\.tif: has 3 channels"),
    ("grey8.png", np.zeros((4, 4), np.uint8), {}, r"grey8\.png: an 8-bit PNG is usually a display image.*"
                                                   r"pass --pixel-format PolarizeMono8"),
    ("grey8.tif", np.zeros((4, 4), np.uint8), {"pixel_format": "PolarizeMono12"},
     r"grey8\.tif: an 8-bit TIFF cannot hold"),
    ("grey16.png", np.zeros((4, 4), np.uint16), {"pixel_format": "PolarizeMono8"}, r"grey16\.png: a 16-bit PNG, but"),
    ("odd12.png", np.full((4, 4), 4097, np.uint16), {"pixel_format": "PolarizeMono12"},
     r"odd12\.png: counts up to 4097, not all multiples of 16: these are not 12-bit counts"),
])
def test_refused_images_name_the_file_and_fix(tmp_path: Path, name: str, image: np.ndarray, options: dict,
                                              match: str) -> None:
    assert cv2.imwrite(str(tmp_path / name), image)
    with pytest.raises(CaptureError, match=match):
        read_arena_frame(tmp_path / name, **options)
    with pytest.raises(CaptureError, match=match):
        import_arena([tmp_path / name], tmp_path / "c", lights=_one_light(tmp_path), light_frame="diligent", **options)


def test_folders_of_previews_or_mixed_kinds_are_refused(tmp_path: Path) -> None:
    (tmp_path / "previews").mkdir()
    assert cv2.imwrite(str(tmp_path / "previews" / "a.bmp"), np.zeros((4, 4), np.uint8))
    with pytest.raises(CaptureError, match=r"previews: holds only \.bmp files.*display image"):
        import_arena(tmp_path / "previews", tmp_path / "c", lights=_one_light(tmp_path), light_frame="diligent")
    (tmp_path / "mixed").mkdir()
    (tmp_path / "mixed" / "a.raw").write_bytes(bytes(32))
    assert cv2.imwrite(str(tmp_path / "mixed" / "b.png"), np.zeros((4, 4), np.uint16))
    with pytest.raises(CaptureError, match=r"mixed: holds frames of several kinds \(\.png, \.raw\)"):
        import_arena(tmp_path / "mixed", tmp_path / "c", lights=_one_light(tmp_path), light_frame="diligent")


def test_frames_of_different_sizes_or_odd_size_are_refused(tmp_path: Path) -> None:
    (tmp_path / "two.txt").write_text("0 0 1\n0 0.6 0.8\n")
    assert cv2.imwrite(str(tmp_path / "a.png"), np.full((4, 4), 16, np.uint16))
    assert cv2.imwrite(str(tmp_path / "b.png"), np.full((4, 6), 16, np.uint16))
    with pytest.raises(CaptureError, match=r"b\.png: is a 16-bit PNG of 6x4 but a\.png is a 16-bit PNG of 4x4"):
        import_arena([tmp_path / "a.png", tmp_path / "b.png"], tmp_path / "c", lights=tmp_path / "two.txt",
                     light_frame="diligent")
    assert cv2.imwrite(str(tmp_path / "odd.png"), np.full((4, 5), 16, np.uint16))
    with pytest.raises(CaptureError, match=r"odd\.png: is 5x4; a polarisation mosaic needs even width and height"):
        import_arena([tmp_path / "odd.png"], tmp_path / "c", lights=_one_light(tmp_path), light_frame="diligent")


def test_import_never_writes_over_anything(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    assert cv2.imwrite(str(src / "a.png"), np.full((4, 4), 4096, np.uint16))
    lights = _one_light(src)
    for out in (src, tmp_path):  # the source folder, or a folder holding it
        with pytest.raises(OutputExistsError, match="is, or holds, the source"):
            import_arena(src, out, lights=lights, light_frame="diligent", overwrite=True)
    (tmp_path / "taken").mkdir()
    with pytest.raises(OutputExistsError, match="already exists.*--overwrite"):
        import_arena(src, tmp_path / "taken", lights=lights, light_frame="diligent")
    import_arena(src, tmp_path / "taken", lights=lights, light_frame="diligent", overwrite=True)
    assert json.loads((tmp_path / "taken" / "ground_truth" / "source.json").read_text())["importer"] == "arena"


# --- the left-shift warning of capture loading ----------------------------------------------------


def _capture16(path: Path, frames: np.ndarray) -> Path:
    spec = CaptureSpec.model_validate({
        "format": "polarshape-capture/1", "camera": {"projection": "orthographic", "bit_depth": 16},
        "lights": [{"direction": [0, 0, -1], "frame": f"frames/{i:03d}.png"} for i in range(len(frames))],
    })
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SuspiciousInputWarning)  # writing warns too; the load is tested
        return write_capture(path, Capture(spec=spec, frames=frames))


def test_left_shifted_capture_warns_on_load(tmp_path: Path, sphere: Capture) -> None:
    """10- and 8-bit counts shifted into 16 bits warn once per capture (their clipping would be
    missed); 12-bit ones shifted by 4 are PolarizeMono16, whose clipping at 65520 is caught: no warning."""
    ten = np.random.default_rng(2).integers(0, 1024, size=(3, 8, 8), dtype=np.uint16) << 6
    with pytest.warns(SuspiciousInputWarning, match=r"frames: every count is a multiple of 64 and the largest is "
                      r"\d+: these look like 10-bit counts left-shifted by 6.*not flagged as saturated.*"
                      r"camera\.bit_depth: 10.*polarshape import arena") as record:
        load_capture(_capture16(tmp_path / "ten", ten))
    assert len(record) == 1  # once for the capture, not once per frame
    eight = np.random.default_rng(4).integers(0, 256, size=(1, 8, 8), dtype=np.uint16) << 8
    with pytest.warns(SuspiciousInputWarning, match=r"8-bit counts left-shifted by 8"):
        load_capture(_capture16(tmp_path / "eight", eight))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SuspiciousInputWarning)
        load_capture(_capture16(tmp_path / "twelve", sphere.frames << 4))


def test_ordinary_captures_do_not_warn(tmp_path: Path, sphere: Capture) -> None:
    rng = np.random.default_rng(3)
    full = rng.integers(0, 65536, size=(2, 64, 64), dtype=np.uint16)
    full[:, 0, 0] = 17  # one odd count is enough, wherever it is
    nearly = (rng.integers(0, 4096, size=(1, 64, 64), dtype=np.uint16) << 4)
    nearly[0, 37, 11] += 1
    flat = np.full((1, 4, 4), 32768, dtype=np.uint16)  # a flat frame cannot tell
    paths = [_capture16(tmp_path / name, frames) for name, frames in (("full", full), ("nearly", nearly),
                                                                        ("flat", flat))]
    with warnings.catch_warnings():
        warnings.simplefilter("error", SuspiciousInputWarning)
        for path in paths:
            load_capture(path)
        load_capture(write_capture(tmp_path / "sphere12", sphere))  # 12-bit: never looked at


def test_arena_formats_are_the_cameras() -> None:
    assert set(ARENA_PIXEL_FORMATS) == {"PolarizeMono8", "PolarizeMono12", "PolarizeMono12p", "PolarizeMono12Packed",
                                        "PolarizeMono16", "BayerRG8", "BayerRG12", "BayerRG12p", "BayerRG12Packed",
                                        "BayerRG16"}  # TRI050S-PC, then the colour TRI050S-QC


# --- the colour polarisation camera (TRI050S-QC, IMX250MYR): raw BayerRG saves ---------------------

COLOUR_RAW = {"BayerRG8": "PolarizeMono8", "BayerRG12": "PolarizeMono12", "BayerRG12p": "PolarizeMono12p",
              "BayerRG12Packed": "PolarizeMono12Packed", "BayerRG16": "PolarizeMono16"}


@pytest.mark.parametrize("colour_format", list(COLOUR_RAW))
def test_colour_raw_saves_import_as_colour_mosaics(tmp_path: Path, colour_format: str) -> None:
    """A TRI050S-QC .raw save has the byte layout of the PolarizeMono format of the same suffix; the capture
    keeps the counts bit-exactly and records camera.mosaic.bayer RGGB (what colour recovery needs)."""
    bits = 8 if colour_format.endswith("8") else 12
    frames = np.random.default_rng(7).integers(0, 1 << bits, size=(3, 8, 12), dtype=np.uint16)
    (tmp_path / "arena").mkdir()
    for k, counts in enumerate(frames, start=1):
        (tmp_path / "arena" / f"frame_{k}.raw").write_bytes(_raw_bytes(counts, COLOUR_RAW[colour_format]))
    (tmp_path / "lights.txt").write_text("0 0 1\n0.2 0 0.98\n0 0.2 0.98\n")
    capture = import_arena(tmp_path / "arena", tmp_path / "capture", lights=tmp_path / "lights.txt",
                           light_frame="diligent", pixel_format=colour_format, width=12, height=8)
    loaded = load_capture(tmp_path / "capture")
    assert loaded.spec.camera.mosaic.bayer == "RGGB" and capture.spec.camera.mosaic.bayer == "RGGB"
    assert loaded.bit_depth == bits and np.array_equal(loaded.frames, frames)
    assert loaded.ground_truth["source"]["left_shift"] == (4 if colour_format == "BayerRG16" else 0)


def test_eight_bit_colour_saves_are_read_with_bayer_rg8(tmp_path: Path) -> None:
    counts = np.random.default_rng(8).integers(0, 256, size=(8, 8), dtype=np.uint16)
    path = tmp_path / "frame.raw"
    path.write_bytes(counts.astype(np.uint8).tobytes())
    assert read_arena_frame(path, pixel_format="BayerRG8", width=8, height=8).counts.tolist() == counts.tolist()
    png = tmp_path / "frame.png"
    cv2.imwrite(str(png), counts.astype(np.uint8))
    assert read_arena_frame(png, pixel_format="BayerRG8").bit_depth == 8
    with pytest.raises(CaptureError, match="BayerRG8 for a colour camera"):
        read_arena_frame(png, pixel_format="BayerRG12")
