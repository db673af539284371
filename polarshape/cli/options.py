"""Command-line values that several commands parse the same way."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from polarshape.imaging.mosaic import MosaicLayout

__all__ = ["IMX250MZR_LABELS", "layout_from_flag"]

#: The maker's labels of the IMX250MZR 2×2 block (top-left, top-right, bottom-left, bottom-right).
IMX250MZR_LABELS = (90, 45, 135, 0)


def layout_from_flag(labels: Sequence[int] | None, angles: str) -> MosaicLayout:
    """The mosaic layout of ``--layout TL TR BL BR`` (None: the IMX250MZR's) measured as ``angles``.

    Raises:
        ValueError: naming ``--layout`` when the labels are not 0, 45, 90 and 135 once each.
    """
    from polarshape.imaging.mosaic import MosaicLayout  # torch is imported only once a command runs

    labels = list(labels) if labels else list(IMX250MZR_LABELS)
    if sorted(label % 180 for label in labels) != [0, 45, 90, 135]:
        raise ValueError(
            f"--layout {' '.join(str(v) for v in labels)}: must hold each of 0, 45, 90, 135 once (top-left, top-right, "
            "bottom-left, bottom-right; the IMX250MZR is 90 45 135 0)"
        )
    return MosaicLayout.from_maker([labels[:2], labels[2:]], angles)
