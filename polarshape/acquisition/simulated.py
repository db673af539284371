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

import json
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from polarshape.acquisition.camera import CameraError, Frame
from polarshape.brdf.geometry import sensor_plane_basis, sensor_plane_stokes
from polarshape.imaging.pixels import PIXEL_FORMATS, bayer_of, bit_depth_of
from polarshape.checks import resolve_device, to_numpy
from polarshape.imaging.analyser import PolarimetricCalibration
from polarshape.imaging.mosaic import our_angle_deg
from polarshape.imaging.pixels import max_count
from polarshape.io.atomic import OutputExistsError, atomic_directory
from polarshape.io.images import write_image
from polarshape.io.polarimetric import write_polarimetric_calibration
from polarshape.io.capture import CAPTURE_FORMAT, CAPTURE_FORMAT_BRACKETS, Capture, parse_capture_spec, write_capture
from polarshape.lights import light_to_dict
from polarshape.scene.render import (
    albedo_scale_map,
    colour_albedo_map,
    mosaic_radiance,
    polariser_angle_map,
    shade_stokes,
)
from polarshape.scene.interreflection import HemisphereHits, hemisphere_hits, one_bounce_stokes
from polarshape.scene.config import SceneConfig, load_scene_config
from polarshape.scene.materials import colour_albedo_factors
from polarshape.scene.objects import Scene
from polarshape.scene.raycast import GeometryBuffers, superpixel_ground_truth
from polarshape.scene.sensor_defects import SensorMaps

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
        self.defects = self.config.sensor.to_defects()  # the real sensor's imperfections (ideal by default)
        self.layout = self.config.camera.mosaic.to_layout()
        self.bayer = self.config.camera.mosaic.bayer  # colour polarisation sensor, or None (mono)
        self.exposure_us = float(self.config.camera.reference_exposure_us)
        self.gain_db = float(self.config.camera.gain_db)
        self.pixel_format = self.config.camera.pixel_format
        self.light_index = 0
        self._scene: Scene | None = None
        self._geometry: GeometryBuffers | None = None
        self._albedo: Tensor | None = None
        self._angle_map: Tensor | None = None
        self._basis: Tensor | None = None
        self._maps: SensorMaps | None = None  # per-pixel analysers/gains/hot pixels; None = ideal sensor
        self._bounce: HemisphereHits | None = None  # render.interreflection's rays; None = direct light only
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
        if self.bayer is not None:  # a colour sensor: each pixel's body albedo is its own colour's
            self._albedo = self._albedo * colour_albedo_map(scene, geometry, self.bayer)
        h, w = geometry.depth.shape
        self._angle_map = polariser_angle_map(self.layout, h, w, device=self.device, dtype=self.dtype)
        self._basis = sensor_plane_basis(geometry.view)
        bounce = self.config.render.interreflection
        if bounce is not None:  # the hemisphere rays are cast once per view, for every light
            self._bounce = hemisphere_hits(scene, geometry, bounce.samples, seed=bounce.seed)
        if not self.defects.is_ideal:  # drawn once from sensor.defects_seed: the same camera for every frame
            self._maps = self.defects.draw(self.layout, h, w).to(self.device, self.dtype)
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
            if bayer_of(pixel_format) not in (None, self.bayer):
                raise CameraError(f"pixel_format {pixel_format} is a colour sensor's ({bayer_of(pixel_format)} Bayer "
                                  f"blocks) but the scene's camera.mosaic.bayer is {self.bayer}: set it, or use a "
                                  "PolarizeMono format")
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
        image = self._expose(radiance, bit_depth)
        frame = Frame(
            image=image,
            bayer=self.bayer,  # the sensor's: a colour scene records colour mosaics whatever the format's name
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
        self._maps = None
        self._bounce = None
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
            light = scene.lights[light_index]
            stokes = shade_stokes(
                scene, geometry, light, shadows=self.config.render.shadows, albedo_scale=self._albedo
            )  # (3, H, W), per-pixel Stokes frames
            if self._bounce is not None:  # light bounced once off the scene (render.interreflection)
                stokes = stokes + one_bounce_stokes(scene, geometry, self._bounce, light,
                                                    shadows=self.config.render.shadows, albedo_scale=self._albedo)
            self._radiance = {light_index: self._analyse(sensor_plane_stokes(stokes, basis=self._basis))}
        return self._radiance[light_index]

    def _analyse(self, stokes: Tensor) -> Tensor:
        """(…, H, W) radiance behind this sensor's analysers of (…, 3, H, W) sensor-plane Stokes."""
        assert self._angle_map is not None
        if self._maps is None:
            return mosaic_radiance(stokes, self._angle_map)
        return mosaic_radiance(stokes, self._maps.angle_rad, self._maps.diattenuation, self._maps.gain)

    def _expose(self, radiance: Tensor, bit_depth: int) -> np.ndarray:
        """Counts of one exposure of (H, W) analysed radiance with the current settings (hot pixels included)."""
        return self.sensor.expose(
            radiance, exposure_us=self.exposure_us, gain_db=self.gain_db, bit_depth=bit_depth, generator=self._generator,
            dark_counts_12bit=None if self._maps is None else self._maps.hot_level_12bit,
        )

    def sensor_truth(self, bit_depth: int | None = None) -> PolarimetricCalibration:
        """The true per-pixel analysers, gains, black level and defects of this camera (camera open),
        as the :class:`~polarshape.imaging.analyser.PolarimetricCalibration` a perfect bench
        calibration would find; black level in counts of ``bit_depth`` (default: the pixel format's)."""
        h, w = self.geometry.depth.shape
        bits = bit_depth_of(self.pixel_format) if bit_depth is None else int(bit_depth)
        black = self.sensor.black_level(bits)
        info = {"source": "polarshape SimulatedCamera (truth)", "defects_seed": self.defects.defects_seed}
        if self._maps is None:
            ideal = PolarimetricCalibration.ideal(self.layout, h, w, bit_depth=bits, black_level=black)
            return PolarimetricCalibration(angle_rad=ideal.angle_rad, diattenuation=ideal.diattenuation,
                                           gain=ideal.gain, black_level=ideal.black_level, defects=ideal.defects,
                                           bit_depth=bits, info=info)
        return self._maps.to_calibration(bit_depth=bits, black_level=black, info=info)

    def _sensor_maps_array(self, bit_depth: int) -> np.ndarray:
        """(2H, 2W, 5) float32 ground truth ``sensor_maps``: analyser angle (radians, our convention),
        diattenuation, gain, black level (counts of ``bit_depth``), defect (1 hot or dead, else 0)."""
        t = self.sensor_truth(bit_depth)
        stack = torch.stack([t.angle_rad, t.diattenuation, t.gain, t.black_level, t.defects.double()], dim=-1)
        return to_numpy(stack, np.float32)

    def render_calibration_frames(
        self,
        out_dir: str | Path,
        *,
        angles_deg: Sequence[float] = tuple(float(a) for a in range(0, 180, 10)),
        n_flat: int = 16,
        n_dark: int = 16,
        mount_offset_deg: float = 3.7,
        flat_fraction: float = 0.5,
        polariser_fraction: float = 0.8,
        overwrite: bool = False,
    ) -> Path:
        """Bench calibration frames of this camera (same sensor maps, noise and settings):
        ``flat/NNN.png`` (uniform unpolarised radiance), ``polariser/NNN.png`` (a uniform, fully
        linearly polarised source at each angle of ``polariser/angles.txt``), ``dark/NNN.png`` (no
        light) and ``truth.json`` + ``truth_polcal.npz`` (the mount offset and the sensor's true maps).

        The angles written are the polariser's dial readings in the maker's
        ``counterclockwise_on_screen`` convention; the true axis is the reading + ``mount_offset_deg``
        (an unknown mount zero, as on a real bench). The flat sits at ``flat_fraction`` of the range
        above black, the polariser's peak at about ``polariser_fraction``.

        Args:
            out_dir: folder to create (refused if it exists unless ``overwrite``).
            angles_deg: (M,) polariser dial readings, degrees (M ≥ 3 distinct angles mod 180).
            n_flat, n_dark: number of flat and dark frames (≥ 1).

        Returns:
            ``out_dir``.
        """
        out = Path(out_dir)
        angles = [float(a) for a in angles_deg]
        if len({round(a % 180.0, 9) for a in angles}) < 3 or not all(math.isfinite(a) for a in angles):
            raise ValueError(f"angles_deg needs at least 3 distinct finite polariser angles (mod 180°); got {angles}")
        if n_flat < 1 or n_dark < 1:
            raise ValueError(f"n_flat and n_dark must be >= 1; got {n_flat} and {n_dark}")
        if not (0 < flat_fraction < 1 and 0 < polariser_fraction < 1):
            raise ValueError("flat_fraction and polariser_fraction must lie in (0, 1)")
        if not math.isfinite(mount_offset_deg):
            raise ValueError(f"mount_offset_deg must be finite; got {mount_offset_deg}")
        opened_here = self._scene is None
        if opened_here:
            self.open()
        try:
            bits = bit_depth_of(self.pixel_format)
            h, w = self.geometry.depth.shape
            black = self.sensor.black_level(bits)
            counts_per_radiance = (self.sensor.mean_electrons(torch.ones((), dtype=torch.float64), self.exposure_us).item()
                                   / self.sensor.e_per_count(bits, self.gain_db))
            span = max_count(bits) - black
            # an unpolarised radiance L gives ½ g L behind every analyser
            flat_l = 2.0 * flat_fraction * span / counts_per_radiance
            pol_l = polariser_fraction * span / counts_per_radiance
            zero = torch.zeros((h, w), dtype=self.dtype, device=self.device)
            flat_stokes = torch.stack([zero + flat_l, zero, zero])  # (3, H, W)
            frames: dict[str, list[np.ndarray]] = {"flat": [], "polariser": [], "dark": []}
            flat_radiance = self._analyse(flat_stokes)
            for _ in range(n_flat):
                frames["flat"].append(self._expose(flat_radiance, bits))
            true_deg = [a + mount_offset_deg for a in angles]
            for a in true_deg:
                phi = math.radians(our_angle_deg(a, "counterclockwise_on_screen"))
                stokes = torch.stack([zero + pol_l, zero + pol_l * math.cos(2 * phi), zero + pol_l * math.sin(2 * phi)])
                frames["polariser"].append(self._expose(self._analyse(stokes), bits))
            dark_radiance = zero
            for _ in range(n_dark):
                frames["dark"].append(self._expose(dark_radiance, bits))
            truth = self.sensor_truth(bits)
        finally:
            if opened_here:
                self.close()
        with atomic_directory(out, overwrite=overwrite) as tmp:
            for name, images in frames.items():
                (tmp / name).mkdir()
                for k, image in enumerate(images):
                    write_image(tmp / name / f"{k:03d}.png", image)
            (tmp / "polariser" / "angles.txt").write_text("".join(f"{a:.6g}\n" for a in angles), encoding="utf-8")
            meta = {
                "simulator": "polarshape SimulatedCamera calibration frames",
                "angle_convention": "counterclockwise_on_screen",
                "mount_offset_deg": mount_offset_deg,
                "true_polariser_angles_deg": true_deg,
                "bit_depth": bits, "black_level": black, "pixel_format": self.pixel_format,
                "exposure_us": self.exposure_us, "gain_db": self.gain_db,
                "flat_radiance": flat_l, "polariser_radiance": pol_l, "seed": self.seed,
                "sensor": self.config.model_dump(mode="json")["sensor"],
            }
            (tmp / "truth.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
            write_polarimetric_calibration(tmp / "truth_polcal.npz", truth)
        logger.info("wrote calibration frames to %s: %d flat, %d polariser, %d dark", out, n_flat, len(angles), n_dark)
        return out

    def ground_truth(self) -> dict[str, np.ndarray]:
        """Ground truth at super-pixel resolution: ``normals`` (H/2, W/2, 3) float32 (NaN off the
        object), ``depth`` (H/2, W/2) float32 (z, metres, NaN off the object), ``mask``
        (H/2, W/2) bool (super-pixels whose four sites all see the object); ``materials`` (H/2, W/2)
        int16 when the scene has more than one material (:meth:`_material_truth`)."""
        normals, depth, mask = superpixel_ground_truth(self.geometry, self.scene.object_mask(self.geometry))
        truth = {
            "normals": to_numpy(normals, np.float32),
            "depth": to_numpy(depth, np.float32),
            "mask": to_numpy(mask),
        }
        if self.bayer is not None:
            truth["albedo_rgb"] = to_numpy(self._albedo_rgb(mask), np.float32)
        if len(self.scene.materials) > 1:
            truth["materials"] = to_numpy(self._material_truth(mask)).astype(np.int16)
        return truth

    def _material_truth(self, mask: Tensor) -> Tensor:
        """(H/2, W/2) int64 material of each super-pixel (numbered as
        :meth:`polarshape.scene.objects.Scene.material_index`): −2 where its four sites see two
        materials (a material edge), −1 off ``mask``."""
        index = self.scene.material_index(self.geometry)  # (2H, 2W)
        h2, w2 = index.shape
        blocks = index.reshape(h2 // 2, 2, w2 // 2, 2).permute(0, 2, 1, 3).reshape(h2 // 2, w2 // 2, 4)
        first = blocks[..., 0]
        same = (blocks == first[..., None]).all(-1)
        out = torch.where(same, first, torch.full_like(first, -2))
        return torch.where(mask, out, torch.full_like(first, -1))

    def _albedo_rgb(self, mask: Tensor) -> Tensor:
        """(H/2, W/2, 3) body albedo (k_b, or k_d for Lambertian/Baek) per colour channel R, G, B at
        super-pixel resolution (texture included, mean of the four sites; scene units), NaN off ``mask``."""
        scene, geometry = self.scene, self.geometry
        texture = albedo_scale_map(scene, geometry)  # (2H, 2W)
        rgb = torch.zeros(*texture.shape, 3, dtype=texture.dtype, device=texture.device)  # (2H, 2W, 3)
        materials = scene.material_index(geometry)  # (2H, 2W)
        for m, material in enumerate(scene.materials):
            sel = materials == m  # (2H, 2W)
            base = float(getattr(material, "k_b", getattr(material, "k_d", math.nan)))
            factors = texture.new_tensor(colour_albedo_factors(material)) * base  # (3,)
            rgb = torch.where(sel[..., None], texture[..., None] * factors, rgb)
        h2, w2 = texture.shape
        sp = rgb.reshape(h2 // 2, 2, w2 // 2, 2, 3).mean(dim=(1, 3))  # (H/2, W/2, 3)
        return torch.where(mask[..., None], sp, torch.full_like(sp, math.nan))

    def render_capture(self, out_dir: str | Path | None = None, *, overwrite: bool = False, progress: bool = True) -> Capture:
        """Capture one frame per light with the current settings, plus ground truth; with the scene's
        ``camera.exposures_us`` one frame per light and exposure (a format-2 capture whose reference
        exposure is the first of them; the camera's exposure is restored afterwards).

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
        exposures = self.config.camera.exposures_us
        saved = self.exposure_us
        try:
            frames: list[list[Frame]] = []
            for index in tqdm(range(len(self.config.lights)), desc="lights", unit="light", disable=not progress):
                self.set_light(index)
                if exposures is None:
                    frames.append([self.capture()])
                    continue
                bracket = []
                for exposure in exposures:
                    self.configure(exposure_us=exposure)
                    bracket.append(self.capture())
                frames.append(bracket)
            capture = self._make_capture(frames, bracketed=exposures is not None)
        finally:
            self.exposure_us = saved
            if opened_here:
                self.close()
        if out_dir is not None:
            write_capture(out_dir, capture, overwrite=overwrite)
        return capture

    def _make_capture(self, frames: list[list[Frame]], *, bracketed: bool = False) -> Capture:
        """Assemble the :class:`Capture` of the frames of each light (one, or one per exposure of the
        bracket when ``bracketed``: format 2, ``frames/NNN.png`` at the reference exposure and
        ``frames/NNN_bJ.png`` for bracket J)."""
        bit_depth = frames[0][0].bit_depth
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
            if bracketed:
                entry["exposure_us"] = frames[k][0].exposure_us
                entry["brackets"] = [{"frame": f"frames/{k:03d}_b{j}.png", "exposure_us": f.exposure_us}
                                     for j, f in enumerate(frames[k][1:], start=1)]
            lights.append(entry)
        fmt = CAPTURE_FORMAT_BRACKETS if bracketed else CAPTURE_FORMAT
        spec = parse_capture_spec({"format": fmt, "camera": camera, "lights": lights}, "simulated capture.yaml")
        truth = self.ground_truth()
        provenance = {
            "simulator": "polarshape SimulatedCamera",
            "seed": self.seed,
            "exposure_us": frames[0][0].exposure_us,
            "gain_db": self.gain_db,
            "pixel_format": self.pixel_format,
            "scene": self.config.model_dump(mode="json"),
        }
        return Capture(
            spec=spec,
            frames=np.stack([light[0].image.astype(np.uint16) for light in frames]),
            brackets=(np.stack([[f.image.astype(np.uint16) for f in light[1:]] for light in frames])
                      if bracketed and len(frames[0]) > 1 else None),
            mask=truth["mask"],
            ground_truth={"normals": truth["normals"], "depth": truth["depth"], "scene": provenance,
                          **({"albedo_rgb": truth["albedo_rgb"]} if "albedo_rgb" in truth else {}),
                          **({"materials": truth["materials"]} if "materials" in truth else {}),
                          **({"sensor_maps": self._sensor_maps_array(bit_depth)} if self._maps is not None else {})},
        )
