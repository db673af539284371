"""The 2×2 polariser mosaic of a division-of-focal-plane sensor: layouts, mosaicking and splitting.

A raw mosaic of size (2H, 2W) holds H×W super-pixels; the site (i, j) ∈ {0, 1}² of a super-pixel
(row parity i, column parity j) sits behind a polariser at the angle the layout gives it.
Angles are in OUR convention (spec fmbrdf.md §1): in the image plane, from image x (right) toward
image y (down). Makers label the IMX250MZR filters counter-clockwise as seen on screen,
[[90, 45], [135, 0]]; a maker's angle a is our angle −a (mod 180°), i.e. [[90, 135], [45, 0]].

Conventions a label can be given in (:data:`MAKER_ANGLES`, ``camera.mosaic.angles``):

- ``clockwise_on_screen`` — ours: from image x toward image y (down); label a = our angle a;
- ``counterclockwise_on_screen`` — the sensor makers': from image x toward image *up*; label a =
  our angle −a (mod 180°);
- ``polanalyser`` — the angles as the polanalyser library labels them: its
  ``demosaicing(raw, COLOR_PolarMono)`` returns ``[img_000, img_045, img_090, img_135]`` taken from
  the IMX250MZR sites (row, column) (1, 1), (0, 1), (0, 0), (1, 0) — the maker's labels — and its
  ``calcStokes`` / ``cvtStokesToAoLP`` use them as angles from x, so its angles run
  counter-clockwise on screen: the same as ``counterclockwise_on_screen`` (label a = our −a).
  Hence, for the same pixels: ``S0_pa = s0``, ``S1_pa = s1``, ``S2_pa = −s2``, ``DoLP_pa = DoLP``,
  ``AoLP_pa = (π − AoLP) mod π`` (its AoLP is ours mirrored about image x).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from polarshape.checks import check_dtype_floating, check_shape, check_tensor, format_shape
from polarshape.errors import ShapeError
from polarshape.imaging.stokes import intensities_from_stokes

__all__ = [
    "CHANNEL_ANGLES_DEG",
    "MAKER_ANGLES",
    "MakerAngles",
    "MosaicLayout",
    "channel_angles_rad",
    "check_layout",
    "check_mosaic_shape",
    "mosaic_from_intensities",
    "mosaic_from_stokes",
    "our_angle_deg",
    "split_mosaic",
]

#: Polariser angles (degrees, our convention) of the four channels of a ``(*, 4, H, W)`` stack.
CHANNEL_ANGLES_DEG: tuple[float, float, float, float] = (0.0, 45.0, 90.0, 135.0)

#: Conventions of polariser angle labels (module docstring): the maker's, ours, polanalyser's.
MakerAngles = Literal["counterclockwise_on_screen", "clockwise_on_screen", "polanalyser"]
MAKER_ANGLES: tuple[str, ...] = ("counterclockwise_on_screen", "clockwise_on_screen", "polanalyser")

Angles2x2 = tuple[tuple[float, float], tuple[float, float]]


def channel_angles_rad(device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
    """(4,) angles of the channels 0°, 45°, 90°, 135° in radians (our convention)."""
    return torch.tensor([math.radians(a) for a in CHANNEL_ANGLES_DEG], device=device, dtype=dtype)


def _as_2x2(layout: object, name: str) -> Angles2x2:
    try:
        rows = [list(row) for row in layout]  # type: ignore[attr-defined]
        ok = len(rows) == 2 and all(len(row) == 2 for row in rows)
        values = [[float(v) for v in row] for row in rows] if ok else []
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(
            f"{name} must be a 2×2 nested list of angles in degrees, top row then bottom row, "
            f"e.g. [[90, 45], [135, 0]]; got {layout!r}"
        )
    return ((values[0][0], values[0][1]), (values[1][0], values[1][1]))


def _normalise_deg(a: float) -> float:
    a = a % 180.0
    if math.isclose(a, 180.0, abs_tol=1e-9):
        a = 0.0
    return a + 0.0  # turn -0.0 into 0.0


def _label_sign(angles: str) -> float:
    """+1 for labels measured as ours (x toward y down), −1 for counter-clockwise on screen."""
    if angles not in MAKER_ANGLES:
        raise ValueError(f"mosaic angles must be one of {MAKER_ANGLES}; got {angles!r}")
    return 1.0 if angles == "clockwise_on_screen" else -1.0


def our_angle_deg(label_deg: float, angles: MakerAngles) -> float:
    """Our angle (degrees in [0, 180), from image x toward image y) of a polariser labelled
    ``label_deg`` in the convention ``angles`` (module docstring).

    Example:
        >>> our_angle_deg(45, "counterclockwise_on_screen"), our_angle_deg(45, "polanalyser")
        (135.0, 135.0)
        >>> our_angle_deg(45, "clockwise_on_screen")
        45.0
    """
    return _normalise_deg(_label_sign(angles) * float(label_deg))


@dataclass(frozen=True)
class MosaicLayout:
    """Polariser angle of each site of the 2×2 super-pixel, degrees, OUR convention.

    Attributes:
        angles_deg: ((top-left, top-right), (bottom-left, bottom-right)) in degrees, measured from
            image x toward image y (down), in [0, 180). Must be a permutation of 0, 45, 90, 135.

    Example:
        >>> MosaicLayout.imx250mzr().angles_deg
        ((90.0, 135.0), (45.0, 0.0))
        >>> MosaicLayout.from_maker([[90, 45], [135, 0]]) == MosaicLayout.imx250mzr()
        True
    """

    angles_deg: Angles2x2

    def __post_init__(self) -> None:
        values = _as_2x2(self.angles_deg, "MosaicLayout.angles_deg")
        values = tuple(tuple(_normalise_deg(a) for a in row) for row in values)  # type: ignore[assignment]
        flat = sorted(a for row in values for a in row)
        if any(not math.isclose(a, b, abs_tol=1e-6) for a, b in zip(flat, CHANNEL_ANGLES_DEG)):
            raise ValueError(
                f"MosaicLayout.angles_deg must hold each of 0, 45, 90, 135 degrees exactly once "
                f"(after reduction modulo 180); got {self.angles_deg!r}"
            )
        snapped = tuple(tuple(float(45 * round(a / 45.0)) for a in row) for row in values)
        object.__setattr__(self, "angles_deg", snapped)

    @classmethod
    def imx250mzr(cls) -> MosaicLayout:
        """Sony IMX250MZR default: maker's [[90, 45], [135, 0]] counter-clockwise on screen."""
        return cls.from_maker(((90, 45), (135, 0)), "counterclockwise_on_screen")

    @classmethod
    def from_maker(
        cls, layout: Sequence[Sequence[float]], angles: MakerAngles = "counterclockwise_on_screen"
    ) -> MosaicLayout:
        """Convert the maker's labels (``camera.mosaic`` of capture.yaml) to our convention.

        Args:
            layout: 2×2 maker labels in degrees, top row then bottom row.
            angles: ``"counterclockwise_on_screen"`` (maker's angle a is our −a mod 180°),
                ``"polanalyser"`` (polanalyser's labels: the same as the maker's) or
                ``"clockwise_on_screen"`` (already our y-down convention).
        """
        values = _as_2x2(layout, "mosaic layout")
        sign = _label_sign(angles)
        return cls(tuple(tuple(_normalise_deg(sign * a) for a in row) for row in values))  # type: ignore[arg-type]

    def to_maker(self, angles: MakerAngles = "counterclockwise_on_screen") -> Angles2x2:
        """The maker-style labels of this layout (inverse of :meth:`from_maker`)."""
        sign = _label_sign(angles)
        return tuple(tuple(_normalise_deg(sign * a) for a in row) for row in self.angles_deg)  # type: ignore[return-value]

    def shifted(self, offset_x: int, offset_y: int) -> MosaicLayout:
        """The layout seen in a region of interest whose top-left pixel is sensor pixel (offset_x, offset_y).

        ROI pixel (row r, column c) is sensor pixel (r + offset_y, c + offset_x), so odd offsets
        move the pattern by one site.
        """
        for name, v in (("offset_x", offset_x), ("offset_y", offset_y)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be a non-negative integer (pixels); got {v!r}")
        a = self.angles_deg
        return MosaicLayout(
            tuple(tuple(a[(i + offset_y) % 2][(j + offset_x) % 2] for j in range(2)) for i in range(2))  # type: ignore[arg-type]
        )

    def site_angles_deg(self) -> tuple[float, float, float, float]:
        """Angles (degrees) in site order (0, 0), (0, 1), (1, 0), (1, 1)."""
        a = self.angles_deg
        return (a[0][0], a[0][1], a[1][0], a[1][1])

    def angles_rad(self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
        """(4,) site angles in radians, site order (0, 0), (0, 1), (1, 0), (1, 1)."""
        return torch.tensor([math.radians(a) for a in self.site_angles_deg()], device=device, dtype=dtype)

    def channel_of_site(self, i: int, j: int) -> int:
        """Index into the 0°/45°/90°/135° channel stack of the filter at site (row parity i, column parity j)."""
        return round(self.angles_deg[i][j] / 45.0)

    def site_of_channel(self, channel: int) -> tuple[int, int]:
        """(row parity, column parity) of the site holding channel ``channel`` (0: 0°, 1: 45°, 2: 90°, 3: 135°)."""
        for i in range(2):
            for j in range(2):
                if self.channel_of_site(i, j) == channel:
                    return (i, j)
        raise ValueError(f"channel must be 0, 1, 2 or 3 (0°, 45°, 90°, 135°); got {channel!r}")


def check_layout(layout: object) -> MosaicLayout:
    """Return ``layout`` if it is a :class:`MosaicLayout`, else raise a TypeError naming the fix."""
    if not isinstance(layout, MosaicLayout):
        raise TypeError(
            f"layout must be a MosaicLayout (e.g. MosaicLayout.imx250mzr() or MosaicLayout.from_maker(...)); "
            f"got {type(layout).__name__}"
        )
    return layout


#: Why a mosaic needs even sizes, and the fix; shown in every mosaic shape error.
_MOSAIC_SIZES = (
    "with even, non-zero height and width (whole 2×2 super-pixels; crop one row/column, and shift the "
    "layout with MosaicLayout.shifted if you crop at the top/left)"
)


def check_mosaic_shape(mosaic: object, name: str = "mosaic") -> Tensor:
    """Return ``mosaic`` if it is a tensor of shape (*, 2H, 2W) with H, W >= 1, else raise.

    Raises:
        TypeError: not a ``torch.Tensor``.
        ShapeError: fewer than two dimensions, an odd or zero height or width (message shows the shape).
    """
    mosaic = check_tensor(mosaic, name)
    check_shape(mosaic, ["*", "2H", "2W"], name, _MOSAIC_SIZES)
    if 0 in mosaic.shape[-2:]:
        raise ShapeError(f"{name} must have shape (*, 2H, 2W) {_MOSAIC_SIZES}; got {format_shape(mosaic.shape)}")
    return mosaic


def mosaic_from_intensities(intensities: Tensor, layout: MosaicLayout) -> Tensor:
    """Interleave four polariser images into a raw mosaic.

    Args:
        intensities: (*, 4, H, W) images behind polarisers at 0°, 45°, 90°, 135° (our convention,
            in that order), one value per super-pixel.
        layout: which angle sits at each site of the 2×2 super-pixel.

    Returns:
        (*, 2H, 2W) mosaic; site (i, j) of super-pixel (y, x) is pixel (2y + i, 2x + j) and holds
        the channel whose angle the layout puts at that site.
    """
    layout = check_layout(layout)
    check_tensor(intensities, "intensities")
    check_shape(intensities, ["*", "4", "H", "W"], "intensities", "(0°, 45°, 90°, 135°)")
    *batch, _, h, w = intensities.shape
    out = intensities.new_empty((*batch, 2 * h, 2 * w))
    for i in range(2):
        for j in range(2):
            out[..., i::2, j::2] = intensities[..., layout.channel_of_site(i, j), :, :]
    return out


def mosaic_from_stokes(stokes: Tensor, layout: MosaicLayout) -> Tensor:
    """Raw mosaic of ideal polarisers seeing the Stokes field ``stokes`` (one value per super-pixel).

    Args:
        stokes: (*, 3, H, W) linear Stokes vectors at super-pixel resolution.
        layout: mosaic layout (our convention).

    Returns:
        (*, 2H, 2W) mosaic of ``½ (s0 + s1 cos 2θ + s2 sin 2θ)`` (spec §1).
    """
    check_dtype_floating(stokes, "stokes")
    angles = channel_angles_rad(device=stokes.device, dtype=stokes.dtype)
    return mosaic_from_intensities(intensities_from_stokes(stokes, angles), layout)


def split_mosaic(mosaic: Tensor, layout: MosaicLayout) -> Tensor:
    """Separate a raw mosaic into its four polariser images (inverse of :func:`mosaic_from_intensities`).

    Args:
        mosaic: (*, 2H, 2W) raw mosaic (any dtype); both sizes must be even.
        layout: mosaic layout of ``mosaic`` as stored (use :meth:`MosaicLayout.shifted` for an ROI).

    Returns:
        (*, 4, H, W) images at 0°, 45°, 90°, 135° (our convention), same dtype/device as ``mosaic``.
    """
    layout = check_layout(layout)
    check_mosaic_shape(mosaic)
    channels = [mosaic[..., i::2, j::2] for i, j in (layout.site_of_channel(c) for c in range(4))]
    return torch.stack(channels, dim=-3)
