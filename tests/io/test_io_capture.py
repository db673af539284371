"""Tests of polarshape.io.capture: capture folders load/validate/write, lossless round trip."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
import yaml

from polarshape.imaging.mosaic import MosaicLayout
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import Capture, CaptureError, CaptureSpec, load_capture, write_capture
from polarshape.lights import DirectionalLight, PointLight

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"


def _spec(bit_depth: int = 12, k: int = 3, **camera: Any) -> CaptureSpec:
    dirs = [[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, -0.6, -0.8], [-0.6, 0.0, -0.8]]
    return CaptureSpec.model_validate(
        {
            "format": "polarshape-capture/1",
            "camera": {"model": "test", "projection": "orthographic", "bit_depth": bit_depth, **camera},
            "lights": [{"direction": dirs[i], "intensity": 1.0 + i, "frame": f"frames/{i:03d}.png"} for i in range(k)],
        }
    )


def _capture(bit_depth: int = 12, k: int = 3, h: int = 8, w: int = 12) -> Capture:
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 2**bit_depth, size=(k, h, w)).astype(np.uint16)
    mask = np.zeros((h // 2, w // 2), dtype=bool)
    mask[1:3, 2:5] = True
    normals = np.full((h // 2, w // 2, 3), np.nan, dtype=np.float32)
    normals[mask] = (0.0, 0.0, -1.0)
    gt = {"normals": normals, "depth": rng.random((h, w)), "scene": {"material": "x", "alpha": 0.2}}
    return Capture(spec=_spec(bit_depth, k), frames=frames, mask=mask, ground_truth=gt)


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    return write_capture(tmp_path / "cap", _capture())


def _edit_yaml(folder: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    path = folder / "capture.yaml"
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data))


def _assert_same(a: Capture, b: Capture) -> None:
    assert a.spec == b.spec
    assert a.frames.dtype == b.frames.dtype == np.uint16
    np.testing.assert_array_equal(a.frames, b.frames)
    assert (a.mask is None) == (b.mask is None)
    if a.mask is not None:
        np.testing.assert_array_equal(a.mask, b.mask)
    assert a.ground_truth.keys() == b.ground_truth.keys()
    for key, value in a.ground_truth.items():
        if isinstance(value, np.ndarray):
            assert value.dtype == b.ground_truth[key].dtype
            np.testing.assert_array_equal(value, b.ground_truth[key])
        else:
            assert value == b.ground_truth[key]


# --- round trip ---------------------------------------------------------------------------------


@pytest.mark.parametrize("bit_depth", [8, 10, 12, 16])
def test_round_trip_is_lossless(tmp_path: Path, bit_depth: int) -> None:
    original = _capture(bit_depth)
    loaded = load_capture(write_capture(tmp_path / "cap", original))
    _assert_same(original, loaded)
    assert loaded.root == (tmp_path / "cap").resolve()
    frame = cv2.imread(str(tmp_path / "cap" / "frames" / "000.png"), cv2.IMREAD_UNCHANGED)
    assert frame.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    # A second round trip from the loaded copy is identical too.
    _assert_same(loaded, load_capture(write_capture(tmp_path / "cap2", loaded)))


def test_round_trip_perspective_point_lights_tiff(tmp_path: Path) -> None:
    spec = CaptureSpec.model_validate(
        {
            "format": "polarshape-capture/1",
            "camera": {
                "projection": "perspective",
                "intrinsics": {"fx": 2500.0, "fy": 2500.5, "cx": 6.0, "cy": 4.0},
                "distortion": [0.1, -0.01, 0.0, 0.0, 0.001],
                "bit_depth": 12,
                "black_level": 64,
                "mosaic": {"layout": [[0, 45], [135, 90]], "angles": "clockwise_on_screen"},
            },
            "lights": [
                {"position": [0.1, -0.2, -0.5], "intensity": 2.0, "frame": "raw/a.tiff"},
                {"direction": [0.6, 0.0, -0.8], "frame": "raw/b.tif"},
            ],
        }
    )
    frames = np.random.default_rng(2).integers(0, 4096, size=(2, 4, 6)).astype(np.uint16)
    original = Capture(spec=spec, frames=frames)
    loaded = load_capture(write_capture(tmp_path / "cap", original) / "capture.yaml")
    _assert_same(original, loaded)
    assert loaded.layout == MosaicLayout(((0.0, 45.0), (135.0, 90.0)))
    lights = loaded.lights()
    assert isinstance(lights[0], PointLight) and isinstance(lights[1], DirectionalLight)
    d, e = lights.illuminate(torch.tensor([[0.1, -0.2, 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64))
    assert d.shape == (2, 2, 3) and e.shape == (2, 2)
    np.testing.assert_allclose(d[0, 0], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(d[1, 1], [0.6, 0.0, -0.8])
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    np.testing.assert_allclose(e[0, 0], 2.0)  # intensity 2 at 1 m
    np.testing.assert_allclose(e[1], 1.0)


def test_helpers(folder: Path) -> None:
    c = load_capture(folder)
    assert c.layout == MosaicLayout.imx250mzr()
    assert c.num_lights == 3 and c.bit_depth == 12
    np.testing.assert_allclose(c.lights()[1].direction, [0.6, 0.0, -0.8])
    np.testing.assert_allclose(c.lights().intensities(), [1.0, 2.0, 3.0])


def test_write_never_overwrites_silently(tmp_path: Path, folder: Path) -> None:
    with pytest.raises(OutputExistsError):
        write_capture(folder, _capture())
    write_capture(folder, _capture(k=2), overwrite=True)
    assert load_capture(folder).num_lights == 2
    assert sorted(p.name for p in folder.parent.iterdir()) == ["cap"]


def test_write_validates_before_writing(tmp_path: Path) -> None:
    bad = _capture()
    bad.frames[0, 0, 0] = 5000
    with pytest.raises(CaptureError, match="above 4095"):
        write_capture(tmp_path / "cap", bad)
    wrong_k = _capture()
    wrong_k.frames = wrong_k.frames[:2]
    with pytest.raises(CaptureError, match="2 frames for 3 lights"):
        write_capture(tmp_path / "cap", wrong_k)
    assert not any(tmp_path.iterdir())


def test_mask_at_mosaic_resolution_needs_all_four_sites(folder: Path) -> None:
    full = np.zeros((8, 12), dtype=np.uint8)
    full[2:4, 2:4] = 255  # whole super-pixel (1, 1)
    full[4, 6] = 255  # one site of super-pixel (2, 3)
    (folder / "mask.png").unlink()
    cv2.imwrite(str(folder / "mask.png"), full)
    mask = load_capture(folder).mask
    assert mask is not None and mask.shape == (4, 6)
    assert mask.sum() == 1 and mask[1, 1]


def test_capture_without_mask_and_ground_truth(tmp_path: Path) -> None:
    c = _capture()
    c.mask, c.ground_truth = None, {}
    loaded = load_capture(write_capture(tmp_path / "cap", c))
    assert loaded.mask is None and loaded.ground_truth == {}


# --- validation errors, one each ------------------------------------------------------------------


def test_missing_folder_and_yaml(tmp_path: Path, folder: Path) -> None:
    with pytest.raises(CaptureError, match="capture folder not found"):
        load_capture(tmp_path / "nope")
    (folder / "capture.yaml").unlink()
    with pytest.raises(CaptureError, match=r"capture\.yaml: not found"):
        load_capture(folder)


def test_invalid_yaml(folder: Path) -> None:
    (folder / "capture.yaml").write_text("format: [unclosed\n")
    with pytest.raises(CaptureError, match="not valid YAML"):
        load_capture(folder)


def test_missing_frame_file(folder: Path) -> None:
    (folder / "frames" / "001.png").unlink()
    with pytest.raises(CaptureError, match=r"001\.png.*lights\[1\]\.frame.*file not found"):
        load_capture(folder)


def test_unknown_field(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["camera"].update(exposure=10))
    with pytest.raises(CaptureError, match=r"camera\.exposure: Extra inputs are not permitted.*unknown field"):
        load_capture(folder)


def test_unknown_light_field_names_the_index(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][2].update(colour="red"))
    with pytest.raises(CaptureError, match=r"lights\[2\]\.colour"):
        load_capture(folder)


def test_wrong_field_values(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["camera"].update(projection="fisheye", bit_depth=14))
    with pytest.raises(CaptureError, match=r"camera\.projection.*\n.*camera\.bit_depth: must be one of"):
        load_capture(folder)


def test_wrong_format_version(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d.update(format="polarshape-capture/9"))
    with pytest.raises(CaptureError, match="this polarshape reads 'polarshape-capture/1'"):
        load_capture(folder)


def test_missing_required_field(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["camera"].pop("bit_depth"))
    with pytest.raises(CaptureError, match=r"camera\.bit_depth: Field required \(required field: add it\)"):
        load_capture(folder)


def test_perspective_needs_intrinsics(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["camera"].update(projection="perspective"))
    with pytest.raises(CaptureError, match=r"camera: camera\.intrinsics .* required when projection is perspective"):
        load_capture(folder)


def test_bad_intrinsics_and_distortion(folder: Path) -> None:
    def edit(d: dict[str, Any]) -> None:
        d["camera"].update(
            projection="perspective", intrinsics={"fx": -1, "fy": 1, "cx": 0, "cy": 0}, distortion=[0, 0, 0]
        )

    _edit_yaml(folder, edit)
    with pytest.raises(CaptureError, match=r"camera\.intrinsics\.fx: Input should be greater than 0[\s\S]*distortion"):
        load_capture(folder)


def test_light_direction_not_unit(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][1].update(direction=[0.6, 0.0, -0.9]))
    with pytest.raises(CaptureError, match=r"lights\[1\]\.direction: must be a unit vector"):
        load_capture(folder)


def test_light_behind_the_object(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][2].update(direction=[0.0, -0.6, 0.8]))
    with pytest.raises(CaptureError, match=r"lights\[2\]\.direction: z = 0\.8 must be < 0, or 0 for a grazing light: .*z > 0 puts it behind"):
        load_capture(folder)


def test_a_grazing_light_is_allowed(folder: Path) -> None:
    """z = 0: the light lies in the plane through the object square to the view axis; it still
    lights the object's sides (only z > 0 is behind it)."""
    _edit_yaml(folder, lambda d: d["lights"][2].update(direction=[0.0, -1.0, 0.0]))
    assert load_capture(folder).lights()[2].direction == (0.0, -1.0, 0.0)


