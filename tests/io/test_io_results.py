"""Result folder files: the material map of an object of several materials."""

from __future__ import annotations

import cv2
import numpy as np

from polarshape.io.images import read_image
from polarshape.io.results import MATERIAL_COLOURS, write_material_maps


def test_material_maps_are_written_as_index_and_colours(tmp_path):
    materials = np.full((4, 5), -1, dtype=np.int64)
    materials[1:3, 1:3] = 0
    materials[1:3, 3:5] = 1
    mixed = np.zeros((4, 5), dtype=bool)
    mixed[1:3, 2:4] = True
    write_material_maps(tmp_path, materials=materials, mixed=mixed)
    index = np.load(tmp_path / "materials.npy")
    assert index.dtype == np.int16 and np.array_equal(index, materials)
    rgb = cv2.imread(str(tmp_path / "materials.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]  # OpenCV reads BGR
    assert rgb.shape == (4, 5, 3)
    assert tuple(rgb[1, 1]) == MATERIAL_COLOURS[0] and tuple(rgb[1, 4]) == MATERIAL_COLOURS[1]
    assert not rgb[0].any()  # black outside the mask
    assert np.array_equal(read_image(tmp_path / "mixed.png") > 0, mixed)
