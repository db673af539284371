"""Capture sessions: one raw mosaic per light, written as a polarshape capture folder.

:func:`run_capture_session` switches the lights of a :class:`~.lights.LightRig` one at a time,
captures with any :class:`~.camera.Camera` (averaging frames, optionally bracketing the exposure
to avoid saturation), saves each light's frame atomically as soon as it is captured, resumes an
interrupted session by skipping lights whose frames are on disk, and finally writes
``capture.yaml`` (format ``polarshape-capture/1``, or ``/2`` with ``exposures_us``; see
docs/capture-format.md).

:func:`capture_session` does the same from a session YAML file (what ``polarshape capture
session.yaml --out DIR`` runs)::

    camera:
      backend: aravis            # aravis | simulated | fake_gige (test camera on 127.0.0.1)
      address: 192.168.1.20      # aravis: IP address (preferred) or Aravis device id
      trigger: software          # off | software | line0
      packet_size: 9000          # optional
      pixel_format: PolarizeMono12p  # a colour TRI050S-QC: BayerRG12p (capture.yaml gets mosaic.bayer RGGB)
      exposure_us: 20000
      gain_db: 0.0
      roi: [0, 0, 2448, 2048]    # optional, x y width height
      projection: perspective    # default orthographic; goes into capture.yaml's camera block
      intrinsics: {fx: 2500, fy: 2500, cx: 1224, cy: 1024}   # raw pixels; needed for perspective
    rig:
      type: serial               # simulated | manual | serial
      port: /dev/ttyACM0         # serial
      strobe: false              # camera ExposureActive on Line1
    lights:                      # direction (unit vector to the light) or position (m), camera frame;
      - {direction: [0.3, -0.2, -0.93]}                  # optional with a simulated scene
      - {direction: [-0.3, -0.2, -0.93], intensity: 1.0}
    capture:
      frames_per_light: 4
      exposure_bracket: [5000, 10000, 20000, 40000]   # optional, µs: pick ONE per light (auto-exposure)
      # exposures_us: [8000, 1000, 125]   # optional, µs: take EVERY one per light (HDR brackets)

Two ways to use several exposures: ``exposure_bracket`` *chooses* one exposure per light (the
longest with fewer than 0.1 % saturated pixels; the light's ``intensity`` is scaled by its exposure)
and writes format 1; ``exposures_us`` *takes* every exposure under every light (the first is the
reference exposure) and writes format 2 (``frames/NNN.png`` at the reference, ``frames/NNN_bJ.png``
for the J-th other exposure), which preprocessing merges into one radiance per site
(:mod:`polarshape.recover.hdr`). They exclude each other.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from polarshape.acquisition.camera import Camera, CameraError, Frame
from polarshape.acquisition.lights import LightRig, RigLight
from polarshape.errors import CaptureError, ConfigError
from polarshape.imaging.pixels import PIXEL_FORMATS, bayer_of
from polarshape.io.atomic import OutputExistsError, atomic_path, atomic_write_text
from polarshape.io.capture import CAPTURE_FORMAT, CAPTURE_FORMAT_BRACKETS, Distortion, IntrinsicsSpec, LightSpec, MosaicSpec, Projection
from polarshape.io.yamlfile import load_yaml

logger = logging.getLogger(__name__)

__all__ = [
    "SATURATION_LIMIT",
    "SessionConfig",
    "average_frames",
    "capture_session",
    "load_session_config",
    "refuse_capture_destination",
    "run_capture_session",
    "saturated_fraction",
]

#: Largest fraction of saturated pixels an exposure of a bracket may have to be chosen.
SATURATION_LIMIT = 0.001


def saturated_fraction(frame: Frame) -> float:
    """Fraction of pixels of ``frame.image`` at the top count ``2**bit_depth - 1``."""
    top = (1 << frame.bit_depth) - 1
    return float(np.count_nonzero(frame.image >= top)) / max(1, frame.image.size)


def average_frames(frames: Sequence[Frame]) -> np.ndarray:
    """Mean of the frames' mosaics, rounded to whole counts.

    Args:
        frames: N >= 1 frames of one (H, W) shape and bit depth.

    Returns:
        (H, W) ``uint16`` mean, in counts (rounding costs at most half a count).
    """
    if not frames:
        raise ValueError("average_frames needs at least one frame")
    shape = frames[0].image.shape
    for f in frames:
        if f.image.shape != shape or f.bit_depth != frames[0].bit_depth:
            raise ValueError(f"frames to average differ: shape {f.image.shape} / {f.bit_depth} bit vs "
                             f"{shape} / {frames[0].bit_depth} bit")
    total = np.zeros(shape, dtype=np.float64)  # (H, W)
    for f in frames:
        total += f.image
    return np.rint(total / len(frames)).astype(np.uint16)


def _write_png(path: Path, image: np.ndarray, bit_depth: int, *, overwrite: bool) -> None:
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    with atomic_path(path, overwrite=overwrite) as tmp:
        if not cv2.imwrite(str(tmp), image.astype(dtype)):
            raise OSError(f"could not encode {path} as PNG")


def _bracket_png(index: int, j: int) -> str:
    """File name of light ``index``'s frame at the ``j``-th exposure of ``exposures_us`` (0: the reference)."""
    return f"{index:03d}.png" if j == 0 else f"{index:03d}_b{j}.png"


