"""A camera that renders its frames: the :class:`~polarshape.acquisition.camera.Camera` protocol
on top of polarshape's scene renderer and sensor model.

Usage::

    from polarshape.scene.config import load_scene_config
    with SimulatedCamera(load_scene_config("configs/scenes/sphere.yaml")) as cam:
        cam.configure(exposure_us=20000, pixel_format="PolarizeMono12")
        cam.set_light(3)
        frame = cam.capture()             # one raw mosaic, uint16 counts
        capture = cam.render_capture("out/sphere")   # every light + ground truth, written to disk
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from polarshape.acquisition.camera import CameraError, Frame
from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
from polarshape.imaging.pixels import PIXEL_FORMATS, bit_depth_of
from polarshape.checks import resolve_device, to_numpy
from polarshape.io.atomic import OutputExistsError
from polarshape.io.capture import CAPTURE_FORMAT, Capture, parse_capture_spec, write_capture
from polarshape.lights import light_to_dict
from polarshape.scene.render import (
    albedo_scale_map,
    mosaic_radiance,
    polariser_angle_map,
    shade_stokes,
)
from polarshape.scene.config import SceneConfig, load_scene_config
from polarshape.scene.objects import Scene
from polarshape.scene.raycast import GeometryBuffers, superpixel_ground_truth

logger = logging.getLogger(__name__)


class SimulatedCamera:
    """Renders raw polarisation mosaics of a scene file, one light at a time.

    Args:
        scene: a validated scene, or the path of a scene YAML file.
        device: torch device for rendering and noise (open3d ray casting always runs on the CPU);
            ``"auto"`` = cuda when available. A device torch cannot use raises
            :class:`~polarshape.errors.DeviceError` (see :func:`polarshape.checks.resolve_device`).
        seed: noise seed; None = ``scene.sensor.seed``. The n-th frame after :meth:`open` depends
            only on the seed, the settings and the lights chosen, so runs are bit-exact repeatable.
    """

    def __init__(self, scene: SceneConfig | str | Path, *, device: torch.device | str = "cpu", seed: int | None = None) -> None:
        self.config = scene if isinstance(scene, SceneConfig) else load_scene_config(scene)
        self.device = resolve_device(device)  # a missing GPU is an error here, before any work
        self.dtype = torch.float64 if self.config.render.dtype == "float64" else torch.float32
        self.seed = self.config.sensor.seed if seed is None else int(seed)
        self.sensor = self.config.sensor.to_model()
        self.layout = self.config.camera.mosaic.to_layout()
        self.exposure_us = float(self.config.camera.exposure_us)
        self.gain_db = float(self.config.camera.gain_db)
        self.pixel_format = self.config.camera.pixel_format
        self.light_index = 0
        self._scene: Scene | None = None
        self._geometry: GeometryBuffers | None = None
        self._albedo: Tensor | None = None
        self._angle_map: Tensor | None = None
        self._basis: Tensor | None = None
        self._radiance: dict[int, Tensor] = {}
        self._generator: torch.Generator | None = None
        self._frame_id = 0

    # --- Camera protocol ----------------------------------------------------------------------

    def open(self) -> None:
        """Build the scene (load/tessellate shapes) and ray cast the view once."""
        if self._scene is not None:
            return
        t0 = time.perf_counter()
        try:
            scene = self.config.build_scene()
        except ValueError as exc:
            raise CameraError(f"cannot build the simulated scene: {exc}") from exc
        geometry = scene.rasterize(device=self.device, dtype=self.dtype)
        self._scene, self._geometry = scene, geometry
        self._albedo = albedo_scale_map(scene, geometry)
        h, w = geometry.depth.shape
        self._angle_map = polariser_angle_map(self.layout, h, w, device=self.device, dtype=self.dtype)
        self._basis = sensor_plane_basis(geometry.view)
        self._generator = torch.Generator(device=self.device)
        self._generator.manual_seed(self.seed)
        self._frame_id = 0
        logger.info(
            "simulated camera open: %dx%d mosaic, %d objects, %d lights, %d object pixels (%.2f s)",
            w, h, len(scene.objects), len(scene.lights), int(geometry.mask.sum()), time.perf_counter() - t0,
        )

    def configure(
        self, *, exposure_us: float | None = None, gain_db: float | None = None, pixel_format: str | None = None
    ) -> None:
        """Set exposure (µs, scales the signal), gain (dB) and pixel format (bit depth 8/12/16)."""
        if exposure_us is not None:
            if not exposure_us > 0:
                raise CameraError(f"exposure_us must be > 0 microseconds, got {exposure_us}")
            self.exposure_us = float(exposure_us)
        if gain_db is not None:
            if not -20.0 <= gain_db <= 48.0:
                raise CameraError(f"gain_db must be within [-20, 48] dB, got {gain_db}")
            self.gain_db = float(gain_db)
        if pixel_format is not None:
            if pixel_format not in PIXEL_FORMATS:
                raise CameraError(f"pixel_format {pixel_format!r} is not supported; use one of {sorted(PIXEL_FORMATS)}")
            self.pixel_format = pixel_format

    def set_light(self, index: int) -> None:
        """Choose which light of the scene is on for the next :meth:`capture`."""
        n = len(self.config.lights)
        if not 0 <= index < n:
            raise CameraError(f"light index {index} is out of range; the scene has lights 0..{n - 1}")
        self.light_index = int(index)

    def capture(self, timeout_s: float = 5.0) -> Frame:
        """Render the current light, add sensor noise, quantise: one raw mosaic."""
        if self._scene is None:
            raise CameraError("the simulated camera is not open; call open() or use it as a context manager")
        radiance = self.radiance(self.light_index)  # (H, W)
        bit_depth = bit_depth_of(self.pixel_format)
        image = self.sensor.expose(
            radiance, exposure_us=self.exposure_us, gain_db=self.gain_db, bit_depth=bit_depth, generator=self._generator
        )
        frame = Frame(
            image=image,
            bit_depth=bit_depth,
            pixel_format=self.pixel_format,
            exposure_us=self.exposure_us,
            gain_db=self.gain_db,
            frame_id=self._frame_id,
            timestamp_ns=time.time_ns(),
            metadata={"light_index": self.light_index, "simulated": True, "seed": self.seed},
        )
        self._frame_id += 1
        return frame

    def close(self) -> None:
        """Drop the rendered state (idempotent)."""
        self._scene = None
        self._geometry = None
        self._albedo = None
        self._angle_map = None
        self._basis = None
        self._radiance.clear()
        self._generator = None

    def __enter__(self) -> SimulatedCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- simulator extras ---------------------------------------------------------------------

    @property
    def scene(self) -> Scene:
        """The built scene (camera open)."""
        if self._scene is None:
            raise CameraError("the simulated camera is not open")
        return self._scene

    @property
    def geometry(self) -> GeometryBuffers:
        """Per-pixel geometry of the view at raw-mosaic resolution (camera open)."""
        if self._geometry is None:
            raise CameraError("the simulated camera is not open")
        return self._geometry

    def radiance(self, light_index: int) -> Tensor:
        """Noise-free (H, W) mosaic radiance under one light (cached for the latest light)."""
        if light_index not in self._radiance:
            scene, geometry = self.scene, self.geometry
            assert self._albedo is not None and self._angle_map is not None and self._basis is not None
            stokes = shade_stokes(
                scene, geometry, scene.lights[light_index], shadows=self.config.render.shadows, albedo_scale=self._albedo
            )  # (3, H, W), per-pixel Stokes frames
            self._radiance = {light_index: mosaic_radiance(sensor_plane_stokes(stokes, basis=self._basis), self._angle_map)}
        return self._radiance[light_index]

    def ground_truth(self) -> dict[str, np.ndarray]:
        """Ground truth at super-pixel resolution: ``normals`` (H/2, W/2, 3) float32 (NaN off the
        object), ``depth`` (H/2, W/2) float32 (z, metres, NaN off the object), ``mask``
        (H/2, W/2) bool (super-pixels whose four sites all see the object)."""
        normals, depth, mask = superpixel_ground_truth(self.geometry, self.scene.object_mask(self.geometry))
        return {
            "normals": to_numpy(normals, np.float32),
            "depth": to_numpy(depth, np.float32),
            "mask": to_numpy(mask),
        }

    def render_capture(self, out_dir: str | Path | None = None, *, overwrite: bool = False, progress: bool = True) -> Capture:
        """Capture one frame per light with the current settings, plus ground truth.

        Args:
            out_dir: if given, the capture folder to write (atomically; refuses an existing
                folder unless ``overwrite``).
            overwrite: replace an existing ``out_dir``.
            progress: show a progress bar over the lights.

        Returns:
            The :class:`polarshape.io.capture.Capture` (ground truth: ``normals``, ``depth`` and
            ``scene``, the settings and scene it was rendered from).
        """
        if out_dir is not None and Path(out_dir).exists() and not overwrite:
            # fail before spending time on rendering; write_capture checks again atomically
            raise OutputExistsError(f"{out_dir} already exists; refusing to overwrite it (use overwrite=True / --overwrite)")
        opened_here = self._scene is None
        if opened_here:
            self.open()
        try:
            frames = []
            for index in tqdm(range(len(self.config.lights)), desc="lights", unit="light", disable=not progress):
                self.set_light(index)
                frames.append(self.capture())
            capture = self._make_capture(frames)
        finally:
            if opened_here:
                self.close()
        if out_dir is not None:
            write_capture(out_dir, capture, overwrite=overwrite)
        return capture

    def _make_capture(self, frames: list[Frame]) -> Capture:
        """Assemble the :class:`Capture` of one frame per light (all with the same settings)."""
        bit_depth = frames[0].bit_depth
        camera: dict[str, Any] = {
            "model": self.config.camera.model,
            "projection": self.config.camera.projection,
            "bit_depth": bit_depth,
            "black_level": self.sensor.black_level(bit_depth),
            "mosaic": self.config.camera.mosaic.model_dump(mode="json"),
        }
        if self.config.camera.intrinsics is not None and self.config.camera.projection == "perspective":
            camera["intrinsics"] = self.config.camera.intrinsics.model_dump()
        lights = []
        for k, light in enumerate(self.scene.lights):
            entry = light_to_dict(light)
            entry["frame"] = f"frames/{k:03d}.png"
            lights.append(entry)
        spec = parse_capture_spec({"format": CAPTURE_FORMAT, "camera": camera, "lights": lights}, "simulated capture.yaml")
        truth = self.ground_truth()
        provenance = {
            "simulator": "polarshape SimulatedCamera",
            "seed": self.seed,
            "exposure_us": self.exposure_us,
            "gain_db": self.gain_db,
            "pixel_format": self.pixel_format,
            "scene": self.config.model_dump(mode="json"),
        }
        return Capture(
            spec=spec,
            frames=np.stack([f.image.astype(np.uint16) for f in frames]),
            mask=truth["mask"],
            ground_truth={"normals": truth["normals"], "depth": truth["depth"], "scene": provenance},
        )