def test_light_needs_exactly_one_of_direction_position(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][0].update(position=[0.0, 0.0, -1.0]))
    with pytest.raises(CaptureError, match=r"lights\[0\]: give exactly one of direction .* or position"):
        load_capture(folder)


def test_mosaic_layout_must_be_a_permutation(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["camera"].update(mosaic={"layout": [[90, 45], [45, 0]]}))
    with pytest.raises(CaptureError, match=r"camera\.mosaic\.layout: must hold the polariser angles"):
        load_capture(folder)


def test_frames_of_different_sizes(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "002.png"), np.zeros((8, 10), np.uint16))
    with pytest.raises(CaptureError, match=r"002\.png \(lights\[2\]\.frame\): is 10×8 .* same size"):
        load_capture(folder)


def test_odd_frame_size(tmp_path: Path, folder: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(folder / "frames" / f"{i:03d}.png"), np.zeros((7, 12), np.uint16))
    with pytest.raises(CaptureError, match="even width and height"):
        load_capture(folder)


def test_counts_above_bit_depth(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "001.png"), np.full((8, 12), 4096, np.uint16))
    with pytest.raises(CaptureError, match=r"001\.png.*up to 4096, above 4095.*shift them right by 4"):
        load_capture(folder)


def test_8bit_png_for_12bit_camera(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "000.png"), np.zeros((8, 12), np.uint8))
    with pytest.raises(CaptureError, match=r"000\.png.*8-bit image but camera\.bit_depth is 12.*16-bit"):
        load_capture(folder)