def _light_done(frames_dir: Path, index: int) -> dict[str, Any] | None:
    png, meta = frames_dir / f"{index:03d}.png", frames_dir / f"{index:03d}.json"
    if png.exists() and meta.exists():
        try:
            done = json.loads(meta.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        brackets = done.get("brackets", []) if isinstance(done, dict) else []
        if all((frames_dir / b.get("frame", "")).is_file() for b in brackets):  # the JSON is written last
            return done
    return None


def _capture_light(
    camera: Camera,
    *,
    frames_per_light: int,
    bracket: Sequence[float] | None,
    saturation_limit: float,
    timeout_s: float,
) -> tuple[list[Frame], dict[str, Any]]:
    """Frames of one light: choose the exposure (longest with few saturated pixels), then average."""
    info: dict[str, Any] = {}
    first: Frame | None = None
    if bracket:
        tried = []
        for exposure in sorted(bracket, reverse=True):
            camera.configure(exposure_us=float(exposure))
            first = camera.capture(timeout_s=timeout_s)
            fraction = saturated_fraction(first)
            tried.append({"exposure_us": first.exposure_us, "saturated_fraction": fraction})
            if fraction < saturation_limit:
                break
        else:
            logger.warning("every exposure of the bracket saturates more than %.2f %% of the pixels; using "
                           "the shortest (%s µs): lower the gain or the light", 100 * saturation_limit,
                           min(bracket))
        info["bracket"] = tried
    frames = [first] if first is not None else []
    while len(frames) < frames_per_light:
        frames.append(camera.capture(timeout_s=timeout_s))
    return frames, info


#: What a resumed session must share with the frames already on disk (``frames/session.json``).
SESSION_FILE = "session.json"


def session_identity(rig: LightRig, *, frames_per_light: int, exposure_bracket: Sequence[float] | None,
                     settings: Mapping[str, Any] | None = None,
                     exposures_us: Sequence[float] | None = None) -> dict[str, Any]:
    """The settings that make frames of one session comparable: the lights (direction or position,
    intensity), frames per light, the exposure bracket, the exposures taken per light, and the
    camera ``settings`` given (pixel format, exposure, gain, ROI; None values left out)."""
    lights = []
    for light in rig.lights:
        entry: dict[str, Any] = {"intensity": float(light.intensity)}
        if light.direction is not None:
            entry["direction"] = [round(float(c), 9) for c in light.direction]
        else:
            entry["position"] = [round(float(c), 9) for c in light.position]
        lights.append(entry)
    camera = {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in (settings or {}).items() if v is not None}
    bracket = None if exposure_bracket is None else [float(e) for e in exposure_bracket]
    identity = {"lights": lights, "frames_per_light": int(frames_per_light), "exposure_bracket": bracket,
                "camera": camera}
    if exposures_us is not None:  # (absent otherwise: session.json of earlier versions stays comparable)
        identity["exposures_us"] = [float(e) for e in exposures_us]
    return identity


def _identity_difference(stored: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """The first field where two session identities differ, as ``field: stored → current``, or None."""
    if len(stored.get("lights", [])) != len(current["lights"]):
        return f"lights: {len(stored.get('lights', []))} lights on disk, {len(current['lights'])} in this session"
    for i, (a, b) in enumerate(zip(stored["lights"], current["lights"])):
        if a != b:
            return f"lights[{i}]: {a} on disk, {b} in this session"
    for key in ("frames_per_light", "exposure_bracket", "exposures_us"):
        if stored.get(key) != current.get(key):
            return f"capture.{key}: {stored.get(key)} on disk, {current.get(key)} in this session"
    keys = sorted(set(stored.get("camera", {})) | set(current["camera"]))
    for key in keys:
        a, b = stored.get("camera", {}).get(key), current["camera"].get(key)
        if a != b:
            return f"camera.{key}: {a} on disk, {b} in this session"
    return None


def _check_resume(frames_dir: Path, identity: dict[str, Any], n: int) -> bool:
    """Before a resumed session captures anything: True when frames of an earlier run are on disk.

    Raises:
        CaptureError: the earlier run's session differs (lights, ROI, pixel format, exposure, …),
            naming the field, so that no frame of the new session is mixed with the old ones.
    """
    if not any(_light_done(frames_dir, i) is not None for i in range(n)):
        return False
    stored_path = frames_dir / SESSION_FILE
    if not stored_path.exists():
        logger.warning("%s holds frames without %s (an older polarshape): resuming without checking that the "
                       "session is the same", frames_dir, SESSION_FILE)
        return True
    stored = json.loads(stored_path.read_text(encoding="utf-8"))
    difference = _identity_difference(stored, identity)
    if difference is not None:
        raise CaptureError(f"{frames_dir}: cannot resume, the frames on disk come from another session ({difference}); "
                           "use the same session file, or another --out (or --no-resume into an empty folder)")
    return True


def _frame_metadata(frames: Sequence[Frame], extra: Mapping[str, Any]) -> dict[str, Any]:
    last = frames[-1]
    return {
        "exposure_us": float(last.exposure_us),
        "gain_db": float(last.gain_db),
        "pixel_format": last.pixel_format,
        "bit_depth": int(last.bit_depth),
        "frames_averaged": len(frames),
        "frame_ids": [int(f.frame_id) for f in frames],
        "frame_counts": [int(f.metadata.get("frame_count", f.frame_id)) for f in frames],
        "timestamps_ns": [int(f.timestamp_ns) for f in frames],
        "offset_xy": [int(v) for v in last.offset_xy],
        "bayer": last.bayer,
        "saturated_fraction": saturated_fraction(last),
        **extra,
    }


def refuse_capture_destination(out_dir: str | Path, *, resume: bool) -> None:
    """Refuse, before any camera is opened, a capture folder a session without ``resume`` may not
    write into: its capture.yaml exists, or its ``frames/`` already holds frames. (With ``resume``,
    :func:`run_capture_session` decides once it knows the lights: a complete capture is returned
    as it is, an incomplete one with a capture.yaml is refused.)

    Raises:
        OutputExistsError: as above, naming the file and the fix.
    """
    out = Path(out_dir)
    frames_dir, capture_yaml = out / "frames", out / "capture.yaml"
    if capture_yaml.exists() and not resume:
        raise OutputExistsError(f"{capture_yaml} already exists; choose another --out folder")
    if not resume and frames_dir.exists() and any(frames_dir.iterdir()):
        raise OutputExistsError(f"{frames_dir} already holds frames; pass resume=True to continue that "
                                "session, or choose another output folder")


def run_capture_session(
    camera: Camera,
    rig: LightRig,
    out_dir: str | Path,
    *,
    frames_per_light: int = 1,
    exposure_bracket: Sequence[float] | None = None,
    exposures_us: Sequence[float] | None = None,
    resume: bool = True,
    camera_info: Mapping[str, Any] | None = None,
    settings: Mapping[str, Any] | None = None,
    saturation_limit: float = SATURATION_LIMIT,
    timeout_s: float = 5.0,
) -> Path:
    """Capture one raw mosaic per light into the capture folder ``out_dir``.

    For each light: ``rig.switch(i)``; with ``exposure_bracket`` the longest exposure whose
    frame has fewer than ``saturation_limit`` (0.1 %) saturated pixels is chosen; then
    ``frames_per_light`` frames are averaged and saved at once to ``frames/NNN.png`` (8- or
    16-bit PNG, counts) with ``frames/NNN.json`` (exposure, frame ids, …), each atomically. When
    ``resume`` is true, lights whose two files exist are skipped, so a session interrupted by an
    error or Ctrl-C continues where it stopped. Finally all lights are switched off and
    ``capture.yaml`` is written; a light captured at a shorter exposure gets a proportionally
    lower ``intensity`` (intensity = rig intensity x exposure / longest exposure), so the
    frames stay comparable.

    Args:
        camera: an opened or openable camera (opened here if it has ``open``).
        rig: the lights.
        out_dir: capture folder (created; an existing complete capture is returned as is when
            resuming, refused otherwise).
        frames_per_light: frames averaged per light (>= 1).
        exposure_bracket: candidate exposure times in µs, or None to keep the camera's.
        exposures_us: exposure times (µs) to take EVERY one of under each light (HDR brackets; the
            first is the reference exposure), each averaged over ``frames_per_light`` frames and
            saved as ``frames/NNN.png`` (reference) and ``frames/NNN_bJ.png``; capture.yaml is then
            format 2. Excludes ``exposure_bracket``.
        resume: skip lights already on disk (otherwise existing frames are an error).
        camera_info: extra keys of capture.yaml's ``camera`` block (``projection``,
            ``intrinsics``, ``distortion``, ``model``, ``black_level``, ``mosaic``).
        settings: the camera settings of the session (``pixel_format``, ``exposure_us``,
            ``gain_db``, ``roi``): recorded with the frames (:func:`session_identity`, in
            ``frames/session.json``) and, when resuming, required to match those of the frames on
            disk, as are the lights, ``frames_per_light`` and ``exposure_bracket``.
        saturation_limit: see above.
        timeout_s: per-frame capture timeout.

    Returns:
        The path of the written ``capture.yaml``.
    """
    if frames_per_light < 1:
        raise ValueError(f"frames_per_light must be >= 1; got {frames_per_light}")
    if exposure_bracket is not None and (not exposure_bracket or min(exposure_bracket) <= 0):
        raise ValueError(f"exposure_bracket must be a non-empty list of positive µs values; got {exposure_bracket}")
    if exposures_us is not None:
        _check_exposures(exposures_us)
        if exposure_bracket is not None:
            raise ValueError("capture.exposure_bracket (pick one exposure per light) and capture.exposures_us (take "
                             "every exposure per light) exclude each other: keep one")
    info = dict(camera_info or {})
    if info.get("projection") == "perspective" and not info.get("intrinsics"):
        raise ValueError("camera projection 'perspective' needs intrinsics {fx, fy, cx, cy} (raw-mosaic pixels): run "
                         "`polarshape calibrate intrinsics` first, or use projection 'orthographic'")
    for index, spec in enumerate(rig.lights):
        if spec.direction is not None and not spec.direction[2] < 0:
            raise ValueError(f"light {index}: direction {spec.direction} has z >= 0 (behind the object); directions "
                             "point from the object to the light, camera frame (z forward), so lights have z < 0")
    out = Path(out_dir)
    frames_dir = out / "frames"
    capture_yaml = out / "capture.yaml"
    n = rig.n_lights
    if capture_yaml.exists():
        if resume and all(_light_done(frames_dir, i) is not None for i in range(n)):
            logger.info("%s is complete; nothing to capture", capture_yaml)
            return capture_yaml
        raise OutputExistsError(f"{capture_yaml} already exists; choose another --out folder")
    refuse_capture_destination(out, resume=resume)
    identity = session_identity(rig, frames_per_light=frames_per_light, exposure_bracket=exposure_bracket,
                                settings=settings, exposures_us=exposures_us)
    if not (resume and _check_resume(frames_dir, identity, n)):
        frames_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(frames_dir / SESSION_FILE, json.dumps(identity, indent=1), overwrite=True)
    if callable(getattr(camera, "open", None)):
        camera.open()

    metadata: list[dict[str, Any]] = []
    for index in range(n):
        done = _light_done(frames_dir, index) if resume else None
        if done is not None:
            logger.info("light %d/%d already captured; skipping", index + 1, n)
            metadata.append(done)
            continue
        rig.switch(index)
        brackets: list[dict[str, Any]] = []
        for j, exposure in enumerate(exposures_us or ()):
            if j == 0:
                continue  # the reference exposure: taken last, below, so the camera ends at it
            camera.configure(exposure_us=float(exposure))
            frames = [camera.capture(timeout_s=timeout_s) for _ in range(frames_per_light)]
            name = _bracket_png(index, j)
            bracket_meta = _frame_metadata(frames, {"frame": name})
            _write_png(frames_dir / name, average_frames(frames), bracket_meta["bit_depth"], overwrite=True)
            brackets.append(bracket_meta)
        if exposures_us:
            camera.configure(exposure_us=float(exposures_us[0]))
        frames, info = _capture_light(camera, frames_per_light=frames_per_light, bracket=exposure_bracket,
                                      saturation_limit=saturation_limit, timeout_s=timeout_s)
        image = average_frames(frames)  # (H, W) uint16
        meta = _frame_metadata(frames, {"light_index": index, **info, **({"brackets": brackets} if brackets else {})})
        png = frames_dir / f"{index:03d}.png"
        _write_png(png, image, meta["bit_depth"], overwrite=True)  # a PNG without its JSON is a leftover
        atomic_write_text(frames_dir / f"{index:03d}.json", json.dumps(meta, indent=1), overwrite=True)
        logger.info("light %d/%d: %d frame(s) at %.0f µs, %.3f %% saturated", index + 1, n, len(frames),
                    meta["exposure_us"], 100 * meta["saturated_fraction"])
        metadata.append(meta)
    rig.all_off()

    document = _capture_document(camera, rig, metadata, camera_info, bracketed=exposures_us is not None)
    atomic_write_text(capture_yaml, yaml.safe_dump(document, sort_keys=False))
    logger.info("wrote %s (%d lights)", capture_yaml, n)
    return capture_yaml


def _check_exposures(exposures_us: Sequence[float]) -> None:
    values = [float(e) for e in exposures_us]
    if not values or not all(e > 0 and e == e and e != float("inf") for e in values):
        raise ValueError(f"capture.exposures_us must be a non-empty list of positive exposure times in µs, e.g. "
                         f"[8000, 1000, 125] (the first is the reference exposure); got {list(exposures_us)}")
    if len(set(values)) != len(values):
        raise ValueError(f"capture.exposures_us repeats an exposure time ({values}): list each once (frames_per_light "
                         "averages repeated frames)")


def _capture_document(camera: Camera, rig: LightRig, metadata: list[dict[str, Any]],
                      camera_info: Mapping[str, Any] | None, *, bracketed: bool = False) -> dict[str, Any]:
    bit_depths = {m["bit_depth"] for m in metadata} | {b["bit_depth"] for m in metadata for b in m.get("brackets", [])}
    if len(bit_depths) != 1:
        raise CameraError(f"the frames of this session have different bit depths {sorted(bit_depths)}: "
                          "recapture with one pixel format")
    bayers = {m.get("bayer") for m in metadata}  # frames of an older polarshape have none: mono
    if len(bayers) != 1:
        raise CameraError(f"the frames of this session have different colour mosaics {sorted(map(str, bayers))} "
                          "(camera.mosaic.bayer): recapture with one pixel format and ROI")
    bayer = bayers.pop()
    longest = max(m["exposure_us"] for m in metadata)
    model = getattr(camera, "model", "") or type(camera).__name__
    block: dict[str, Any] = {"model": str(model), "projection": "orthographic", "bit_depth": bit_depths.pop(),
                             "black_level": 0, "mosaic": MosaicSpec(bayer=bayer).model_dump(mode="json")}
    block.update(dict(camera_info or {}))
    given = MosaicSpec.model_validate(block["mosaic"]).bayer
    if given != bayer:
        raise CameraError(f"camera_info mosaic.bayer {given} contradicts the frames' colour mosaic {bayer} "
                          "(the pixel format's): drop mosaic.bayer from camera_info or recapture")
    lights = []
    for index, (spec, meta) in enumerate(zip(rig.lights, metadata, strict=True)):
        entry = spec.to_capture_entry()
        entry.pop("name", None)
        entry["intensity"] = float(spec.intensity * meta["exposure_us"] / longest)
        entry["frame"] = f"frames/{index:03d}.png"
        if bracketed:
            entry["exposure_us"] = float(meta["exposure_us"])
            entry["brackets"] = [{"frame": f"frames/{b['frame']}", "exposure_us": float(b["exposure_us"])}
                                 for b in meta.get("brackets", [])]
        lights.append(entry)
    return {"format": CAPTURE_FORMAT_BRACKETS if bracketed else CAPTURE_FORMAT, "camera": block, "lights": lights}


# -- session files --------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class CameraSection(_Strict):
    """``camera:`` of a session file: the backend's settings, and the capture.yaml ``camera`` fields
    it passes on (``projection``, ``intrinsics``, ``distortion``, ``black_level``, ``model``; the
    capture format's types)."""

    backend: Literal["aravis", "simulated", "fake_gige"]
    address: str | None = None
    scene: str | None = None
    trigger: Literal["off", "software", "line0"] = "software"
    packet_size: int | None = None
    frame_rate_hz: float | None = None
    pixel_format: str | None = None
    exposure_us: float | None = Field(None, gt=0)
    gain_db: float | None = None
    roi: tuple[int, int, int, int] | None = None
    projection: Projection = "orthographic"
    intrinsics: IntrinsicsSpec | None = None
    distortion: Distortion | None = None
    black_level: float = 0
    model: str | None = None

    @model_validator(mode="after")
    def _check(self) -> CameraSection:
        if self.backend == "aravis" and not self.address:
            raise ValueError("camera.address is required for backend 'aravis' (the camera's IP address)")
        if self.backend == "simulated" and not self.scene:
            raise ValueError("camera.scene (a scene YAML file) is required for backend 'simulated'")
        if self.projection == "perspective" and self.intrinsics is None:
            raise ValueError("camera.intrinsics {fx, fy, cx, cy} is required with projection 'perspective' (run "
                             "`polarshape calibrate intrinsics` first), or set projection: orthographic")
        if self.pixel_format is not None and self.pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"camera.pixel_format {self.pixel_format!r}: use one of {sorted(PIXEL_FORMATS)}")
        return self


class LightEntry(LightSpec):
    """One light of ``lights:``: a :class:`~polarshape.io.capture.LightSpec` with a free label."""

    name: str = ""

    def to_rig_light(self) -> RigLight:
        return RigLight(direction=self.direction, position=self.position, intensity=self.intensity, name=self.name)


class RigSection(_Strict):
    """``rig:`` of a session file."""

    type: Literal["simulated", "manual", "serial"]
    port: str | None = None
    baudrate: int = 115200
    settle_s: float = Field(0.05, ge=0)
    strobe: bool = False

    @model_validator(mode="after")
    def _check(self) -> RigSection:
        if self.type == "serial" and not self.port:
            raise ValueError("rig.port is required for rig type 'serial' (e.g. /dev/ttyACM0)")
        return self


class CaptureSection(_Strict):
    """``capture:`` of a session file."""

    frames_per_light: int = Field(1, ge=1)
    exposure_bracket: list[float] | None = None
    #: HDR brackets: take every one of these exposures (µs) under each light, the first the reference
    #: (capture format 2); excludes ``exposure_bracket``.
    exposures_us: list[float] | None = None
    timeout_s: float = Field(5.0, gt=0)

    @model_validator(mode="after")
    def _check(self) -> CaptureSection:
        if self.exposures_us is not None:
            _check_exposures(self.exposures_us)
            if self.exposure_bracket is not None:
                raise ValueError("capture.exposure_bracket (pick one exposure per light) and capture.exposures_us (take "
                                 "every exposure per light) exclude each other: keep one")
        return self


class SessionConfig(_Strict):
    """A capture session file (see the module docstring)."""

    camera: CameraSection
    rig: RigSection
    lights: list[LightEntry] = []
    capture: CaptureSection = Field(default_factory=lambda: CaptureSection.model_validate({}))

    @model_validator(mode="after")
    def _check(self) -> SessionConfig:
        if not self.lights and not (self.rig.type == "simulated" and self.camera.backend == "simulated"):
            raise ValueError("lights: list one entry per light (direction or position, camera frame); only "
                             "a simulated scene can supply its own")
        return self


def load_session_config(path: str | Path) -> SessionConfig:
    """Read and validate a session YAML file; errors name the file and the field."""
    path = Path(path)
    data = load_yaml(path, error=ConfigError)  # unreadable, not YAML, or a key given twice
    try:
        return SessionConfig.model_validate(data)
    except ValidationError as exc:
        raise ValueError(f"{path}: invalid session file:\n{exc}") from exc


def _lights_of(config: SessionConfig, camera: Any) -> list[RigLight]:
    if config.lights:
        return [entry.to_rig_light() for entry in config.lights]
    # a simulated scene knows its lights
    scene_lights = getattr(getattr(camera, "config", None), "lights", None)
    if not scene_lights:
        raise ValueError("lights is empty and the camera has no scene lights: list the lights")
    specs = []
    for light in scene_lights:
        light = light.to_light() if hasattr(light, "to_light") else light
        specs.append(RigLight(direction=getattr(light, "direction", None), position=getattr(light, "position", None),
                               intensity=float(getattr(light, "intensity", 1.0)) or 1.0))
    return specs


def capture_session(
    session_yaml: str | Path,
    out_dir: str | Path,
    *,
    resume: bool = True,
    input_fn: Callable[[str], str] = input,
) -> Path:
    """Run the capture session described by ``session_yaml`` into ``out_dir``.

    Returns the path of the written ``capture.yaml``. ``input_fn`` answers a manual rig's prompts.
    """
    from polarshape.acquisition.lights import ManualLightRig, SerialLightRig, SimulatedLightRig

    config = load_session_config(session_yaml)
    refuse_capture_destination(out_dir, resume=resume)  # before the camera is opened or the scene loaded
    cam_cfg, rig_cfg = config.camera, config.rig
    with ExitStack() as stack:
        camera: Any
        light_target: Any = None
        if cam_cfg.backend == "simulated":
            from polarshape.acquisition.simulated import SimulatedCamera

            scene = Path(cam_cfg.scene or "")
            if not scene.is_absolute():
                scene = Path(session_yaml).parent / scene
            camera = stack.enter_context(SimulatedCamera(scene))
        else:
            from polarshape.acquisition.aravis import AravisCamera

            address = cam_cfg.address or "127.0.0.1"
            if cam_cfg.backend == "fake_gige":
                from polarshape.acquisition.fake_gige import FakeGigECamera

                # the fake's synthetic scene follows a simulated rig; a colour format makes it a TRI050S-QC
                colour = cam_cfg.pixel_format is not None and bayer_of(cam_cfg.pixel_format) is not None
                light_target = stack.enter_context(FakeGigECamera(
                    address, model="TRI050S-QC" if colour else "TRI050S-PC", width=256, height=256))
            camera = stack.enter_context(AravisCamera(
                address, trigger=cam_cfg.trigger, packet_size=cam_cfg.packet_size,
                frame_rate_hz=cam_cfg.frame_rate_hz))
        camera.configure(exposure_us=cam_cfg.exposure_us, gain_db=cam_cfg.gain_db, pixel_format=cam_cfg.pixel_format)
        if cam_cfg.roi is not None:
            if not hasattr(camera, "set_roi"):
                raise ValueError(f"camera.roi: the {cam_cfg.backend} backend has no region of interest")
            camera.set_roi(*cam_cfg.roi)
        specs = _lights_of(config, camera)
        strobe = camera if rig_cfg.strobe else None
        rig: Any
        if rig_cfg.type == "simulated":
            rig = SimulatedLightRig(light_target or camera, specs, strobe_camera=strobe)
        elif rig_cfg.type == "manual":
            rig = ManualLightRig(specs, input_fn=input_fn, strobe_camera=strobe)
        else:
            rig = SerialLightRig(rig_cfg.port or "", specs, baudrate=rig_cfg.baudrate,
                                 settle_s=rig_cfg.settle_s, strobe_camera=strobe)
        stack.enter_context(rig)
        info: dict[str, Any] = {"projection": cam_cfg.projection, "black_level": cam_cfg.black_level}
        if cam_cfg.model:
            info["model"] = cam_cfg.model
        if cam_cfg.intrinsics is not None:
            info["intrinsics"] = cam_cfg.intrinsics.model_dump()
        if cam_cfg.distortion is not None:
            info["distortion"] = list(cam_cfg.distortion)
        return run_capture_session(
            camera, rig, out_dir, frames_per_light=config.capture.frames_per_light,
            exposure_bracket=config.capture.exposure_bracket, exposures_us=config.capture.exposures_us,
            resume=resume, camera_info=info,
            settings={"pixel_format": cam_cfg.pixel_format, "exposure_us": cam_cfg.exposure_us,
                      "gain_db": cam_cfg.gain_db, "roi": cam_cfg.roi},
            timeout_s=config.capture.timeout_s,
        )
