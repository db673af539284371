"""GenICam / GigE Vision camera backend on Aravis 0.8 (e.g. a Lucid TRI050S-PC or TRI050S-QC).

:class:`AravisCamera` implements :class:`~polarshape.acquisition.camera.Camera` through Aravis'
GObject-introspection binding (PyGObject). PyGObject and Aravis are optional: this module imports
without them, and constructing an :class:`AravisCamera` then raises :class:`CameraError` naming
what to install (``scripts/install-system-deps.sh`` and the ``aravis`` extra).

What it takes care of:

- opening by IP address (unicast GVCP, no broadcast discovery) or by Aravis device id;
- ExposureTime (µs, auto off), Gain (dB, auto off), PixelFormat (the five PolarizeMono formats of
  the mono sensor, the five BayerRG formats of the colour one; checked against what the device
  offers), ROI (offsets in multiples of 4 with a colour format, so the Bayer pattern of the
  polariser blocks stays the format's), frame-rate limit, packet size, link throughput
  limit, trigger (free-running, software, hardware on Line0) and an ExposureActive strobe output;
- a stream with a pool of buffers and an automatically sized socket buffer; every popped buffer is
  pushed back; the stream is released before the camera;
- per-frame timeout and retries on incomplete or missing frames, ending in a :class:`CameraError`
  that names the cause (no camera, unsupported format, dropped frames with their buffer statuses,
  link too slow, no trigger);
- 16-bit GigE Vision frame ids that wrap (…, 65535, 1, …): ``Frame.metadata["frame_count"]`` is a
  monotonic 64-bit count (it also advances over dropped frames).

Frames arrive as (H, W) ``uint16`` mosaics in sensor counts (see :mod:`polarshape.imaging.pixel_formats`);
a colour format's frames carry their Bayer pattern in ``Frame.bayer``.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from types import TracebackType
from typing import Any, Literal

from polarshape.acquisition.camera import CameraError, Frame
from polarshape.imaging.pixel_formats import format_name_of, payload_size, unpack_mosaic
from polarshape.imaging.pixels import PIXEL_FORMATS, bayer_of

logger = logging.getLogger(__name__)

__all__ = ["AravisCamera", "FrameCounter", "TriggerMode", "import_aravis"]

TriggerMode = Literal["off", "software", "line0"]

INSTALL_HINT = (
    "install the Aravis 0.8 runtime and PyGObject: `sudo bash scripts/install-system-deps.sh` "
    "(Debian packages libaravis-0.8-0 gir1.2-aravis-0.8, plus libgirepository1.0-dev libcairo2-dev "
    "pkg-config gcc to build PyGObject) then `pip install 'polarshape[aravis]'` "
    "(PyGObject>=3.42,<3.51)"
)


def import_aravis() -> Any:
    """Import and return the ``Aravis`` 0.8 GI module; :class:`CameraError` with the fix if absent."""
    try:
        import gi
    except ImportError as exc:
        raise CameraError(f"AravisCamera needs PyGObject (module 'gi' not found): {INSTALL_HINT}") from exc
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise CameraError(f"AravisCamera needs the Aravis 0.8 typelib ({exc}): {INSTALL_HINT}") from exc
    return Aravis


def _check_colour_offsets(pixel_format: str, x: int, y: int) -> None:
    """Refuse ROI offsets that would shift the Bayer pattern of a colour format's polariser blocks."""
    if x % 4 or y % 4:
        raise ValueError(
            f"roi offset (x={x}, y={y}) with the colour format {pixel_format}: a colour polarisation sensor's "
            f"offsets must be multiples of 4 (one Bayer super-block of 2x2 polariser blocks), so that the "
            f"frames keep the {bayer_of(pixel_format)} pattern {pixel_format} names"
        )


