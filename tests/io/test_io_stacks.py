"""Importer of demosaiced polariser stacks: a simulated sphere split into its four polariser images,
written as a stack (four PNGs per light; one .npy or 4-page TIFF per light) with a DiLiGenT-frame
light file, imported — the same raw frames, lights and normals — and every refusal naming its file."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from polarshape.errors import CaptureError, OutputExistsError
from polarshape.imaging.mosaic import split_mosaic
from polarshape.io.capture import Capture, load_capture, parse_capture_spec
from polarshape.io.importers import import_stack, read_stack
from polarshape.metrics import angular_error_deg
from polarshape.normals import recover_normals
from polarshape.recover.options import RecoveryOptions
from polarshape.recover.preprocess import preprocess_capture

#: DiLiGenT (x right, y up, z toward the viewer) → ours, written out here (not the package's).
FLIP = np.array([1.0, -1.0, -1.0])
#: The label of our angle a in each convention, written out here: ours is clockwise on screen
#: (x toward y, down); the maker's and polanalyser's run the other way (label = −a mod 180).
LABEL_OF_OURS = {
    "clockwise_on_screen": {0: 0, 45: 45, 90: 90, 135: 135},
    "counterclockwise_on_screen": {0: 0, 45: 135, 90: 90, 135: 45},
    "polanalyser": {0: 0, 45: 135, 90: 90, 135: 45},
}
LAMBERTIAN = RecoveryOptions(model="lambertian")


@pytest.fixture(scope="module")
def sphere(tmp_path_factory: pytest.TempPathFactory, render_sphere: Callable[..., Path]) -> Capture:
    """The shipped polarising sphere, 64×64 raw pixels (32×32 super-pixels), 8 lights, 12-bit."""
    return load_capture(render_sphere(tmp_path_factory.mktemp("sphere"), width=64, pixel_size_m=4.4e-4, lights=8,
                                      seed=3))


def _labelled(capture: Capture, angles: str) -> list[dict[int, np.ndarray]]:
    """Per light, {label: (H, W) uint16 image} of the capture's four polariser sites, labelled in ``angles``."""
    ours = split_mosaic(torch.from_numpy(capture.frames.astype(np.int32)), capture.layout).numpy()  # (K, 4, H, W)
    return [{LABEL_OF_OURS[angles][a]: ours[k, c].astype(np.uint16) for c, a in enumerate((0, 45, 90, 135))}
            for k in range(ours.shape[0])]


def _light_file(capture: Capture, path: Path) -> Path:
    """The capture's light directions in DiLiGenT's frame, one 'x y z' per line."""
    lines = [" ".join(f"{v:.15f}" for v in np.asarray(l.direction) * FLIP) for l in capture.spec.lights]
    path.write_text("\n".join(lines) + "\n")
    return path


def _new_stack_folder(capture: Capture, folder: Path) -> None:
    """The folder, with the capture's object mask as mask.png (super-pixel size = the stack's)."""
    folder.mkdir(parents=True)
    assert cv2.imwrite(str(folder / "mask.png"), capture.mask.astype(np.uint8) * 255)


def _write_pngs(capture: Capture, folder: Path, angles: str) -> Path:
    _new_stack_folder(capture, folder)
    for k, images in enumerate(_labelled(capture, angles)):
        for label, image in images.items():
            assert cv2.imwrite(str(folder / f"{k + 1}_{label}.png"), image)
    return folder


def _write_npys(capture: Capture, folder: Path, angles: str, *, channels_last: bool) -> Path:
    _new_stack_folder(capture, folder)
    for k, images in enumerate(_labelled(capture, angles)):
        stack = np.stack([images[a] for a in (0, 45, 90, 135)])  # (4, H, W), label order
        np.save(folder / f"{k:03d}.npy", np.moveaxis(stack, 0, -1) if channels_last else stack)
    return folder


def _write_tiffs(capture: Capture, folder: Path, angles: str) -> Path:
    _new_stack_folder(capture, folder)
    for k, images in enumerate(_labelled(capture, angles)):
        assert cv2.imwritemulti(str(folder / f"light{k:02d}.tif"), [images[a] for a in (0, 45, 90, 135)])
    return folder


def _normals(capture: Capture) -> tuple[np.ndarray, np.ndarray]:
    result = recover_normals(preprocess_capture(capture, demosaic="superpixel"), LAMBERTIAN)
    return result.normals.numpy(), result.mask.numpy()


def _check_same(original: Capture, imported: Capture) -> None:
    assert imported.bit_depth == original.bit_depth
    assert imported.frames.dtype == np.uint16 and np.array_equal(imported.frames, original.frames)
    assert np.allclose([l.direction for l in imported.spec.lights], [l.direction for l in original.spec.lights],
                       atol=1e-12)
    assert [l.intensity for l in imported.spec.lights] == [1.0] * original.num_lights
    assert np.array_equal(imported.mask, original.mask)


