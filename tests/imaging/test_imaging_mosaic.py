"""Tests of polarshape.imaging.mosaic: layouts (maker <-> our convention, ROI shifts), (un)mosaicking."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from polarshape.errors import ShapeError
from polarshape.imaging.mosaic import (
    MAKER_ANGLES,
    MosaicLayout,
    channel_angles_rad,
    mosaic_from_intensities,
    mosaic_from_stokes,
    our_angle_deg,
    split_mosaic,
)
from polarshape.imaging.stokes import intensities_from_stokes

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
ALL_LAYOUTS = [MosaicLayout(((p[0], p[1]), (p[2], p[3]))) for p in itertools.permutations((0.0, 45.0, 90.0, 135.0))]


def test_imx250mzr_default_is_spec_block() -> None:
    layout = MosaicLayout.imx250mzr()
    assert layout.angles_deg == ((90.0, 135.0), (45.0, 0.0))
    assert layout == MosaicLayout.from_maker([[90, 45], [135, 0]], "counterclockwise_on_screen")
    assert layout.to_maker("counterclockwise_on_screen") == ((90.0, 45.0), (135.0, 0.0))


def test_from_maker_directions() -> None:
    maker = [[0, 45], [135, 90]]
    assert MosaicLayout.from_maker(maker, "clockwise_on_screen").angles_deg == ((0.0, 45.0), (135.0, 90.0))
    assert MosaicLayout.from_maker(maker, "counterclockwise_on_screen").angles_deg == ((0.0, 135.0), (45.0, 90.0))
    with pytest.raises(ValueError, match="counterclockwise_on_screen"):
        MosaicLayout.from_maker(maker, "ccw")  # type: ignore[arg-type]


@pytest.mark.parametrize("layout", ALL_LAYOUTS[:6])
@pytest.mark.parametrize("angles", ["counterclockwise_on_screen", "clockwise_on_screen"])
def test_to_maker_inverts_from_maker(layout: MosaicLayout, angles: str) -> None:
    assert MosaicLayout.from_maker(layout.to_maker(angles), angles) == layout  # type: ignore[arg-type]


def test_invalid_layouts_rejected() -> None:
    with pytest.raises(ValueError, match="0, 45, 90, 135"):
        MosaicLayout(((0.0, 45.0), (90.0, 90.0)))
    with pytest.raises(ValueError, match="2×2"):
        MosaicLayout.from_maker([[0, 45, 90], [135, 0, 0]])
    with pytest.raises(ValueError, match="2×2"):
        MosaicLayout.from_maker("0 45 90 135")  # type: ignore[arg-type]


def test_angles_normalised_modulo_180() -> None:
    assert MosaicLayout(((180.0, -135.0), (-90.0, 315.0))).angles_deg == ((0.0, 45.0), (90.0, 135.0))


def test_shifted_matches_cropping_the_sensor() -> None:
    layout = MosaicLayout.imx250mzr()
    sensor = mosaic_from_intensities(torch.arange(4.0).view(4, 1, 1).expand(4, 3, 3), layout)  # value = channel
    for ox, oy in itertools.product(range(4), range(4)):
        roi = sensor[oy:, ox:]
        shifted = layout.shifted(ox, oy)
        for i, j in itertools.product(range(2), range(2)):
            assert int(roi[i, j]) == shifted.channel_of_site(i, j)
    assert layout.shifted(2, 2) == layout
    assert layout.shifted(1, 0).angles_deg == ((135.0, 90.0), (0.0, 45.0))
    with pytest.raises(ValueError, match="offset_x"):
        layout.shifted(-1, 0)


def test_angles_rad_site_order() -> None:
    a = MosaicLayout.imx250mzr().angles_rad(dtype=torch.float64)
    torch.testing.assert_close(a, torch.tensor([90.0, 135.0, 45.0, 0.0], dtype=torch.float64).deg2rad())


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("layout", ALL_LAYOUTS)
def test_split_inverts_mosaic(layout: MosaicLayout, device: str) -> None:
    i = torch.rand(2, 4, 3, 5, device=device)
    m = mosaic_from_intensities(i, layout)
    assert m.shape == (2, 6, 10)
    torch.testing.assert_close(split_mosaic(m, layout), i, rtol=0, atol=0)
    # Each site holds the channel whose angle the layout puts there.
    for si, sj in itertools.product(range(2), range(2)):
        c = round(layout.angles_deg[si][sj] / 45)
        torch.testing.assert_close(m[:, si::2, sj::2], i[:, c], rtol=0, atol=0)


def test_mosaic_from_stokes_is_malus_per_site() -> None:
    s = torch.tensor([1.0, 0.2, -0.4], dtype=torch.float64).view(3, 1, 1)
    layout = MosaicLayout.imx250mzr()
    m = mosaic_from_stokes(s, layout)
    for si, sj in itertools.product(range(2), range(2)):
        theta = math.radians(layout.angles_deg[si][sj])
        assert float(m[si, sj]) == pytest.approx(0.5 * (1.0 + 0.2 * math.cos(2 * theta) - 0.4 * math.sin(2 * theta)))
    ints = intensities_from_stokes(s, channel_angles_rad(dtype=torch.float64))
    torch.testing.assert_close(split_mosaic(m, layout), ints)


def test_split_rejects_odd_sizes_and_bad_layout() -> None:
    with pytest.raises(ShapeError, match=r"mosaic must have shape \(\*, 2H, 2W\) with even.*; got \(5, 4\)"):
        split_mosaic(torch.zeros(5, 4), MosaicLayout.imx250mzr())
    with pytest.raises(ShapeError, match=r"non-zero.*; got \(0, 4\)"):
        split_mosaic(torch.zeros(0, 4), MosaicLayout.imx250mzr())
    with pytest.raises(TypeError, match="MosaicLayout"):
        split_mosaic(torch.zeros(4, 4), ((90, 135), (45, 0)))  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match=r"intensities must have shape \(\*, 4, H, W\)"):
        mosaic_from_intensities(torch.zeros(3, 2, 2), MosaicLayout.imx250mzr())


# --- polanalyser's labels -------------------------------------------------------------------------


def test_our_angle_of_a_label_in_each_convention() -> None:
    assert MAKER_ANGLES == ("counterclockwise_on_screen", "clockwise_on_screen", "polanalyser")
    assert [our_angle_deg(a, "clockwise_on_screen") for a in (0, 45, 90, 135)] == [0.0, 45.0, 90.0, 135.0]
    for angles in ("counterclockwise_on_screen", "polanalyser"):
        assert [our_angle_deg(a, angles) for a in (0, 45, 90, 135)] == [0.0, 135.0, 90.0, 45.0]  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="polanalyser"):
        our_angle_deg(45, "pa")  # type: ignore[arg-type]


def test_polanalyser_labels_are_the_makers() -> None:
    imx = [[90, 45], [135, 0]]
    assert MosaicLayout.from_maker(imx, "polanalyser") == MosaicLayout.imx250mzr()
    assert MosaicLayout.from_maker(imx, "polanalyser") == MosaicLayout.from_maker([[90, 135], [45, 0]],
                                                                                  "clockwise_on_screen")
    assert MosaicLayout.imx250mzr().to_maker("polanalyser") == ((90.0, 45.0), (135.0, 0.0))


def test_polanalyser_stokes_and_aolp_against_ours() -> None:
    """polanalyser on an IMX250MZR mosaic (its documented sites, written out here: 0° at (1, 1), 45° at
    (0, 1), 90° at (0, 0), 135° at (1, 0); S1 = I0 − I90, S2 = I45 − I135, AoLP = ½ atan2(S2, S1)
    mod π) against our Stokes: S1 the same, S2 = −s2, DoLP the same, AoLP = π − ours (mod π)."""
    s = torch.tensor([[1.0, 0.8], [0.6, 0.5]], dtype=torch.float64)  # (2, 2) s0
    lin = torch.tensor([[[0.3, -0.1], [0.05, 0.0]], [[0.2, 0.25], [-0.3, 0.1]]], dtype=torch.float64)  # (2, 2, 2)
    stokes = torch.cat([s[None], lin])  # (3, 2, 2): ours
    raw = mosaic_from_stokes(stokes, MosaicLayout.imx250mzr())  # (4, 4)
    i000, i045, i090, i135 = raw[1::2, 1::2], raw[0::2, 1::2], raw[0::2, 0::2], raw[1::2, 0::2]
    s1_pa, s2_pa = i000 - i090, i045 - i135
    torch.testing.assert_close(s1_pa, stokes[1])
    torch.testing.assert_close(s2_pa, -stokes[2])
    aolp_pa = torch.remainder(0.5 * torch.atan2(s2_pa, s1_pa), math.pi)
    aolp = torch.remainder(0.5 * torch.atan2(stokes[2], stokes[1]), math.pi)
    # AoLP_pa = π − AoLP (mod π): the same cos 2φ, the opposite sin 2φ
    torch.testing.assert_close(torch.cos(2 * aolp_pa), torch.cos(2 * aolp))
    torch.testing.assert_close(torch.sin(2 * aolp_pa), -torch.sin(2 * aolp))
    assert not torch.allclose(aolp_pa, aolp)
    # the four images, labelled as polanalyser labels them, are the polarisers at our −label
    ours = split_mosaic(raw, MosaicLayout.imx250mzr())  # (4, 2, 2) at our 0, 45, 90, 135
    for label, image in zip((0, 45, 90, 135), (i000, i045, i090, i135)):
        torch.testing.assert_close(image, ours[round(our_angle_deg(label, "polanalyser") / 45)])
