"""Light rigs: switch one light on at a time while a camera captures.

A :class:`LightRig` has ``n_lights`` lights described by :class:`RigLight` (a direction to the
light or a position, camera frame: x right, y down, z forward), and ``switch(index)`` /
``all_off()``. Implementations:

- :class:`SimulatedLightRig` tells a simulated camera (any object with ``set_light(index)``,
  e.g. :class:`~polarshape.acquisition.simulated.SimulatedCamera`) which light is on;
- :class:`ManualLightRig` asks a person to move or switch a hand-held lamp (input is injectable);
- :class:`SerialLightRig` drives a microcontroller board over a serial line with the line
  protocol below.

Serial line protocol (ASCII, one command per line, ``\\n``-terminated; the board answers every
command with one line):

==================  ==========================  =============================================
host sends          board answers               meaning
==================  ==========================  =============================================
``N?``              ``N <count>``               number of lights the board drives
``L <i>``           ``OK``                      light ``i`` (0-based) on, every other off
``OFF``             ``OK``                      all lights off
anything invalid    ``ERR <reason>``            nothing changed
==================  ==========================  =============================================

Any rig can also set a camera's strobe output (``LineSource = ExposureActive`` on Line1) so the
board can gate the light with the exposure (see :func:`enable_camera_strobe`).
"""

from __future__ import annotations

import logging
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

from polarshape.errors import LightRigError

logger = logging.getLogger(__name__)

__all__ = [
    "LightRig",
    "LightRigError",
    "ManualLightRig",
    "RigLight",
    "SerialLightRig",
    "SimulatedLightRig",
    "enable_camera_strobe",
]


@dataclass(frozen=True)
class RigLight:
    """One light of a rig, in the camera frame (OpenCV: x right, y down, z forward), and its label.

    A session file's ``lights`` entries (:class:`polarshape.acquisition.session.LightEntry`, a
    :class:`polarshape.io.capture.LightSpec` with a name) become rig lights.

    Attributes:
        direction: unit vector from the scene *to* a distant light (normalised on creation), or None.
        position: position of a point light in metres, or None. Exactly one of the two is set.
        intensity: relative intensity (1.0 = nominal).
        name: free label (e.g. the LED's position on the rig).
    """

    direction: tuple[float, float, float] | None = None
    position: tuple[float, float, float] | None = None
    intensity: float = 1.0
    name: str = ""

    def __post_init__(self) -> None:
        if (self.direction is None) == (self.position is None):
            raise ValueError(f"light {self.name!r}: give exactly one of direction or position")
        vec = self.direction if self.direction is not None else self.position
        if vec is None or len(vec) != 3 or not all(math.isfinite(float(v)) for v in vec):
            raise ValueError(f"light {self.name!r}: direction/position must be 3 finite numbers; got {vec!r}")
        if not self.intensity > 0:
            raise ValueError(f"light {self.name!r}: intensity must be > 0; got {self.intensity}")
        if self.direction is not None:
            norm = math.sqrt(sum(float(v) ** 2 for v in self.direction))
            if norm < 1e-9:
                raise ValueError(f"light {self.name!r}: direction must be non-zero")
            object.__setattr__(self, "direction", tuple(float(v) / norm for v in self.direction))
        else:
            object.__setattr__(self, "position", tuple(float(v) for v in self.position))  # type: ignore[union-attr]

    def to_capture_entry(self) -> dict[str, Any]:
        """The ``lights[*]`` entry of capture.yaml (without the ``frame`` key)."""
        entry: dict[str, Any] = {}
        if self.direction is not None:
            entry["direction"] = [float(v) for v in self.direction]
        else:
            entry["position"] = [float(v) for v in self.position]  # type: ignore[union-attr]
        entry["intensity"] = float(self.intensity)
        if self.name:
            entry["name"] = self.name
        return entry


@runtime_checkable
class LightRig(Protocol):
    """What a capture session needs from a set of lights."""

    @property
    def n_lights(self) -> int:
        """Number of lights."""

    @property
    def lights(self) -> tuple[RigLight, ...]:
        """Direction/position metadata of every light, index order."""

    def switch(self, index: int) -> None:
        """Turn light ``index`` on and every other light off (blocks until settled)."""

    def all_off(self) -> None:
        """Turn every light off."""


def enable_camera_strobe(camera: Any, line: str = "Line1") -> None:
    """Make ``camera`` output its exposure on ``line`` (``LineSource = ExposureActive``).

    ``camera`` must have ``configure_strobe(line, source)`` (e.g.
    :class:`~polarshape.acquisition.aravis.AravisCamera`).
    """
    configure = getattr(camera, "configure_strobe", None)
    if configure is None:
        raise LightRigError(
            f"{type(camera).__name__} has no strobe output (configure_strobe); use an AravisCamera "
            "or drop strobe_camera"
        )
    configure(line, "ExposureActive")


