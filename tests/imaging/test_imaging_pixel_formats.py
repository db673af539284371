"""Bit-exact packing and unpacking of the polarisation pixel formats."""

from __future__ import annotations

import numpy as np
import pytest

from polarshape.imaging.pixel_formats import format_name_of, pack_mosaic, payload_size, unpack_mosaic
from polarshape.imaging.pixels import (
    COLOUR_PIXEL_FORMATS,
    MONO_PIXEL_FORMATS,
    PIXEL_FORMATS,
    bayer_of,
    bit_depth_of,
)

FORMATS = sorted(PIXEL_FORMATS)


def _random_mosaic(pixel_format: str, height: int, width: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    top = (1 << bit_depth_of(pixel_format)) - 1
    img = rng.integers(0, top + 1, size=(height, width), dtype=np.uint16)
    img.flat[0] = top  # make sure the extremes are exercised
    img.flat[-1] = 0
    return img


@pytest.mark.parametrize("pixel_format", FORMATS)
@pytest.mark.parametrize("shape", [(4, 6), (3, 5), (1, 1), (64, 48)])
def test_round_trip_is_bit_exact(pixel_format: str, shape: tuple[int, int]) -> None:
    img = _random_mosaic(pixel_format, *shape)
    data = pack_mosaic(img, pixel_format)
    assert len(data) == payload_size(pixel_format, shape[1], shape[0])
    back = unpack_mosaic(data, pixel_format, width=shape[1], height=shape[0])
    assert back.dtype == np.uint16 and back.shape == shape
    np.testing.assert_array_equal(back, img)


@pytest.mark.parametrize("pixel_format", FORMATS)
def test_bytes_round_trip_is_bit_exact(pixel_format: str) -> None:
    # every byte sequence of an even pixel count is a valid payload (except 12-bit-in-16 whose
    # high nibble must be zero): unpack then pack must give the same bytes back
    rng = np.random.default_rng(1)
    w, h = 8, 4
    data = rng.integers(0, 256, size=payload_size(pixel_format, w, h), dtype=np.uint8)
    if pixel_format in ("PolarizeMono12", "BayerRG12"):  # 12 significant bits in two bytes
        data[1::2] &= 0x0F
    img = unpack_mosaic(data.tobytes(), pixel_format, width=w, height=h)
    assert pack_mosaic(img, pixel_format) == data.tobytes()


def test_known_layouts() -> None:
    img = np.array([[0x123, 0xABC]], dtype=np.uint16)
    assert pack_mosaic(img, "PolarizeMono12p") == bytes([0x23, 0xC1, 0xAB])
    assert pack_mosaic(img, "PolarizeMono12Packed") == bytes([0x12, 0xC3, 0xAB])
    assert pack_mosaic(img, "PolarizeMono12") == bytes([0x23, 0x01, 0xBC, 0x0A])
    assert pack_mosaic(np.array([[0xBEEF]], dtype=np.uint16), "PolarizeMono16") == bytes([0xEF, 0xBE])
    assert pack_mosaic(np.array([[7, 255]], dtype=np.uint16), "PolarizeMono8") == bytes([7, 255])
    # odd pixel counts: the stream is padded to whole bytes
    assert pack_mosaic(np.array([[0x123]], dtype=np.uint16), "PolarizeMono12p") == bytes([0x23, 0x01])
    assert pack_mosaic(np.array([[0x123]], dtype=np.uint16), "PolarizeMono12Packed") == bytes([0x12, 0x03])


def test_payload_sizes_match_the_pfnc_bits_per_pixel() -> None:
    for name, (code, _) in PIXEL_FORMATS.items():
        bpp = (code >> 16) & 0xFF  # what a GigE Vision device announces
        assert payload_size(name, 2448, 2048) == 2448 * 2048 * bpp // 8
        assert format_name_of(code) == name


def test_invalid_input_is_rejected_with_a_clear_message() -> None:
    with pytest.raises(ValueError, match="pixel_format 'Mono8'"):
        pack_mosaic(np.zeros((2, 2), np.uint16), "Mono8")
    with pytest.raises(ValueError, match=r"\[0, 4095\]"):
        pack_mosaic(np.full((2, 2), 4096, np.uint16), "PolarizeMono12p")
    with pytest.raises(ValueError, match=r"shape \(H, W\)"):
        pack_mosaic(np.zeros(4, np.uint16), "PolarizeMono8")
    with pytest.raises(ValueError, match="needs 6 bytes"):
        unpack_mosaic(b"\x00" * 5, "PolarizeMono12p", width=2, height=2)
    with pytest.raises(ValueError, match="not low-bit aligned"):
        unpack_mosaic(b"\xff\xff", "PolarizeMono12", width=1, height=1)
    with pytest.raises(ValueError, match="0x01080001"):
        format_name_of(0x01080001)


# -- the colour polarisation sensor (IMX250MYR, Lucid TRI050S-QC): raw BayerRG formats ------------


def test_colour_formats_have_the_pfnc_codes_and_the_mono_layouts() -> None:
    """BayerRG* carry the raw 4x4 super-block mosaic with the same bytes as the PolarizeMono format of
    the same suffix; their codes are PFNC's (as Aravis' ARV_PIXEL_FORMAT_BAYER_RG_* and Arena's PFNC.h)."""
    assert {name: code for name, (code, _) in COLOUR_PIXEL_FORMATS.items()} == {
        "BayerRG8": 0x01080009, "BayerRG12p": 0x010C0059, "BayerRG12Packed": 0x010C002B,
        "BayerRG12": 0x01100011, "BayerRG16": 0x0110002F,
    }
    img = _random_mosaic("BayerRG12p", 8, 12, seed=3)
    for colour, mono in zip(COLOUR_PIXEL_FORMATS, MONO_PIXEL_FORMATS, strict=True):
        assert bit_depth_of(colour) == bit_depth_of(mono)
        counts = img >> (12 - bit_depth_of(colour)) if bit_depth_of(colour) < 12 else img
        assert pack_mosaic(counts, colour) == pack_mosaic(counts, mono)
    assert pack_mosaic(np.array([[0x123, 0xABC]], np.uint16), "BayerRG12p") == bytes([0x23, 0xC1, 0xAB])
    assert pack_mosaic(np.array([[0x123, 0xABC]], np.uint16), "BayerRG12Packed") == bytes([0x12, 0xC3, 0xAB])
    with pytest.raises(ValueError, match="BayerRG16"):
        unpack_mosaic(b"\xff\xff", "BayerRG12", width=1, height=1)


def test_which_formats_are_colour() -> None:
    assert {name: bayer_of(name) for name in PIXEL_FORMATS} == {
        **{name: None for name in MONO_PIXEL_FORMATS}, **{name: "RGGB" for name in COLOUR_PIXEL_FORMATS}}
    with pytest.raises(ValueError, match="BayerGR8"):
        bayer_of("BayerGR8")  # not a format of the TRI050S-QC: refused, not guessed


def test_full_colour_frame_round_trip_is_bit_exact() -> None:
    """A full 2448x2048 IMX250MYR mosaic through every colour format, bytes and counts."""
    for name in COLOUR_PIXEL_FORMATS:
        img = _random_mosaic(name, 2048, 2448, seed=5)
        data = pack_mosaic(img, name)
        assert len(data) == payload_size(name, 2448, 2048)
        np.testing.assert_array_equal(unpack_mosaic(data, name, width=2448, height=2048), img)
