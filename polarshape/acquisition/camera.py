"""The camera protocol every acquisition backend implements.

A backend delivers raw polarisation mosaics (sensor counts, low-bit aligned in ``uint16`` or
``uint8``) with the metadata needed to interpret them. Backends: :class:`SimulatedCamera`
(renders with polarshape's forward model) and :class:`AravisCamera` (GenICam / GigE Vision).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from polarshape.errors import CameraError


@dataclass(frozen=True)
class Frame:
    """One raw mosaic and what is known about it.

    Attributes:
        image: (H, W) raw polarisation mosaic in sensor counts, ``uint8`` or ``uint16``, low-bit
            aligned (values in ``[0, 2**bit_depth - 1]``).
        bit_depth: significant bits per pixel (8, 10, 12 or 16).
        pixel_format: PFNC name the frame was acquired in (e.g. ``"PolarizeMono12p"``).
        exposure_us: exposure time in microseconds.
        gain_db: analogue gain in dB.
        frame_id: the backend's frame counter (may wrap).
        timestamp_ns: acquisition time stamp in nanoseconds (backend clock).
        offset_xy: ROI offset (x, y) of ``image`` on the full sensor, in pixels. An odd offset shifts
            the 2x2 polariser pattern.
        metadata: anything else the backend knows.
        bayer: for a colour polarisation sensor (IMX250MYR, the ``BayerRG*`` formats), the Bayer
            pattern of the 2x2 polariser blocks of ``image`` (``"RGGB"``: colours of its top-left
            blocks, :mod:`polarshape.imaging.colour`); None for a mono sensor.
    """

    image: np.ndarray
    bit_depth: int
    pixel_format: str
    exposure_us: float
    gain_db: float
    frame_id: int = 0
    timestamp_ns: int = 0
    offset_xy: tuple[int, int] = (0, 0)
    metadata: dict[str, Any] = field(default_factory=dict)
    bayer: str | None = None


@runtime_checkable
class Camera(Protocol):
    """What polarshape needs from a camera backend.

    Usage::

        with SimulatedCamera(scene) as cam:      # or AravisCamera("192.168.1.20")
            cam.configure(exposure_us=20000, gain_db=0.0, pixel_format="PolarizeMono12p")
            frame = cam.capture()
    """

    def open(self) -> None:
        """Connect to the camera. Raises :class:`CameraError` naming the cause on failure."""

    def configure(
        self,
        *,
        exposure_us: float | None = None,
        gain_db: float | None = None,
        pixel_format: str | None = None,
    ) -> None:
        """Set exposure (µs), gain (dB) and pixel format (a key of
        :data:`polarshape.imaging.pixels.PIXEL_FORMATS`)."""

    def capture(self, timeout_s: float = 5.0) -> Frame:
        """Acquire one frame; raises :class:`CameraError` on timeout or a broken frame."""

    def close(self) -> None:
        """Release the camera (idempotent)."""

    def __enter__(self) -> "Camera": ...

    def __exit__(self, *exc: object) -> None: ...
