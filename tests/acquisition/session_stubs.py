"""A stub camera and an interruptible light rig for the capture-session tests (one copy for all of them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from polarshape.acquisition.camera import Frame
from polarshape.acquisition.lights import SimulatedLightRig


@dataclass
class StubCamera:
    """Counts proportional to exposure x (light + 1); 12-bit; records what it was asked."""

    light: int = 0
    exposure_us: float = 1000.0
    captured: list[tuple[int, float]] = field(default_factory=list)

    def open(self) -> None: ...

    def close(self) -> None: ...

    def configure(self, *, exposure_us: float | None = None, gain_db: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure_us is not None:
            self.exposure_us = exposure_us

    def set_light(self, index: int) -> None:
        self.light = index

    def capture(self, timeout_s: float = 5.0) -> Frame:
        ramp = np.linspace(0.0, 1.0, 64 * 48).reshape(48, 64)
        counts = np.minimum(4095, np.rint(ramp * self.exposure_us * (self.light + 1) * 0.2)).astype(np.uint16)
        self.captured.append((self.light, self.exposure_us))
        return Frame(image=counts, bit_depth=12, pixel_format="PolarizeMono12", exposure_us=self.exposure_us,
                     gain_db=0.0, frame_id=len(self.captured))


class FailingRig(SimulatedLightRig):
    def __init__(self, *args: Any, fail_at: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.fail_at = fail_at
        self.switched: list[int] = []

    def switch(self, index: int) -> None:
        if index == self.fail_at:
            raise KeyboardInterrupt("operator pressed Ctrl-C")
        self.switched.append(index)
        super().switch(index)