def _as_specs(lights: Sequence[RigLight] | int) -> tuple[RigLight, ...]:
    if isinstance(lights, int):
        if lights < 1:
            raise ValueError(f"a light rig needs at least one light; got {lights}")
        # unknown geometry: straight along the view axis, to be calibrated (polarshape calibrate)
        return tuple(RigLight(direction=(0.0, 0.0, -1.0), name=f"light{i}") for i in range(lights))
    specs = tuple(lights)
    if not specs:
        raise ValueError("a light rig needs at least one light; got an empty list")
    for spec in specs:
        if not isinstance(spec, RigLight):
            raise TypeError(f"lights must be RigLight objects; got {type(spec).__name__}")
    return specs


class _RigBase(ABC):
    """Shared bookkeeping: light metadata, index checks, optional camera strobe, state."""

    def __init__(
        self,
        lights: Sequence[RigLight] | int,
        *,
        strobe_camera: Any = None,
        strobe_line: str = "Line1",
        settle_s: float = 0.0,
    ) -> None:
        self._lights = _as_specs(lights)
        self._settle_s = float(settle_s)
        self._current: int | None = None
        if strobe_camera is not None:
            enable_camera_strobe(strobe_camera, strobe_line)

    @property
    def n_lights(self) -> int:
        """Number of lights."""
        return len(self._lights)

    @property
    def lights(self) -> tuple[RigLight, ...]:
        """Direction/position metadata of every light, index order."""
        return self._lights

    @property
    def current(self) -> int | None:
        """Index of the light that is on, or None when all are off."""
        return self._current

    def _check_index(self, index: int) -> int:
        if not isinstance(index, int) or not 0 <= index < self.n_lights:
            raise ValueError(f"light index {index!r} is out of range; this rig has lights 0..{self.n_lights - 1}")
        return index

    @abstractmethod
    def switch(self, index: int) -> None:
        """Turn light ``index`` on and every other light off."""

    @abstractmethod
    def all_off(self) -> None:
        """Turn every light off."""

    def _settle(self) -> None:
        if self._settle_s > 0:
            time.sleep(self._settle_s)

    def __enter__(self) -> _RigBase:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Turn the lights off and release the rig (idempotent)."""
        if self._current is not None:
            self.all_off()


class SimulatedLightRig(_RigBase):
    """Lights of a simulated scene: ``switch(i)`` calls ``target.set_light(i)``.

    Args:
        target: any object with ``set_light(index)`` (a SimulatedCamera, a fake GigE camera…).
            If it also has ``all_off()``, :meth:`all_off` calls it.
        lights: light metadata, or a count (directions then unknown: +z placeholders to calibrate).
        strobe_camera, strobe_line: optionally enable a camera's ExposureActive strobe output.
    """

    def __init__(self, target: Any, lights: Sequence[RigLight] | int, *, strobe_camera: Any = None,
                 strobe_line: str = "Line1") -> None:
        if not callable(getattr(target, "set_light", None)):
            raise TypeError(f"target {type(target).__name__} has no set_light(index) method")
        super().__init__(lights, strobe_camera=strobe_camera, strobe_line=strobe_line)
        self.target = target

    def switch(self, index: int) -> None:
        """Tell the target that light ``index`` is on."""
        self.target.set_light(self._check_index(index))
        self._current = index

    def all_off(self) -> None:
        """Tell the target all lights are off (when it supports it)."""
        off = getattr(self.target, "all_off", None)
        if callable(off):
            off()
        self._current = None


class ManualLightRig(_RigBase):
    """A person moves or switches a lamp when asked.

    Args:
        lights: light metadata (where to put the lamp), or a count.
        input_fn: reads the operator's answer to a prompt (default: :func:`input`); answering
            ``q`` aborts with :class:`LightRigError`.
        strobe_camera, strobe_line: optionally enable a camera's ExposureActive strobe output.
    """

    def __init__(self, lights: Sequence[RigLight] | int, *, input_fn: Callable[[str], str] = input,
                 strobe_camera: Any = None, strobe_line: str = "Line1") -> None:
        super().__init__(lights, strobe_camera=strobe_camera, strobe_line=strobe_line)
        self._input = input_fn

    def _ask(self, prompt: str) -> None:
        answer = self._input(prompt).strip().lower()
        if answer in ("q", "quit", "abort"):
            raise LightRigError("capture aborted by the operator")

    def switch(self, index: int) -> None:
        """Ask the operator to put the lamp in position ``index`` and switch it on."""
        spec = self.lights[self._check_index(index)]
        where = (f"direction {tuple(round(v, 3) for v in spec.direction)}" if spec.direction is not None
                 else f"position {spec.position} m")
        label = f" ({spec.name})" if spec.name else ""
        self._ask(f"Light {index + 1}/{self.n_lights}{label}: place the lamp at {where} "
                  "(camera frame), switch it on, then press Enter [q = abort] ")
        self._current = index

    def all_off(self) -> None:
        """Ask the operator to switch the lamp off."""
        self._ask("Switch the lamp off, then press Enter [q = abort] ")
        self._current = None


class SerialLightRig(_RigBase):
    """A light board on a serial port, speaking the line protocol of this module's docstring.

    Args:
        port: serial device (``/dev/ttyACM0``, ``COM3``) or a pyserial URL.
        lights: light metadata, or a count. On open the board's ``N?`` answer must match.
        baudrate: line speed.
        timeout_s: how long to wait for each answer.
        settle_s: wait after each ``OK`` (LED warm-up) before returning.
        strobe_camera, strobe_line: optionally enable a camera's ExposureActive strobe output.
        serial_factory: builds the port object (default: ``serial.serial_for_url``); tests inject.
    """

    def __init__(
        self,
        port: str,
        lights: Sequence[RigLight] | int,
        *,
        baudrate: int = 115200,
        timeout_s: float = 1.0,
        settle_s: float = 0.05,
        strobe_camera: Any = None,
        strobe_line: str = "Line1",
        serial_factory: Callable[..., Any] | None = None,
    ) -> None:
        super().__init__(lights, strobe_camera=strobe_camera, strobe_line=strobe_line, settle_s=settle_s)
        self.port = port
        self._timeout_s = float(timeout_s)
        if serial_factory is None:
            try:
                import serial
            except ImportError as exc:
                raise LightRigError(
                    "SerialLightRig needs pyserial: `pip install pyserial` (>= 3.5)"
                ) from exc
            serial_factory = serial.serial_for_url
        try:
            self._serial = serial_factory(port, baudrate=baudrate, timeout=self._timeout_s,
                                          write_timeout=self._timeout_s)
        except Exception as exc:  # pyserial raises SerialException (an OSError) or ValueError
            raise LightRigError(f"cannot open the light board on {port!r}: {exc}") from exc
        try:
            self._serial.reset_input_buffer()
            answer = self._command("N?")
            parts = answer.split()
            if len(parts) != 2 or parts[0] != "N" or not parts[1].isdigit():
                raise LightRigError(f"light board on {port!r} answered {answer!r} to 'N?' (expected 'N <count>'): "
                                    "is it running the polarshape light firmware?")
            if int(parts[1]) != self.n_lights:
                raise LightRigError(f"light board on {port!r} drives {parts[1]} lights but {self.n_lights} are "
                                    "configured: fix the lights list of the session")
        except BaseException:
            self._serial.close()
            raise

    def _command(self, command: str) -> str:
        try:
            self._serial.write(f"{command}\n".encode("ascii"))
            self._serial.flush()
            line = self._serial.readline()
        except Exception as exc:
            raise LightRigError(
                f"serial I/O with the light board on {self.port!r} failed ({command!r}): {exc}"
            ) from exc
        if not line.endswith(b"\n"):
            raise LightRigError(
                f"the light board on {self.port!r} did not answer {command!r} within {self._timeout_s} s "
                f"(got {line!r}): check the cable, the port name and the baud rate"
            )
        answer = line.decode("ascii", errors="replace").strip()
        if answer.startswith("ERR"):
            raise LightRigError(f"the light board on {self.port!r} refused {command!r}: {answer}")
        return answer

    def _expect_ok(self, command: str) -> None:
        answer = self._command(command)
        if answer != "OK":
            raise LightRigError(f"the light board on {self.port!r} answered {answer!r} to {command!r} (expected 'OK')")

    def switch(self, index: int) -> None:
        """Send ``L <index>`` and wait for ``OK`` (then ``settle_s``)."""
        self._expect_ok(f"L {self._check_index(index)}")
        self._current = index
        self._settle()

    def all_off(self) -> None:
        """Send ``OFF`` and wait for ``OK``."""
        self._expect_ok("OFF")
        self._current = None

    def close(self) -> None:
        """Switch everything off and close the port (idempotent)."""
        if getattr(self, "_serial", None) is None:
            return
        try:
            if self._current is not None and self._serial.is_open:
                self.all_off()
        finally:
            self._serial.close()
            self._serial = None
