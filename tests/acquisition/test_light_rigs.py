"""Light rigs: simulated, manual (injected input) and serial (against a fake board on a pty)."""

from __future__ import annotations

import os
import threading
import tty
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from polarshape.acquisition.lights import (
    LightRig,
    LightRigError,
    ManualLightRig,
    RigLight,
    SerialLightRig,
    SimulatedLightRig,
    enable_camera_strobe,
)

try:
    import serial  # noqa: F401
except ImportError:  # the serial tests skip; the others still run
    HAVE_SERIAL = False
else:
    HAVE_SERIAL = True
needs_serial = pytest.mark.skipif(not HAVE_SERIAL, reason="pyserial not installed (SerialLightRig)")


@dataclass
class _Target:
    lights: list[int | None] = field(default_factory=list)

    def set_light(self, index: int) -> None:
        self.lights.append(index)

    def all_off(self) -> None:
        self.lights.append(None)


@dataclass
class _StrobeCamera:
    calls: list[tuple[str, str]] = field(default_factory=list)

    def configure_strobe(self, line: str, source: str) -> None:
        self.calls.append((line, source))


class _FakeBoard:
    """A light board on the master side of a pty: answers the line protocol in a thread."""

    def __init__(self, n_lights: int, *, silent: bool = False, refuse: bool = False) -> None:
        self.n_lights = n_lights
        self.silent = silent
        self.refuse = refuse
        self.state: int | None = None
        self.received: list[str] = []
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave = slave
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _answer(self, line: str) -> str:
        words = line.split()
        if line == "N?":
            return f"N {self.n_lights}"
        if self.refuse:
            return "ERR overheated"
        if line == "OFF":
            self.state = None
            return "OK"
        if len(words) == 2 and words[0] == "L" and words[1].isdigit() and int(words[1]) < self.n_lights:
            self.state = int(words[1])
            return "OK"
        return f"ERR bad command {line!r}"

    def _run(self) -> None:
        buf = b""
        while not self._stop:
            try:
                chunk = os.read(self.master, 256)
            except OSError:
                return
            buf += chunk
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                line = raw.decode().strip()
                self.received.append(line)
                if self.silent and line != "N?":
                    continue
                os.write(self.master, (self._answer(line) + "\n").encode())

    def close(self) -> None:
        # closing our slave end (the rig has closed its own) makes the pending read fail with EIO
        self._stop = True
        os.close(self._slave)
        self._thread.join(timeout=2.0)
        os.close(self.master)


@pytest.fixture
def board() -> Iterator[_FakeBoard]:
    b = _FakeBoard(4)
    yield b
    b.close()


def test_light_spec_validation_and_yaml_entry() -> None:
    spec = RigLight(direction=(0.0, 3.0, -4.0), intensity=2.0, name="top")
    assert spec.direction == pytest.approx((0.0, 0.6, -0.8))
    assert spec.to_capture_entry() == {"direction": pytest.approx([0.0, 0.6, -0.8]), "intensity": 2.0, "name": "top"}
    assert RigLight(position=(0.1, 0.2, -0.5)).to_capture_entry()["position"] == [0.1, 0.2, -0.5]
    with pytest.raises(ValueError, match="exactly one of direction or position"):
        RigLight()
    with pytest.raises(ValueError, match="non-zero"):
        RigLight(direction=(0, 0, 0))
    with pytest.raises(ValueError, match="intensity must be > 0"):
        RigLight(direction=(0, 0, -1), intensity=0)


def test_simulated_rig_drives_its_target_and_the_strobe() -> None:
    target, cam = _Target(), _StrobeCamera()
    specs = [RigLight(direction=(0, 0, -1)), RigLight(direction=(0.5, 0, -1))]
    rig = SimulatedLightRig(target, specs, strobe_camera=cam)
    assert isinstance(rig, LightRig)
    assert rig.n_lights == 2 and rig.lights[1].direction == pytest.approx((0.4472136, 0, -0.8944272))
    assert cam.calls == [("Line1", "ExposureActive")]
    rig.switch(1)
    rig.switch(0)
    rig.all_off()
    assert target.lights == [1, 0, None]
    with pytest.raises(ValueError, match=r"out of range; this rig has lights 0..1"):
        rig.switch(2)
    with pytest.raises(TypeError, match="set_light"):
        SimulatedLightRig(object(), 2)
    with pytest.raises(LightRigError, match="no strobe output"):
        enable_camera_strobe(object())


def test_manual_rig_prompts_through_the_injected_input() -> None:
    prompts: list[str] = []
    answers = iter(["", "", "q"])

    def fake_input(prompt: str) -> str:
        prompts.append(prompt)
        return next(answers)

    rig = ManualLightRig([RigLight(direction=(0, 0, -1), name="centre"), RigLight(position=(0.2, 0, -0.5))],
                         input_fn=fake_input)
    rig.switch(0)
    assert rig.current == 0
    rig.switch(1)
    assert "Light 1/2 (centre)" in prompts[0] and "direction (0.0, 0.0, -1.0)" in prompts[0]
    assert "position (0.2, 0.0, -0.5) m" in prompts[1]
    with pytest.raises(LightRigError, match="aborted by the operator"):
        rig.all_off()


@needs_serial
def test_serial_rig_speaks_the_line_protocol(board: _FakeBoard) -> None:
    with SerialLightRig(board.port, 4, timeout_s=1.0, settle_s=0.0) as rig:
        assert isinstance(rig, LightRig)
        rig.switch(2)
        assert board.state == 2
        rig.switch(3)
        assert board.state == 3
        with pytest.raises(ValueError, match="out of range"):
            rig.switch(4)
    # leaving the context switched the light off
    assert board.state is None
    assert board.received == ["N?", "L 2", "L 3", "OFF"]


@needs_serial
def test_serial_rig_reports_a_silent_board() -> None:
    board = _FakeBoard(2, silent=True)
    try:
        rig = SerialLightRig(board.port, 2, timeout_s=0.2, settle_s=0.0)
        with pytest.raises(LightRigError, match=r"did not answer 'L 1' within 0.2 s"):
            rig.switch(1)
        rig.close()
    finally:
        board.close()


@needs_serial
def test_serial_rig_reports_refusals_and_mismatches() -> None:
    board = _FakeBoard(3, refuse=True)
    try:
        with SerialLightRig(board.port, 3, timeout_s=1.0, settle_s=0.0) as rig:
            with pytest.raises(LightRigError, match="refused 'L 0': ERR overheated"):
                rig.switch(0)
        with pytest.raises(LightRigError, match="drives 3 lights but 5 are configured"):
            SerialLightRig(board.port, 5, timeout_s=1.0)
    finally:
        board.close()
    with pytest.raises(LightRigError, match="cannot open the light board"):
        SerialLightRig("/dev/does-not-exist-polarshape", 2)
