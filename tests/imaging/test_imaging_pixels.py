"""Tests of polarshape.imaging.pixels: counts <-> floats, masks, bit-depth validation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarshape.errors import ShapeError
from polarshape.imaging.pixels import (
    check_bit_depth,
    left_shift_of,
    counts_to_float,
    dark_mask,
    float_to_counts,
    max_count,
    reduce_mask_to_superpixels,
    saturation_mask,
)


@pytest.mark.parametrize("bit_depth", [8, 10, 12, 16])
def test_counts_round_trip_every_code(bit_depth: int) -> None:
    top = max_count(bit_depth)
    raw = np.arange(top + 1, dtype=np.uint8 if bit_depth == 8 else np.uint16)
    x = counts_to_float(raw, bit_depth, dtype=torch.float64)
    assert float(x[0]) == 0.0 and float(x[-1]) == 1.0
    back = float_to_counts(x, bit_depth)
    assert back.dtype == (np.uint8 if bit_depth == 8 else np.uint16)
    np.testing.assert_array_equal(back, raw)


def test_black_level_subtracted_and_restored() -> None:
    raw = np.array([[64, 100], [4095, 10]], dtype=np.uint16)
    x = counts_to_float(raw, 12, black_level=64, dtype=torch.float64)
    np.testing.assert_allclose(x.numpy(), (raw.astype(float) - 64) / (4095 - 64))
    assert float(x[1, 1]) < 0  # below black: kept negative, not clipped
    np.testing.assert_array_equal(float_to_counts(x, 12, black_level=64), raw)


def test_counts_to_float_accepts_torch_and_keeps_device() -> None:
    raw = torch.tensor([[0, 1023]], dtype=torch.int32)
    x = counts_to_float(raw, 10)
    assert x.dtype == torch.float32 and x.device == raw.device
    torch.testing.assert_close(x, torch.tensor([[0.0, 1.0]]))


def test_float_to_counts_rounds_and_clips() -> None:
    out = float_to_counts(np.array([-0.5, 0.49 / 255, 0.51 / 255, 1.7, np.nan]), 8)
    np.testing.assert_array_equal(out, [0, 0, 1, 255, 0])
    assert out.dtype == np.uint8


def test_counts_above_bit_depth_rejected() -> None:
    with pytest.raises(ValueError, match=r"shift right by 4"):
        counts_to_float(np.array([4096], dtype=np.uint16), 12)


@pytest.mark.parametrize("bad", [7, 14, 32, 12.0, "12", True, None])
def test_bit_depth_validation(bad: object) -> None:
    with pytest.raises(ValueError, match=r"bit_depth must be one of \(8, 10, 12, 16\)"):
        check_bit_depth(bad)


def test_invalid_arguments() -> None:
    with pytest.raises(ValueError, match="black_level"):
        counts_to_float(np.zeros(2, np.uint16), 12, black_level=4095)
    with pytest.raises(TypeError, match="integer sensor counts"):
        counts_to_float(np.zeros(2, np.float32), 12)
    with pytest.raises(ValueError, match="margin"):
        saturation_mask(np.zeros(2, np.uint16), 12, margin=-1)
    with pytest.raises(ValueError, match="threshold"):
        dark_mask(np.zeros(2, np.uint16), 12, threshold=1.5)


def test_saturation_and_dark_masks() -> None:
    raw = np.array([[4095, 4090], [70, 200]], dtype=np.uint16)
    np.testing.assert_array_equal(saturation_mask(raw, 12), [[True, False], [False, False]])
    np.testing.assert_array_equal(saturation_mask(raw, 12, margin=5), [[True, True], [False, False]])
    # 2 % of (4095 - 64) = 80.6 counts above black.
    np.testing.assert_array_equal(dark_mask(raw, 12, black_level=64, threshold=0.02), [[False, False], [True, False]])
    t = saturation_mask(torch.from_numpy(raw.astype(np.int32)), 12)
    assert isinstance(t, torch.Tensor) and t.dtype == torch.bool


def test_superpixel_reduction_any_and_all() -> None:
    mask = np.zeros((4, 6), dtype=bool)
    mask[0, 1] = True  # one site of super-pixel (0, 0)
    mask[2:4, 4:6] = True  # all sites of super-pixel (1, 2)
    np.testing.assert_array_equal(reduce_mask_to_superpixels(mask, "any"), [[True, False, False], [False, False, True]])
    np.testing.assert_array_equal(
        reduce_mask_to_superpixels(mask, "all"), [[False, False, False], [False, False, True]]
    )
    t = reduce_mask_to_superpixels(torch.from_numpy(mask)[None], "any")
    assert t.shape == (1, 2, 3) and bool(t[0, 0, 0])
    with pytest.raises(ShapeError, match=r"mask must have shape \(\*, 2H, 2W\) with even sizes; got \(3, 4\)"):
        reduce_mask_to_superpixels(np.zeros((3, 4), bool))


def test_saturated_superpixel_flags_whole_block() -> None:
    raw = np.full((4, 4), 1000, dtype=np.uint16)
    raw[3, 2] = 4095
    sat = reduce_mask_to_superpixels(saturation_mask(raw, 12), "any")
    np.testing.assert_array_equal(sat, [[False, False], [False, True]])


@pytest.mark.parametrize("black_level", [0.0, 64.0, 100.25, 100.3])
def test_counts_to_float_float32_is_the_rounded_float64_result_without_an_int64_copy(black_level: float) -> None:
    """Every 16-bit code: float32 equals the float64 result rounded once (computed in float32 when
    exact), and the conversion holds no 8-byte-per-pixel copy of the counts (numpy allocations are
    traced; the old int64 copy alone was 8 bytes per pixel)."""
    import tracemalloc

    raw = np.tile(np.arange(65536, dtype=np.uint16), 8)  # (524288,)
    expected = ((raw.astype(np.float64) - black_level) / (65535 - black_level)).astype(np.float32)
    tracemalloc.start()
    try:
        x = counts_to_float(raw, 16, black_level, dtype=torch.float32)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(x.numpy(), expected)
    np.testing.assert_array_equal(counts_to_float(torch.from_numpy(raw.astype(np.int32)), 16, black_level).numpy(), expected)
    per_pixel = 8 if black_level == 100.3 else 4  # not exact in float32: float64 first
    assert peak < (per_pixel + 0.5) * raw.size


def test_left_shift_is_found_over_all_frames() -> None:
    rng = np.random.default_rng(5)
    twelve = rng.integers(0, 4096, size=(2, 16, 16), dtype=np.uint16) << 4
    assert left_shift_of(twelve) == 4 and left_shift_of(list(twelve)) == 4
    assert left_shift_of(twelve >> 4) == 0  # low-bit aligned: the largest count stays <= 4095
    odd = twelve.copy()
    odd[1, 5, 7] |= 1
    assert left_shift_of(odd) == 0 and left_shift_of([twelve[0], odd[1]]) == 0
    assert left_shift_of(np.full((4, 4), 65520, np.uint16)) == 0  # flat: cannot tell