def test_colour_frame(folder: Path) -> None:
    cv2.imwrite(str(folder / "frames" / "000.png"), np.zeros((8, 12, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"000\.png.*single-channel.*lights\[0\]\.frame"):
        load_capture(folder)


def test_mask_of_the_wrong_size(folder: Path) -> None:
    (folder / "mask.png").unlink()
    cv2.imwrite(str(folder / "mask.png"), np.zeros((5, 5), np.uint8))
    with pytest.raises(CaptureError, match=r"mask\.png: mask is 5×5.*mosaic resolution \(12×8\).*super-pixel"):
        load_capture(folder)


def test_normals_of_the_wrong_size(folder: Path) -> None:
    (folder / "ground_truth" / "normals.npy").unlink()
    np.save(folder / "ground_truth" / "normals.npy", np.zeros((3, 3, 3)))
    with pytest.raises(CaptureError, match=r"normals\.npy: normals must be"):
        load_capture(folder)


def test_duplicate_frames(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][2].update(frame="frames/000.png"))
    with pytest.raises(CaptureError, match=r"lights\[2\]\.frame 'frames/000\.png' is also the frame of lights\[0\]"):
        load_capture(folder)


def test_frame_path_must_stay_inside(folder: Path) -> None:
    _edit_yaml(folder, lambda d: d["lights"][0].update(frame="../elsewhere/000.png"))
    with pytest.raises(CaptureError, match=r"lights\[0\]\.frame: must be a relative path inside"):
        load_capture(folder)


# --- the shared real captures ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "k", "hw", "bit_depth"),
    [("mitsuba_sphere_a020", 13, (512, 512), 12), ("official_sphere128", 12, (256, 256), 16)],
)
def test_shared_captures(tmp_path: Path, name: str, k: int, hw: tuple[int, int], bit_depth: int) -> None:
    folder = SHARED / "data" / name
    if not (folder / "capture.yaml").is_file():
        pytest.skip(f"shared data not found at {folder}")
    c = load_capture(folder)
    assert c.frames.shape == (k, *hw) and c.frames.dtype == np.uint16
    assert c.bit_depth == bit_depth and c.layout == MosaicLayout.imx250mzr()
    assert c.mask is not None and c.mask.shape == (hw[0] // 2, hw[1] // 2) and 0 < c.mask.sum() < c.mask.size
    normals = c.ground_truth["normals"]
    assert normals.shape == (hw[0] // 2, hw[1] // 2, 3)
    inside = np.isfinite(normals).all(-1) & (np.linalg.norm(np.nan_to_num(normals), axis=-1) > 0.5)
    assert (normals[inside][:, 2] < 0).all()  # facing the camera: N_z < 0
    d, _ = c.lights().illuminate(torch.zeros(3, dtype=torch.float64))  # (K, 3): directional lights
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    assert (d[:, 2] < 0).all()
    # Copying the whole folder through write_capture keeps every bit.
    copy = load_capture(write_capture(tmp_path / name, c))
    _assert_same(c, copy)
    shutil.rmtree(tmp_path / name)


def test_overwrite_replaces_only_a_capture(tmp_path: Path) -> None:
    """``write_capture(..., overwrite=True)`` replaces a previous capture or an empty folder, never a
    folder of something else (e.g. the one holding the scene file being simulated)."""
    capture = load_capture(write_capture(tmp_path / "cap", _capture()))
    write_capture(tmp_path / "cap", capture, overwrite=True)  # a capture: replaced
    (tmp_path / "empty").mkdir()
    write_capture(tmp_path / "empty", capture, overwrite=True)
    other = tmp_path / "scenes"
    other.mkdir()
    (other / "scene.yaml").write_text("keep me")
    with pytest.raises(OutputExistsError, match="not a capture .*overwrite only replaces captures"):
        write_capture(other, capture, overwrite=True)
    assert (other / "scene.yaml").read_text() == "keep me" and not (other / "capture.yaml").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputExistsError, match="this file is not a capture"):
        write_capture(tmp_path / "file", capture, overwrite=True)