class FrameCounter:
    """Turns wrapping GigE Vision frame ids into a monotonic 64-bit count.

    GigE Vision 1.x block ids are 16-bit, never 0 once streaming: 65534, 65535, 1, 2, … (Aravis'
    fake camera starts at 65400 to exercise this). Ids above 0xFFFF (GigE Vision 2 extended ids)
    are taken as they are.

    Example:
        >>> c = FrameCounter()
        >>> [c.update(i) for i in (65534, 65535, 1, 3)]
        [65534, 65535, 65536, 65538]
    """

    _PERIOD = 0xFFFF  # ids 1..65535: 65535 distinct values

    def __init__(self) -> None:
        self._last_raw: int | None = None
        self._count = 0

    def update(self, raw_id: int) -> int:
        """Account for a frame with device id ``raw_id``; returns its monotonic count."""
        raw_id = int(raw_id)
        if self._last_raw is None or raw_id > 0xFFFF or self._last_raw > 0xFFFF:
            self._count = raw_id  # first frame, or extended ids that do not wrap
        else:
            self._count += (raw_id - self._last_raw) % self._PERIOD
        self._last_raw = raw_id
        return self._count

    @property
    def count(self) -> int:
        """Count of the last frame seen (0 before any)."""
        return self._count


class AravisCamera:
    """A GenICam GigE Vision polarisation camera, driven through Aravis 0.8.

    Args:
        address_or_id: the camera's IPv4 address (preferred: opened by unicast, nothing is
            broadcast) or an Aravis device id such as ``"Lucid Vision Labs-TRI050S-PC-213400123"``
            (found by discovery on all interfaces).
        trigger: ``"off"`` (free-running; a capture takes the first frame exposed after the call),
            ``"software"`` (each capture sends TriggerSoftware) or ``"line0"`` (hardware trigger,
            rising edge on Line0; a capture waits for it).
        packet_size: GigE Vision stream packet size in bytes (``GevSCPSPacketSize``); ``None``
            leaves the device's setting. Use 1400 on loopback, up to 9000 with jumbo frames.
        frame_rate_hz: free-running frame-rate limit (``AcquisitionFrameRate``); ``None`` leaves it.
        throughput_limit_bps: ``DeviceLinkThroughputLimit`` in bytes/s; ``None`` leaves it.
        n_buffers: size of the stream's buffer pool.
        max_attempts: frames tried per :meth:`capture` before giving up (incomplete frames and
            timeouts count as failed attempts).
        socket_buffer_bytes: fixed receive socket buffer of a GigE Vision stream; ``None`` (the
            default) sizes it automatically from the payload (``GvStreamSocketBuffer.AUTO``).
        packet_socket: let Aravis use its packet-socket fast path when it can (root / CAP_NET_RAW);
            ``False`` forces the plain UDP socket path (what unprivileged users get).

    Example::

        with AravisCamera("192.168.1.20", trigger="software", packet_size=9000) as cam:
            cam.configure(exposure_us=20000, gain_db=0.0, pixel_format="PolarizeMono12p")
            frame = cam.capture(timeout_s=2.0)      # frame.image: (2048, 2448) uint16
    """

    def __init__(
        self,
        address_or_id: str,
        *,
        trigger: TriggerMode = "off",
        packet_size: int | None = None,
        frame_rate_hz: float | None = None,
        throughput_limit_bps: int | None = None,
        n_buffers: int = 4,
        max_attempts: int = 3,
        socket_buffer_bytes: int | None = None,
        packet_socket: bool = True,
    ) -> None:
        self._aravis = import_aravis()
        if trigger not in ("off", "software", "line0"):
            raise ValueError(f"trigger={trigger!r}: use 'off', 'software' or 'line0'")
        if n_buffers < 1 or max_attempts < 1:
            raise ValueError(f"n_buffers ({n_buffers}) and max_attempts ({max_attempts}) must be >= 1")
        if packet_size is not None and not 576 <= packet_size <= 16384:
            raise ValueError(f"packet_size={packet_size}: use 576..16384 bytes (1400 on loopback, up to the MTU - 28)")
        self.address = str(address_or_id)
        self._trigger: TriggerMode = trigger
        self._packet_size = packet_size
        self._frame_rate_hz = frame_rate_hz
        self._throughput_limit_bps = throughput_limit_bps
        self._n_buffers = n_buffers
        self._max_attempts = max_attempts
        self._socket_buffer_bytes = socket_buffer_bytes
        self._packet_socket = packet_socket
        self._last_trigger_ns = 0
        self._triggers_sent = 0
        self._camera: Any = None
        self._stream: Any = None
        self._acquiring = False
        self._counter = FrameCounter()
        self._pixel_format = "PolarizeMono8"
        self._exposure_us = 0.0
        self._gain_db = 0.0
        self._region = (0, 0, 0, 0)
        self._payload = 0
        self.vendor = self.model = self.serial = ""

    # -- Camera protocol -------------------------------------------------------------------------

    def open(self) -> None:
        """Connect and put the camera in a known state (auto exposure/gain off, continuous mode)."""
        if self._camera is not None:
            return
        from gi.repository import GLib

        try:
            camera = self._aravis.Camera.new(self.address)
        except GLib.Error as exc:
            raise CameraError(
                f"no camera answered at {self.address!r} ({exc.message}); check the address, cable "
                f"and power, that the camera is on this host's subnet, and try `arv-tool-0.8 -a "
                f"{self.address}`"
            ) from exc
        if camera is None:
            raise CameraError(f"no camera answered at {self.address!r}")
        self._camera = camera
        try:
            self.vendor = self._call("read DeviceVendorName", camera.get_vendor_name) or ""
            self.model = self._call("read DeviceModelName", camera.get_model_name) or ""
            self.serial = self._call("read DeviceSerialNumber", camera.get_device_serial_number) or ""
            self._set_enum_if_available("ExposureAuto", "Off")
            self._set_enum_if_available("GainAuto", "Off")
            self._call("set AcquisitionMode", camera.set_acquisition_mode,
                       self._aravis.AcquisitionMode.CONTINUOUS)
            if self._call("check for a GigE Vision device", camera.is_gv_device):
                if not self._packet_socket:
                    camera.gv_set_stream_options(self._aravis.GvStreamOption.PACKET_SOCKET_DISABLED)
                if self._packet_size is not None:
                    camera.gv_set_packet_size_adjustment(self._aravis.GvPacketSizeAdjustment.NEVER)
                    self._call("set GevSCPSPacketSize", camera.gv_set_packet_size, self._packet_size)
            elif self._packet_size is not None:
                raise CameraError(f"packet_size applies to GigE Vision cameras; {self.address!r} is not one")
            if self._frame_rate_hz is not None:
                self.set_frame_rate_limit(self._frame_rate_hz)
            if self._throughput_limit_bps is not None:
                self.set_throughput_limit(self._throughput_limit_bps)
            self.set_trigger(self._trigger)
            self._read_state()
        except BaseException:
            self.close()
            raise
        logger.info("opened %s %s (serial %s) at %s", self.vendor, self.model, self.serial, self.address)

    def configure(
        self,
        *,
        exposure_us: float | None = None,
        gain_db: float | None = None,
        pixel_format: str | None = None,
        roi: tuple[int, int, int, int] | None = None,
    ) -> None:
        """Set exposure (µs), gain (dB), pixel format and ROI ``(x, y, width, height)`` in pixels.

        Values are checked against the device's bounds and read back (the device may round).
        Changing the format or ROI restarts the stream.
        """
        self.open()
        camera = self._camera
        if pixel_format is not None:
            if pixel_format not in PIXEL_FORMATS:
                raise ValueError(f"pixel_format {pixel_format!r}: use one of {sorted(PIXEL_FORMATS)}")
            offered = list(self._call("list PixelFormat entries", camera.dup_available_pixel_formats_as_strings) or [])
            if pixel_format not in offered:
                raise CameraError(
                    f"the camera at {self.address} ({self.model}) does not offer pixel format "
                    f"{pixel_format}; it offers {offered}: choose one of those"
                )
            if bayer_of(pixel_format) is not None and roi is None:
                _check_colour_offsets(pixel_format, *self._region[:2])
            if pixel_format != self._pixel_format:
                self._stop_stream()
                self._call(f"set PixelFormat={pixel_format}", camera.set_pixel_format_from_string, pixel_format)
                self._pixel_format = pixel_format  # read back below; set_roi checks against it first
        if roi is not None:
            self.set_roi(*roi)
        if exposure_us is not None:
            lo, hi = self._call("read ExposureTime bounds", camera.get_exposure_time_bounds)
            if not lo <= exposure_us <= hi:
                raise ValueError(f"exposure_us={exposure_us} is outside the camera's range [{lo}, {hi}] µs")
            self._call(f"set ExposureTime={exposure_us}", camera.set_exposure_time, float(exposure_us))
        if gain_db is not None:
            lo, hi = self._call("read Gain bounds", camera.get_gain_bounds)
            if not lo <= gain_db <= hi:
                raise ValueError(f"gain_db={gain_db} is outside the camera's range [{lo}, {hi}] dB")
            self._call(f"set Gain={gain_db}", camera.set_gain, float(gain_db))
        self._read_state()

    def capture(self, timeout_s: float = 5.0, *, send_trigger: bool = True) -> Frame:
        """Acquire one complete frame.

        Each attempt waits up to ``timeout_s`` for a complete frame, sending TriggerSoftware first
        in software-trigger mode (unless ``send_trigger=False``: then the frame of an earlier
        :meth:`trigger_software` call, or of a trigger sent by another program, is awaited).
        Incomplete frames are dropped and retried up to ``max_attempts`` times. Frames exposed
        before the call (stale buffers of a free-running camera, late frames of an earlier
        trigger) are skipped.

        Raises:
            CameraError: naming the cause: dropped frames (with their buffer statuses), link too
                slow / stream blocked, or no trigger.
        """
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive; got {timeout_s}")
        self.open()
        self._start_stream()
        failures: list[str] = []
        triggers_before = self._triggers_sent
        for attempt in range(1, self._max_attempts + 1):
            requested_ns = time.time_ns()
            if self._trigger == "software" and send_trigger:
                self.trigger_software()
            if self._trigger == "off":
                # the whole exposure must start after the request
                earliest_ns = requested_ns + int(self._exposure_us * 1000)
            elif self._trigger == "software" and not send_trigger:
                earliest_ns = self._last_trigger_ns
            else:
                earliest_ns = requested_ns
            frame, failure = self._wait_for_frame(timeout_s, earliest_ns, attempt)
            if frame is not None:
                return frame
            failures.append(failure)
            logger.warning("camera %s: attempt %d/%d failed (%s)", self.address, attempt,
                           self._max_attempts, failure)
        raise CameraError(self._explain(failures, timeout_s, sent_triggers=self._triggers_sent > triggers_before))

    def close(self) -> None:
        """Stop acquisition and release stream then camera (idempotent)."""
        try:
            self._stop_stream()
        finally:
            self._camera = None

    def __enter__(self) -> AravisCamera:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- further controls ------------------------------------------------------------------------

    @property
    def pixel_format(self) -> str:
        """Current PFNC pixel format."""
        return self._pixel_format

    @property
    def exposure_us(self) -> float:
        """Exposure time read back from the device, µs."""
        return self._exposure_us

    @property
    def gain_db(self) -> float:
        """Gain read back from the device, dB."""
        return self._gain_db

    @property
    def roi(self) -> tuple[int, int, int, int]:
        """Current region ``(x, y, width, height)`` on the sensor, pixels."""
        return self._region

    @property
    def trigger(self) -> TriggerMode:
        """Current trigger mode."""
        return self._trigger

    @property
    def sensor_size(self) -> tuple[int, int]:
        """Full sensor ``(width, height)`` in pixels."""
        self.open()
        w, h = self._call("read SensorWidth/SensorHeight", self._camera.get_sensor_size)
        return int(w), int(h)

    def set_roi(self, x: int, y: int, width: int, height: int) -> None:
        """Set the region of interest in sensor pixels (restarts the stream).

        Offsets should be even so the 2x2 polariser cell keeps its layout; with a colour format
        (``BayerRG*``) they must be multiples of 4, so that the Bayer pattern of the polariser
        blocks stays the one the format names. The device's increments are enforced.
        """
        self.open()
        camera = self._camera
        if bayer_of(self._pixel_format) is not None:
            _check_colour_offsets(self._pixel_format, x, y)
        sw, sh = self.sensor_size
        if width <= 0 or height <= 0 or x < 0 or y < 0 or x + width > sw or y + height > sh:
            raise ValueError(f"roi (x={x}, y={y}, width={width}, height={height}) does not fit the {sw}x{sh} sensor")
        for name, value, inc in (
            ("x", x, camera.get_x_offset_increment()), ("y", y, camera.get_y_offset_increment()),
            ("width", width, camera.get_width_increment()), ("height", height, camera.get_height_increment()),
        ):
            if inc > 1 and value % inc:
                raise ValueError(f"roi {name}={value} must be a multiple of {inc} on this camera")
        self._stop_stream()
        # offsets to 0 first so the new size is always within range, then the final offsets
        self._call("set OffsetX", camera.set_integer, "OffsetX", 0)
        self._call("set OffsetY", camera.set_integer, "OffsetY", 0)
        self._call("set Width", camera.set_integer, "Width", int(width))
        self._call("set Height", camera.set_integer, "Height", int(height))
        self._call("set OffsetX", camera.set_integer, "OffsetX", int(x))
        self._call("set OffsetY", camera.set_integer, "OffsetY", int(y))
        self._read_state()
        if self._region != (x, y, width, height):
            raise CameraError(f"the camera set roi {self._region} instead of {(x, y, width, height)}")

    def set_trigger(self, mode: TriggerMode) -> None:
        """Select free-running (``"off"``), ``"software"`` or hardware ``"line0"`` triggering."""
        if mode not in ("off", "software", "line0"):
            raise ValueError(f"trigger mode {mode!r}: use 'off', 'software' or 'line0'")
        self.open()
        camera = self._camera
        self._set_enum_if_available("TriggerSelector", "FrameStart")
        if mode == "off":
            self._call("set TriggerMode=Off", camera.set_string, "TriggerMode", "Off")
        else:
            source = "Software" if mode == "software" else "Line0"
            self._call(f"set TriggerSource={source}", camera.set_string, "TriggerSource", source)
            if mode == "line0":
                self._set_enum_if_available("TriggerActivation", "RisingEdge")
            self._call("set TriggerMode=On", camera.set_string, "TriggerMode", "On")
        self._trigger = mode

    def trigger_software(self) -> None:
        """Execute TriggerSoftware (the camera must be in software-trigger mode)."""
        self.open()
        if self._trigger != "software":
            raise CameraError(f"trigger_software() needs trigger='software'; the camera is in {self._trigger!r} mode")
        self._last_trigger_ns = time.time_ns()
        self._call("execute TriggerSoftware", self._camera.execute_command, "TriggerSoftware")
        self._triggers_sent += 1

    def set_frame_rate_limit(self, frame_rate_hz: float | None) -> None:
        """Limit the free-running frame rate (``None`` removes the limit where the device allows)."""
        self.open()
        camera = self._camera
        has_enable = self._call("check AcquisitionFrameRateEnable", camera.is_feature_available,
                                "AcquisitionFrameRateEnable")
        if frame_rate_hz is None:
            if has_enable:
                self._call("clear AcquisitionFrameRateEnable", camera.set_boolean,
                           "AcquisitionFrameRateEnable", False)
            return
        lo, hi = self._call("read AcquisitionFrameRate bounds", camera.get_float_bounds, "AcquisitionFrameRate")
        if not lo <= frame_rate_hz <= hi:
            raise ValueError(f"frame_rate_hz={frame_rate_hz} is outside the camera's range [{lo}, {hi}] Hz")
        if has_enable:
            self._call("set AcquisitionFrameRateEnable", camera.set_boolean, "AcquisitionFrameRateEnable", True)
        self._call("set AcquisitionFrameRate", camera.set_float, "AcquisitionFrameRate", float(frame_rate_hz))

    def set_throughput_limit(self, bytes_per_s: int) -> None:
        """Cap the link throughput (``DeviceLinkThroughputLimit``, bytes/s) to avoid packet loss."""
        self.open()
        self._set_enum_if_available("DeviceLinkThroughputLimitMode", "On")
        self._call("set DeviceLinkThroughputLimit", self._camera.set_integer,
                   "DeviceLinkThroughputLimit", int(bytes_per_s))

    def configure_strobe(self, line: str = "Line1", source: str = "ExposureActive", *, inverted: bool = False) -> None:
        """Drive output ``line`` with ``source`` (default: ExposureActive on Line1, for a flash)."""
        self.open()
        camera = self._camera
        self._call(f"set LineSelector={line}", camera.set_string, "LineSelector", line)
        self._call(f"set LineMode=Output on {line}", camera.set_string, "LineMode", "Output")
        self._call(f"set LineSource={source} on {line}", camera.set_string, "LineSource", source)
        if self._call("check LineInverter", camera.is_feature_available, "LineInverter"):
            self._call(f"set LineInverter on {line}", camera.set_boolean, "LineInverter", bool(inverted))

    def get_feature(self, name: str) -> Any:
        """Read a GenICam feature by name (string, float, integer or boolean, by its node type)."""
        self.open()
        camera = self._camera
        node = self._call(f"find feature {name}", camera.get_device().get_feature, name)
        if node is None:
            raise CameraError(f"the camera at {self.address} has no feature {name!r}")
        kind = type(node).__name__
        if "Enumeration" in kind or "String" in kind:
            return self._call(f"read {name}", camera.get_string, name)
        if "Float" in kind or "Converter" in kind:
            return self._call(f"read {name}", camera.get_float, name)
        if "Boolean" in kind:
            return self._call(f"read {name}", camera.get_boolean, name)
        return self._call(f"read {name}", camera.get_integer, name)

    def stream_statistics(self) -> dict[str, int]:
        """Completed buffers, failures, underruns (and GigE resent/missing packets) of the stream."""
        stats = {"completed": 0, "failures": 0, "underruns": 0}
        if self._stream is None:
            return stats
        # GvStream.get_statistics shadows the generic one; call the base class' explicitly
        completed, failures, underruns = self._aravis.Stream.get_statistics(self._stream)
        stats.update(completed=int(completed), failures=int(failures), underruns=int(underruns))
        if isinstance(self._stream, self._aravis.GvStream):
            resent, missing = self._aravis.GvStream.get_statistics(self._stream)
            stats.update(resent_packets=int(resent), missing_packets=int(missing))
        return stats

    # -- internals -------------------------------------------------------------------------------

    def _call(self, what: str, fn: Any, *args: Any) -> Any:
        from gi.repository import GLib

        try:
            return fn(*args)
        except GLib.Error as exc:
            raise CameraError(f"{what} failed on the camera at {self.address}: {exc.message}") from exc

    def _set_enum_if_available(self, feature: str, value: str) -> None:
        camera = self._camera
        if self._call(f"check {feature}", camera.is_feature_available, feature):
            self._call(f"set {feature}={value}", camera.set_string, feature, value)

    def _read_state(self) -> None:
        camera = self._camera
        name = self._call("read PixelFormat", camera.get_pixel_format_as_string)
        self._pixel_format = name if name in PIXEL_FORMATS else self._pixel_format
        self._exposure_us = float(self._call("read ExposureTime", camera.get_exposure_time))
        self._gain_db = float(self._call("read Gain", camera.get_gain))
        x, y, w, h = self._call("read the region", camera.get_region)
        self._region = (int(x), int(y), int(w), int(h))
        self._payload = int(self._call("read PayloadSize", camera.get_payload))

    def _start_stream(self) -> None:
        if self._acquiring:
            return
        camera = self._camera
        current = self._call("read PixelFormat", camera.get_pixel_format_as_string)
        if current not in PIXEL_FORMATS:
            raise CameraError(
                f"the camera at {self.address} is set to pixel format {current!r}, which is not a "
                f"polarisation mosaic format; call configure(pixel_format=...) with one of "
                f"{sorted(PIXEL_FORMATS)}"
            )
        self._read_state()
        if bayer_of(current) is not None:  # a region set by another program must keep the pattern too
            try:
                _check_colour_offsets(current, *self._region[:2])
            except ValueError as exc:
                raise CameraError(f"the camera at {self.address}: {exc}; call set_roi() first") from None
        stream = self._call("create the stream", camera.create_stream, None, None)
        if stream is None:
            raise CameraError(f"could not create a stream for the camera at {self.address}")
        if isinstance(stream, self._aravis.GvStream):
            if self._socket_buffer_bytes is None:
                stream.set_property("socket-buffer", self._aravis.GvStreamSocketBuffer.AUTO)
            else:
                stream.set_property("socket-buffer", self._aravis.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", int(self._socket_buffer_bytes))
        for _ in range(self._n_buffers):
            stream.push_buffer(self._aravis.Buffer.new_allocate(self._payload))
        self._stream = stream
        self._call("start acquisition", camera.start_acquisition)
        self._acquiring = True
        logger.debug("stream started: %s %dx%d, payload %d B", self._pixel_format,
                     self._region[2], self._region[3], self._payload)

    def _stop_stream(self) -> None:
        if self._acquiring and self._camera is not None:
            try:
                self._call("stop acquisition", self._camera.stop_acquisition)
            finally:
                self._acquiring = False
        self._acquiring = False
        # the stream must go before the camera (it holds the device's stream channel)
        self._stream = None

    def _wait_for_frame(self, timeout_s: float, earliest_ns: int, attempt: int) -> tuple[Frame | None, str]:
        stream = self._stream
        status_ok = self._aravis.BufferStatus.SUCCESS
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None, "TIMEOUT_NO_FRAME"
            buffer = stream.timeout_pop_buffer(max(1, int(remaining * 1e6)))
            if buffer is None:
                return None, "TIMEOUT_NO_FRAME"
            try:
                status = buffer.get_status()
                if status != status_ok:
                    logger.debug("dropped frame %d: %s", buffer.get_frame_id(), status.value_nick)
                    return None, status.value_nick.upper().replace("-", "_")
                # only complete frames carry a trustworthy id; gaps count the dropped ones
                raw_id = int(buffer.get_frame_id())
                count = self._counter.update(raw_id)
                if buffer.get_system_timestamp() < earliest_ns:
                    logger.debug("skipping stale frame %d", raw_id)
                    continue
                return self._to_frame(buffer, raw_id, count, attempt), ""
            finally:
                stream.push_buffer(buffer)

    def _to_frame(self, buffer: Any, raw_id: int, count: int, attempt: int) -> Frame:
        code = int(buffer.get_image_pixel_format())
        try:
            pixel_format = format_name_of(code)
        except ValueError as exc:
            raise CameraError(f"the camera at {self.address} sent a non-polarisation frame: {exc}") from exc
        width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
        data = buffer.get_data()
        if len(data) < payload_size(pixel_format, width, height):
            raise CameraError(
                f"frame {raw_id} holds {len(data)} bytes, fewer than a {width}x{height} {pixel_format} "
                "image needs (SIZE_MISMATCH): restart the stream after changing the format or ROI"
            )
        image = unpack_mosaic(data, pixel_format, width=width, height=height)  # (H, W) uint16
        x, y = self._region[0], self._region[1]
        return Frame(
            image=image,
            bayer=bayer_of(pixel_format),
            bit_depth=PIXEL_FORMATS[pixel_format][1],
            pixel_format=pixel_format,
            exposure_us=self._exposure_us,
            gain_db=self._gain_db,
            frame_id=raw_id,
            timestamp_ns=int(buffer.get_timestamp()),
            offset_xy=(x, y),
            metadata={
                "frame_count": count,
                "raw_frame_id": raw_id,
                "system_timestamp_ns": int(buffer.get_system_timestamp()),
                "attempts": attempt,
                "camera": {"vendor": self.vendor, "model": self.model, "serial": self.serial,
                           "address": self.address},
                "trigger": self._trigger,
            },
        )

    def _explain(self, failures: list[str], timeout_s: float, *, sent_triggers: bool) -> str:
        counts = Counter(failures)
        timeouts = counts.pop("TIMEOUT_NO_FRAME", 0)
        stats = self.stream_statistics()
        parts = []
        if counts:
            listed = ", ".join(f"{name} x{n}" for name, n in counts.most_common())
            parts.append(
                f"frames dropped {sum(counts.values())} times (buffer status {listed}; stream: {stats}): "
                "packets are being lost - lower the packet size or frame rate, set a "
                "DeviceLinkThroughputLimit, use a dedicated NIC with jumbo frames, or raise "
                "net.core.rmem_max"
            )
        if timeouts:
            if self._trigger == "line0":
                cause = ("no hardware trigger arrived on Line0: check the trigger wiring and signal "
                         "(rising edge), or use trigger='software'")
            elif self._trigger == "software" and not sent_triggers:
                cause = ("no trigger: the camera is in software-trigger mode and no TriggerSoftware "
                         "was sent (call trigger_software(), or capture() with send_trigger=True)")
            elif self._trigger == "software":
                cause = ("the camera did not deliver after TriggerSoftware: the link is too slow or "
                         "the stream is blocked (firewall, packet size above the MTU)")
            else:
                cause = ("the link is too slow or the stream is blocked (firewall, packet size above "
                         "the path MTU), or the frame rate is below 1/timeout")
            parts.append(f"no frame within {timeout_s} s {timeouts} times: {cause}")
        return (f"capture failed on the camera at {self.address} after {len(failures)} attempts "
                f"({self._pixel_format}, {self._region[2]}x{self._region[3]}, payload {self._payload} B): "
                + "; ".join(parts))