@pytest.mark.parametrize("angles", ["counterclockwise_on_screen", "clockwise_on_screen", "polanalyser"])
def test_round_trip_png_stacks_give_the_same_frames_and_normals(sphere: Capture, tmp_path: Path, angles: str) -> None:
    src = _write_pngs(sphere, tmp_path / "src", angles)
    lights = _light_file(sphere, tmp_path / "light_directions.txt")
    import_stack(src, tmp_path / "cap", lights=lights, light_frame="diligent", angles=angles, bit_depth=12)
    imported = load_capture(tmp_path / "cap")
    _check_same(sphere, imported)
    (n0, m0), (n1, m1) = _normals(sphere), _normals(imported)
    assert (m0 == m1).all() and m0.sum() > 400
    assert np.nanmean(angular_error_deg(n0, n1, m0 & m1)) < 0.05
    source = imported.ground_truth["source"]
    assert source["importer"] == "stack" and source["form"] == "images" and source["angles"] == angles
    assert source["files"][0] == [f"1_{a}.png" for a in (0, 45, 90, 135)]


@pytest.mark.parametrize("form", ["npy_first", "npy_last", "tiff"])
def test_round_trip_one_file_per_light(sphere: Capture, tmp_path: Path, form: str) -> None:
    if form == "tiff":
        src = _write_tiffs(sphere, tmp_path / "src", "counterclockwise_on_screen")
    else:
        src = _write_npys(sphere, tmp_path / "src", "counterclockwise_on_screen", channels_last=form == "npy_last")
    lights = _light_file(sphere, tmp_path / "l.txt")
    capture = import_stack(src, tmp_path / "cap", lights=lights, light_frame="diligent", bit_depth=12)
    imported = load_capture(tmp_path / "cap")
    _check_same(sphere, imported)
    assert np.array_equal(capture.frames, imported.frames) and capture.ground_truth["source"]["form"] == "stacks"
    (n0, m0), (n1, m1) = _normals(sphere), _normals(imported)
    assert np.nanmean(angular_error_deg(n0, n1, m0 & m1)) < 0.05


def test_superpixel_demosaic_gives_back_the_stack_values(tmp_path: Path) -> None:
    """Each stack pixel is one super-pixel: its four sites hold the four images, at our angles."""
    rng = np.random.default_rng(0)
    labelled = rng.integers(100, 4000, size=(2, 4, 3, 5)).astype(np.uint16)  # (K, labels 0/45/90/135, H, W)
    (tmp_path / "src").mkdir()
    for k in range(2):
        np.save(tmp_path / "src" / f"{k}.npy", labelled[k])
    (tmp_path / "l.txt").write_text("0 0 1\n0.6 0 0.8\n")
    capture = import_stack(tmp_path / "src", tmp_path / "cap", lights=tmp_path / "l.txt", light_frame="diligent",
                           angles="counterclockwise_on_screen", bit_depth=12)
    f = capture.frames  # (2, 6, 10); IMX250MZR sites as the maker labels them: [[90, 45], [135, 0]]
    for (i, j), label in {(0, 0): 90, (0, 1): 45, (1, 0): 135, (1, 1): 0}.items():
        assert np.array_equal(f[:, i::2, j::2], labelled[:, (0, 45, 90, 135).index(label)])
    clockwise = import_stack(tmp_path / "src", tmp_path / "cap2", lights=tmp_path / "l.txt", light_frame="diligent",
                             angles="clockwise_on_screen", bit_depth=12)
    # labels taken as ours: the 45 image goes where our 45° polariser is — the maker's 135 site
    assert np.array_equal(clockwise.frames[:, 1::2, 0::2], labelled[:, 1])
    assert not np.array_equal(clockwise.frames, capture.frames)


