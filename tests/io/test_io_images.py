"""Tests of polarshape.io.images: lossless 8/16-bit PNG/TIFF, atomic, clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from polarshape.io.atomic import OutputExistsError
from polarshape.io.images import ImageError, read_image, write_image


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_lossless_round_trip(tmp_path: Path, suffix: str, dtype: type) -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, np.iinfo(dtype).max + 1, size=(6, 10), dtype=dtype)
    path = write_image(tmp_path / f"frame{suffix}", image)
    back = read_image(path)
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image)
    assert [p.name for p in tmp_path.iterdir()] == [f"frame{suffix}"]  # no temporary left behind


def test_no_overwrite_unless_asked(tmp_path: Path) -> None:
    path = tmp_path / "a.png"
    write_image(path, np.zeros((2, 2), np.uint8))
    with pytest.raises(OutputExistsError):
        write_image(path, np.ones((2, 2), np.uint8))
    assert read_image(path).max() == 0
    write_image(path, np.ones((2, 2), np.uint8), overwrite=True)
    assert read_image(path).max() == 1


def test_write_rejects_bad_arrays(tmp_path: Path) -> None:
    with pytest.raises(ImageError, match="uint8 or uint16"):
        write_image(tmp_path / "a.png", np.zeros((2, 2), np.float32))
    with pytest.raises(ImageError, match="uint8 or uint16"):
        write_image(tmp_path / "a.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ImageError, match="unsupported image type"):
        write_image(tmp_path / "a.jpg", np.zeros((2, 2), np.uint8))
    assert not any(tmp_path.iterdir())


def test_read_errors(tmp_path: Path) -> None:
    with pytest.raises(ImageError, match="not found"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ImageError, match="cannot be decoded"):
        read_image(tmp_path / "junk.png")
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(ImageError, match="single-channel"):
        read_image(tmp_path / "rgb.png")
    cv2.imwrite(str(tmp_path / "float.tiff"), np.zeros((2, 2), np.float32))
    with pytest.raises(ImageError, match="8-bit or 16-bit"):
        read_image(tmp_path / "float.tiff")