def test_natural_order_zero_padded_angles_mask_intensities_and_lp_names(sphere: Capture, tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    images = _labelled(sphere, "counterclockwise_on_screen")[:3]
    for name, light in zip(("2", "10", "1"), images):  # natural order: 1, 2, 10
        for label, image in light.items():
            cv2.imwrite(str(src / f"obj-{name}-{label:03d}.tif"), image)
    mask = np.zeros(images[0][0].shape, dtype=np.uint8)
    mask[4:20, 5:25] = 255
    cv2.imwrite(str(src / "mask.png"), mask)
    # an .lp file naming each light (in another order) goes by name
    (tmp_path / "l.lp").write_text("3\nobj-10.png 0.6 0 0.8\nobj-1.png 0 0 1\nobj-2.png 0 0.6 0.8\n")
    (tmp_path / "e.txt").write_text("1 1 1\n2\n3 3 3\n")
    capture = import_stack(src, tmp_path / "cap", lights=tmp_path / "l.lp", light_frame="diligent",
                           intensities=tmp_path / "e.txt")
    assert capture.bit_depth == 16 and capture.frames.shape == (3, 64, 64)
    assert capture.ground_truth["source"]["lights"] == ["obj-1", "obj-2", "obj-10"]
    assert np.array_equal(capture.frames[1], sphere.frames[0]) and np.array_equal(capture.frames[0], sphere.frames[2])
    assert np.allclose([l.direction for l in capture.spec.lights], [[0, 0, -1], [0, -0.6, -0.8], [0.6, 0, -0.8]])
    assert [l.intensity for l in capture.spec.lights] == [1.0, 2.0, 3.0]
    assert np.array_equal(load_capture(tmp_path / "cap").mask, mask != 0)


def test_float_npy_needs_a_bit_depth(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    np.save(tmp_path / "src" / "0.npy", np.full((4, 2, 2), 0.5, dtype=np.float32))
    (tmp_path / "l.txt").write_text("0 0 1\n")
    with pytest.raises(CaptureError, match=r"0\.npy: holds floats .*--bit-depth N"):
        read_stack(tmp_path / "src")
    assert read_stack(tmp_path / "src", bit_depth=12).images.max() == round(0.5 * 4095)
    np.save(tmp_path / "src" / "0.npy", np.full((4, 2, 2), 1.5))
    with pytest.raises(CaptureError, match=r"0\.npy: float values must be finite fractions of full scale in \[0, 1\]"):
        read_stack(tmp_path / "src", bit_depth=12)


def _png_stack(folder: Path, k: int = 2, shape: tuple[int, int] = (4, 6)) -> Path:
    folder.mkdir()
    for light in range(k):
        for label in (0, 45, 90, 135):
            cv2.imwrite(str(folder / f"{light:03d}_{label}.png"), np.full(shape, 100 + label, dtype=np.uint16))
    return folder


@pytest.mark.parametrize("damage, match", [
    (lambda s: (s / "001_90.png").unlink(), r"light '001' has no 90° image \(found 001_0\.png, 001_45\.png, "
                                            r"001_135\.png\); give four images"),
    (lambda s: cv2.imwrite(str(s / "001_45.png"), np.zeros((4, 5), np.uint16)),
     r"001_45\.png: is uint16 5x4 but 001_0\.png is uint16 6x4"),
    (lambda s: [cv2.imwrite(str(s / f"001_{a}.png"), np.zeros((6, 6), np.uint16)) for a in (0, 45, 90, 135)],
     r"001_0\.png: is uint16 6x6 but 000_0\.png is uint16 6x4; all lights must have one size"),
    (lambda s: cv2.imwrite(str(s / "000_135.png"), np.zeros((4, 6, 3), np.uint16)), r"000_135\.png: a colour image"),
    (lambda s: cv2.imwrite(str(s / "000_0.tif"), np.zeros((4, 6), np.uint16)), r"the 0° image of light '000' is also"),
    (lambda s: cv2.imwrite(str(s / "preview.png"), np.zeros((4, 6), np.uint8)), r"preview\.png: a \.png file without "
                                                                                r"an angle in its name"),
    (lambda s: np.save(s / "002.npy", np.zeros((4, 4, 6), np.uint16)), r"holds both single polariser images"),
    (lambda s: cv2.imwrite(str(s / "000_90.png"), np.full((4, 6), 5000, np.uint16)),
     r"000_0\.png: holds counts up to 5000, above 4095 = 2\*\*12 - 1"),
    (lambda s: (s / "000_0.png").write_bytes(b"not a png"), r"000_0\.png: cannot be decoded"),
])
def test_bad_stacks_are_refused_naming_the_file(tmp_path: Path, damage, match: str) -> None:  # noqa: ANN001
    src = _png_stack(tmp_path / "src")
    (tmp_path / "l.txt").write_text("0 0 1\n0.6 0 0.8\n")
    damage(src)
    with pytest.raises(CaptureError, match=match):
        import_stack(src, tmp_path / "cap", lights=tmp_path / "l.txt", light_frame="diligent", bit_depth=12)
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("write, match", [
    (lambda p: cv2.imwrite(str(p), np.zeros((4, 6, 4), np.uint16)), r"a 4-channel \(interleaved\) TIFF"),
    (lambda p: cv2.imwritemulti(str(p), [np.zeros((4, 6), np.uint16)] * 3), r"3 page\(s\)"),
    (lambda p: np.save(p.with_suffix(".npy"), np.zeros((3, 4, 6), np.uint16)), r"shape \(3, 4, 6\); a light's array"),
    (lambda p: np.save(p.with_suffix(".npy"), np.zeros((4, 4, 6), np.int32)), r"pixel type int32"),
])
def test_bad_per_light_files_are_refused(tmp_path: Path, write, match: str) -> None:  # noqa: ANN001
    (tmp_path / "src").mkdir()
    write(tmp_path / "src" / "000.tif")
    with pytest.raises(CaptureError, match=match):
        read_stack(tmp_path / "src")


def test_light_file_problems_and_empty_folders(tmp_path: Path) -> None:
    src = _png_stack(tmp_path / "src")
    (tmp_path / "three.txt").write_text("0 0 1\n0 0 1\n0.6 0 0.8\n")
    with pytest.raises(CaptureError, match=r"three\.txt: 3 light\(s\) for the 2 frame\(s\)"):
        import_stack(src, tmp_path / "cap", lights=tmp_path / "three.txt", light_frame="diligent")
    (tmp_path / "behind.txt").write_text("0 0 1\n0 0 -1\n")
    with pytest.raises(CaptureError, match=r"behind\.txt:2: light 1 points behind the object"):
        import_stack(src, tmp_path / "cap", lights=tmp_path / "behind.txt", light_frame="diligent")
    with pytest.raises(CaptureError, match="angles .*'ccw' is not one of"):
        import_stack(src, tmp_path / "cap", lights=tmp_path / "three.txt", light_frame="diligent",
                     angles="ccw")  # type: ignore[arg-type]
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("x")
    with pytest.raises(CaptureError, match=r"empty: no polariser images; name them <light>_<angle>\.png"):
        read_stack(tmp_path / "empty")
    with pytest.raises(CaptureError, match="not a folder"):
        read_stack(tmp_path / "none")
    with pytest.raises(CaptureError, match=r"8-bit images but bit_depth 12"):
        cv2.imwrite(str(src / "000_0.png"), np.zeros((4, 6), np.uint8))
        [cv2.imwrite(str(src / f"{k:03d}_{a}.png"), np.zeros((4, 6), np.uint8)) for k in (0, 1) for a in (0, 45, 90, 135)]
        read_stack(src, bit_depth=12)
    assert not (tmp_path / "cap").exists()


def test_stack_import_refuses_to_write_over_anything(tmp_path: Path) -> None:
    src = _png_stack(tmp_path / "src")
    (src / "l.txt").write_text("0 0 1\n0.6 0 0.8\n")  # a light file inside the folder is not an image
    listing = sorted(p.name for p in src.iterdir())
    for out in (src, tmp_path):
        with pytest.raises(OutputExistsError, match="holds, the source folder"):
            import_stack(src, out, lights=src / "l.txt", light_frame="diligent", overwrite=True)
    (tmp_path / "cap").mkdir()
    with pytest.raises(OutputExistsError, match="already exists"):
        import_stack(src, tmp_path / "cap", lights=src / "l.txt", light_frame="diligent")
    import_stack(src, tmp_path / "cap", lights=src / "l.txt", light_frame="diligent", overwrite=True)
    assert (tmp_path / "cap" / "capture.yaml").is_file() and sorted(p.name for p in src.iterdir()) == listing


# --- mosaic.angles: polanalyser ------------------------------------------------------------------


@pytest.mark.parametrize("layout, angles", [
    ([[90, 45], [135, 0]], "polanalyser"),  # as polanalyser labels the IMX250MZR
    ([[90, 135], [45, 0]], "clockwise_on_screen"),  # the same sites in our names
])
def test_a_capture_declared_in_polanalysers_labels_reads_as_ours(sphere: Capture, layout: list, angles: str) -> None:
    data = sphere.spec.model_dump(mode="json")
    data["camera"]["mosaic"] = {"layout": layout, "angles": angles}
    declared = dataclasses.replace(sphere, spec=parse_capture_spec(data))
    assert declared.layout == sphere.layout
    a, b = preprocess_capture(declared, demosaic="superpixel"), preprocess_capture(sphere, demosaic="superpixel")
    assert torch.equal(a.stokes, b.stokes)
    (n0, m0), (n1, _) = _normals(sphere), _normals(declared)
    assert np.array_equal(np.nan_to_num(n0), np.nan_to_num(n1)) and m0.sum() > 400
    # the maker's labels read in OUR direction would be another mosaic: s2 flips sign
    data["camera"]["mosaic"] = {"layout": [[90, 45], [135, 0]], "angles": "clockwise_on_screen"}
    mirrored = preprocess_capture(dataclasses.replace(sphere, spec=parse_capture_spec(data)), demosaic="superpixel")
    torch.testing.assert_close(mirrored.stokes[:, 2], -b.stokes[:, 2])
