"""Scene files (YAML) for the simulated camera: validated once here, turned into typed objects.

A scene file holds ``camera``, ``sensor``, ``objects`` and ``lights`` (see configs/scenes/*.yaml,
whose comments document every field). Units: metres, microseconds, degrees only where a field
name says ``_deg``. Frames: the camera frame (OpenCV: x right, y down, z forward). Relative file
paths (meshes, texture images, material files) are relative to the scene file's folder.

An object's ``material`` is given inline (``{model: fmbrdf, ior: ..., ...}``) or as a file,
``{file: material.json}`` (:mod:`polarshape.io.material`, e.g. measured by ``polarshape material``):
read and checked when the scene is, rendered as :func:`polarshape.scene.materials.material_from_file` says.
An object of two materials adds ``split: {normal: [x, y, z], offset: metres, material: {...}}``: the
points beyond that plane (through the shape's centre, moved by ``offset`` along the normal) take the
second material (configs/scenes/two_materials_blob.yaml).
"""

from __future__ import annotations

import math
from dataclasses import fields
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError, ValidationInfo, field_validator, model_validator,
)
from pydantic.dataclasses import dataclass as pydantic_dataclass

from polarshape.brdf.fmbrdf import check_param
from polarshape.brdf.params import FMBRDFParams
from polarshape.cameras import Camera, OrthographicCamera, PerspectiveCamera
from polarshape.errors import ConfigError
from polarshape.imaging.pixels import PIXEL_FORMATS, bayer_of
from polarshape.io.capture import IntrinsicsSpec, LightSpec, MosaicSpec, Projection
from polarshape.io.material import MaterialError, load_material
from polarshape.io.yamlfile import load_yaml
from polarshape.lights import DirectionalLight, Light, ring_lights
from polarshape.scene.geometry import BlobShape, CraterShape, MeshShape, PlaneShape, Shape, SphereShape, TorusShape
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial, Material, material_from_file
from polarshape.scene.objects import MaterialSplit, Scene, SceneObject
from polarshape.scene.sensor import SensorModel
from polarshape.scene.sensor_defects import SensorDefects
from polarshape.scene.textures import AlbedoTexture, make_texture

SCENE_FORMAT = "polarshape-scene/1"

Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    # allow_inf_nan=False: every float of a scene file must be finite (``.inf`` is an error naming its key)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _resolve(path: str, base_dir: Path | None) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() or base_dir is None else base_dir / p


# --- camera -----------------------------------------------------------------------------------


class CameraConfig(_Strict):
    """``camera:``: the simulated sensor's size, projection and settings. ``intrinsics`` and
    ``mosaic`` are the capture format's (:class:`~polarshape.io.capture.IntrinsicsSpec`,
    :class:`~polarshape.io.capture.MosaicSpec`) and go into the capture.yaml it records."""

    model: str = "simulated (polarshape)"
    projection: Projection = "orthographic"
    width: int = Field(256, gt=0, description="raw mosaic width, pixels (even)")
    height: int = Field(256, gt=0, description="raw mosaic height, pixels (even)")
    pixel_size_m: float | None = Field(None, gt=0, description="orthographic: metres per raw pixel")
    principal_point: tuple[float, float] | None = None
    intrinsics: IntrinsicsSpec | None = None
    mosaic: MosaicSpec = MosaicSpec()
    pixel_format: str = "PolarizeMono12"
    exposure_us: float = Field(10000.0, gt=0)
    #: Exposure brackets: every light is captured at each of these exposures (µs), the first being the
    #: reference exposure (``exposure_us``); the capture is written in format 2. None = one exposure.
    exposures_us: tuple[float, ...] | None = Field(None, min_length=1)
    gain_db: float = 0.0

    @field_validator("exposures_us")
    @classmethod
    def _brackets(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is None:
            return v
        if not all(math.isfinite(e) and e > 0 for e in v):
            raise ValueError(f"must be positive exposure times in µs, e.g. [8000, 1000, 125]; got {list(v)}")
        if len(set(v)) != len(v):
            raise ValueError(f"must not repeat an exposure time (each is one frame per light); got {list(v)}")
        return v

    @field_validator("pixel_format")
    @classmethod
    def _known_format(cls, v: str) -> str:
        if v not in PIXEL_FORMATS:
            raise ValueError(f"unknown pixel_format {v!r}; use one of {sorted(PIXEL_FORMATS)}")
        return v

    @model_validator(mode="after")
    def _projection_fields(self) -> CameraConfig:
        if self.width % 2 or self.height % 2:
            raise ValueError(f"camera width and height must be even (whole 2x2 blocks), got {self.width}x{self.height}")
        if bayer_of(self.pixel_format) not in (None, self.mosaic.bayer):
            raise ValueError(f"camera.pixel_format {self.pixel_format} is a colour sensor's raw format "
                             f"({bayer_of(self.pixel_format)} Bayer blocks) but camera.mosaic.bayer is "
                             f"{self.mosaic.bayer}: set mosaic.bayer: {bayer_of(self.pixel_format)}, or use a PolarizeMono format")
        if self.projection == "orthographic" and self.pixel_size_m is None:
            raise ValueError("an orthographic camera needs camera.pixel_size_m (metres per raw pixel)")
        if self.projection == "perspective" and self.intrinsics is None:
            raise ValueError("a perspective camera needs camera.intrinsics {fx, fy, cx, cy} (raw-mosaic pixels)")
        if self.exposures_us is not None and "exposure_us" in self.model_fields_set and \
                self.exposure_us != self.exposures_us[0]:
            raise ValueError(f"camera.exposure_us {self.exposure_us:g} differs from the first of camera.exposures_us "
                             f"{list(self.exposures_us)} (the reference exposure): drop exposure_us or make them agree")
        return self

    @property
    def reference_exposure_us(self) -> float:
        """The exposure frames are taken at (the first of ``exposures_us`` when bracketing)."""
        return self.exposures_us[0] if self.exposures_us is not None else self.exposure_us

    def to_camera(self) -> Camera:
        if self.projection == "orthographic":
            assert self.pixel_size_m is not None
            cx, cy = self.principal_point if self.principal_point is not None else (None, None)
            return OrthographicCamera(self.width, self.height, self.pixel_size_m, cx, cy)
        assert self.intrinsics is not None
        k = self.intrinsics
        return PerspectiveCamera(self.width, self.height, k.fx, k.fy, k.cx, k.cy)


# --- sensor -----------------------------------------------------------------------------------


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))
class SensorConfig(SensorModel, SensorDefects):
    """``sensor:``: the fields, defaults and checks of :class:`polarshape.scene.sensor.SensorModel`
    and of the imperfect sensor :class:`polarshape.scene.sensor_defects.SensorDefects` (defaults:
    ideal), plus the noise seed."""

    seed: int = 0

    def __post_init__(self) -> None:
        SensorModel.__post_init__(self)
        SensorDefects.__post_init__(self)

    def to_model(self) -> SensorModel:
        return SensorModel(**{f.name: getattr(self, f.name) for f in fields(SensorModel)})

    def to_defects(self) -> SensorDefects:
        return self.defects_only()


# --- shapes -----------------------------------------------------------------------------------


class SphereConfig(_Strict):
    type: Literal["sphere"]
    center: Vec3
    radius: float = Field(gt=0)

    def to_shape(self, base_dir: Path | None) -> Shape:
        return SphereShape(self.center, self.radius)


class PlaneConfig(_Strict):
    type: Literal["plane"]
    point: Vec3
    normal: Vec3
    size: tuple[float, float] | None = None

    def to_shape(self, base_dir: Path | None) -> Shape:
        return PlaneShape(self.point, self.normal, self.size)


class BlobConfig(_Strict):
    type: Literal["blob"]
    center: Vec3
    radius: float = Field(gt=0)
    bumps: int = Field(24, ge=0)
    amplitude: float = Field(0.25, ge=0, lt=0.5)
    width: float = Field(0.3, gt=0)
    seed: int = 2
    subdivisions: int = Field(6, ge=2, le=8)

    def to_shape(self, base_dir: Path | None) -> Shape:
        return BlobShape(
            self.center, self.radius, bumps=self.bumps, amplitude=self.amplitude, width=self.width,
            seed=self.seed, subdivisions=self.subdivisions,
        )


class TorusConfig(_Strict):
    type: Literal["torus"]
    center: Vec3
    major_radius: float = Field(gt=0)
    minor_radius: float = Field(gt=0)
    axis: Vec3 = (0.0, 0.0, 1.0)
    sections: int = Field(256, ge=16)

    def to_shape(self, base_dir: Path | None) -> Shape:
        return TorusShape(self.center, self.major_radius, self.minor_radius, axis=self.axis, sections=self.sections)


class MeshConfig(_Strict):
    type: Literal["mesh"]
    path: str
    scale: float = Field(1.0, gt=0)
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)
    translation: Vec3 = (0.0, 0.0, 0.0)
    smooth: bool = True

    def to_shape(self, base_dir: Path | None) -> Shape:
        path = _resolve(self.path, base_dir)
        if not path.is_file():
            raise ValueError(f"shape.path: mesh file {path} does not exist")
        return MeshShape.from_file(
            str(path), scale=self.scale, rotation_deg=self.rotation_deg, translation=self.translation, smooth=self.smooth
        )


class CraterConfig(_Strict):
    """A plate facing the camera with a round dish pressed into it (concave: light bounces inside)."""

    type: Literal["crater"]
    center: Vec3
    radius: float = Field(gt=0)
    depth: float = Field(gt=0)
    half_width: float = Field(gt=0)
    resolution: int = Field(257, ge=8, le=2049)

    @model_validator(mode="after")
    def _dish_on_the_plate(self) -> CraterConfig:
        if self.half_width <= self.radius:
            raise ValueError(f"half_width {self.half_width:g} must exceed the dish radius {self.radius:g} (the plate holds the dish)")
        return self

    def to_shape(self, base_dir: Path | None) -> Shape:
        return CraterShape(self.center, self.radius, self.depth, half_width=self.half_width, resolution=self.resolution)


ShapeConfig = Annotated[
    SphereConfig | PlaneConfig | BlobConfig | TorusConfig | MeshConfig | CraterConfig, Field(discriminator="type")
]


# --- materials and textures -------------------------------------------------------------------


@pydantic_dataclass(config=ConfigDict(extra="forbid", allow_inf_nan=False))
class FMBRDFConfig(FMBRDFParams):
    """``material: {model: fmbrdf, ...}``: the fields and defaults of
    :class:`~polarshape.brdf.FMBRDFParams`, checked against spec §2's ranges."""

    model: Literal["fmbrdf"] = "fmbrdf"
    #: a number (grey) or ``[r, g, b]``: the body albedo per colour channel (colour sensors,
    #: ``camera.mosaic.bayer``); a list is moved to ``k_b_rgb`` and ``k_b`` becomes its mean
    k_b: float | tuple[float, float, float] = 0.5  # type: ignore[assignment]
    #: written by polarshape from ``k_b: [r, g, b]`` (so ``k_b`` stays one number for its readers)
    k_b_rgb: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.k_b, tuple):
            if self.k_b_rgb is not None and tuple(self.k_b_rgb) != tuple(self.k_b):
                raise ValueError("give the colour body albedo once, as k_b: [r, g, b] (k_b_rgb is written from it)")
            self.k_b_rgb = self.k_b
        if self.k_b_rgb is not None:
            for c, v in zip(("r", "g", "b"), self.k_b_rgb):
                try:
                    check_param("k_b", v)
                except ValueError as err:
                    raise ValueError(f"k_b [r, g, b]: {c} = {v:g}: {err}") from None
            mean = sum(self.k_b_rgb) / 3.0
            if not isinstance(self.k_b, tuple) and not math.isclose(self.k_b, mean, rel_tol=1e-9, abs_tol=1e-12):
                raise ValueError(
                    f"k_b {self.k_b:g} and k_b_rgb {list(self.k_b_rgb)} disagree: give the colour body albedo as "
                    "k_b: [r, g, b] only (polarshape writes k_b_rgb and sets k_b to their mean)"
                )
            self.k_b = mean
        self.validate()

    def to_material(self) -> Material:
        return FMBRDFMaterial(**self.as_kwargs(), k_b_rgb=self.k_b_rgb)


class LambertianConfig(_Strict):
    model: Literal["lambertian"]
    k_d: float = Field(0.5, ge=0)

    def to_material(self) -> Material:
        return LambertianMaterial(self.k_d)


class BaekConfig(_Strict):
    model: Literal["baek"]
    ior: float = Field(1.5, ge=1)
    k_s: float = Field(1.0, ge=0)
    k_d: float = Field(0.5, ge=0)
    alpha: float = Field(0.3, gt=0)
    distribution: Literal["ggx", "beckmann"] = "ggx"

    def to_material(self) -> Material:
        return BaekMaterial(self.ior, self.k_s, self.k_d, self.alpha, self.distribution)


class MaterialFileConfig(_Strict):
    """``material: {file: material.json}``: a material file (relative to the scene file's folder),
    read and checked when the scene is validated; fmbrdf, lambertian or baek."""

    file: str

    @field_validator("file")
    @classmethod
    def _readable_material(cls, value: str, info: ValidationInfo) -> str:
        if not value.strip():
            raise ValueError("must be the path of a material.json")
        path = _resolve(value, (info.context or {}).get("base_dir"))
        try:
            material_from_file(load_material(path), str(path))
        except MaterialError as err:  # reported under the key ...material.file
            raise ValueError(f"{err} (relative paths start at the scene file's folder)") from None
        return str(path)

    def to_material(self) -> Material:
        return material_from_file(load_material(self.file), self.file)


def _material_kind(value: Any) -> str | None:
    """The tag of a material mapping: ``file`` for ``{file: ...}``, else its ``model``."""
    if isinstance(value, dict):
        return "file" if "file" in value else value.get("model")
    return "file" if isinstance(value, MaterialFileConfig) else getattr(value, "model", None)


MaterialConfig = Annotated[
    Annotated[FMBRDFConfig, Tag("fmbrdf")] | Annotated[LambertianConfig, Tag("lambertian")]
    | Annotated[BaekConfig, Tag("baek")] | Annotated[MaterialFileConfig, Tag("file")],
    Discriminator(_material_kind, custom_error_type="material_kind",
                  custom_error_message="a material needs model: fmbrdf | lambertian | baek, or file: material.json"),
]


class TextureConfig(_Strict):
    kind: Literal["checker", "stripes", "image"]
    mapping: Literal["spherical", "planar"] = "spherical"
    cells: float = Field(8.0, gt=0)
    low: float = Field(0.25, ge=0)
    high: float = Field(1.0, ge=0)
    size_m: float = Field(0.02, gt=0)
    path: str | None = None

    @model_validator(mode="after")
    def _image_has_path(self) -> TextureConfig:
        if self.kind == "image" and self.path is None:
            raise ValueError("texture kind 'image' needs texture.path (an image file)")
        return self

    def to_texture(self, center: Vec3, base_dir: Path | None) -> AlbedoTexture:
        path = _resolve(self.path, base_dir) if self.path is not None else None
        return make_texture(
            self.kind, self.mapping, center, cells=self.cells, low=self.low, high=self.high, size_m=self.size_m, path=path
        )


class SplitConfig(_Strict):
    """``split:``: a second material on one side of a plane through the object (an object of two
    parts): points with (p − center)·n̂ > ``offset`` take ``material`` (:class:`~polarshape.scene.objects.MaterialSplit`)."""

    normal: Vec3 = Field(description="the plane's normal, camera frame (any non-zero length)")
    offset: float = Field(0.0, description="signed distance of the plane from the shape's center along normal, metres")
    material: MaterialConfig

    @field_validator("normal")
    @classmethod
    def _non_zero(cls, v: Vec3) -> Vec3:
        if math.hypot(*v) <= 0:
            raise ValueError("split.normal must be a non-zero vector, e.g. [1, 0, 0]")
        return v

    def to_split(self) -> MaterialSplit:
        return MaterialSplit(self.normal, self.offset, self.material.to_material())


class ObjectConfig(_Strict):
    shape: ShapeConfig
    material: MaterialConfig = FMBRDFConfig()
    texture: TextureConfig | None = None
    in_mask: bool = True
    split: SplitConfig | None = None

    def to_object(self, base_dir: Path | None) -> SceneObject:
        shape = self.shape.to_shape(base_dir)
        texture = self.texture.to_texture(shape.center, base_dir) if self.texture is not None else None
        split = self.split.to_split() if self.split is not None else None
        return SceneObject(shape, self.material.to_material(), texture, self.in_mask, split)


# --- lights -----------------------------------------------------------------------------------


class LightConfig(LightSpec):
    """A :class:`~polarshape.io.capture.LightSpec` (``direction`` toward the light, any length,
    or ``position``, metres) that may instead be placed by ``zenith_deg`` + ``azimuth_deg``
    (zenith from the camera axis toward the camera, −z; azimuth from +x toward +y, image down)."""

    zenith_deg: float | None = Field(None, ge=0, lt=90)
    azimuth_deg: float | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> LightConfig:  # replaces LightSpec's rule: angles are a third placement
        by_angles = self.zenith_deg is not None or self.azimuth_deg is not None
        given = [self.direction is not None, self.position is not None, by_angles]
        if sum(given) != 1:
            raise ValueError("a light needs exactly one of direction, position, or zenith_deg + azimuth_deg")
        if given[2] and (self.zenith_deg is None or self.azimuth_deg is None):
            raise ValueError("a light given by angles needs both zenith_deg and azimuth_deg")
        return self

    def to_light(self) -> Light:
        if self.zenith_deg is None or self.azimuth_deg is None:
            return super().to_light()
        z, a = math.radians(self.zenith_deg), math.radians(self.azimuth_deg)
        return DirectionalLight((math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), -math.cos(z)), self.intensity)


class RingLightConfig(_Strict):
    """``lights: [{ring: {...}}]``: an LED ring (:func:`polarshape.lights.ring_lights`), expanded to
    ``count`` point-light entries in place (so the capture records plain positions)."""

    count: int = Field(gt=0, le=1000, description="number of LEDs, evenly spaced")
    radius_m: float = Field(gt=0, description="ring radius, metres")
    distance_m: float = Field(ge=0, description="z of the ring's plane in front of the camera, metres (0: around the lens)")
    intensity: float = Field(1.0, gt=0, description="each LED's irradiance at normal incidence at 1 m")
    center_xy: tuple[float, float] = Field((0.0, 0.0), description="x, y of the ring's centre, metres")
    phase_deg: float = Field(0.0, description="azimuth of the first LED, from +x toward +y (image down)")

    def entries(self) -> list[dict[str, Any]]:
        lights = ring_lights(self.count, self.radius_m, self.distance_m, self.intensity, center_xy=self.center_xy,
                             phase_deg=self.phase_deg)
        return [{"position": list(light.position), "intensity": light.intensity} for light in lights]


def _expand_rings(value: Any) -> Any:
    """A ``lights`` list with every ``{ring: {...}}`` entry replaced by its point lights (in order)."""
    if not isinstance(value, list):
        return value
    out: list[Any] = []
    for k, entry in enumerate(value):
        if not (isinstance(entry, dict) and "ring" in entry):
            out.append(entry)
            continue
        if set(entry) != {"ring"}:
            raise ValueError(f"lights[{k}]: a ring entry holds only ring: {{count, radius_m, distance_m, ...}}; "
                             f"remove {sorted(set(entry) - {'ring'})}")
        try:
            ring = entry["ring"] if isinstance(entry["ring"], RingLightConfig) else RingLightConfig.model_validate(entry["ring"])
        except ValidationError as err:
            problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err.errors())
            raise ValueError(f"lights[{k}].ring: {problems} (keys: {', '.join(RingLightConfig.model_fields)})") from None
        out.extend(ring.entries())
    return out


# --- the whole scene --------------------------------------------------------------------------


class InterreflectionConfig(_Strict):
    """``render.interreflection``: one bounce of light off the scene (:mod:`polarshape.scene.interreflection`)."""

    samples: int = Field(64, ge=1, le=4096)  # hemisphere rays per pixel
    seed: int = 0  # seed of the ray directions


class RenderConfig(_Strict):
    shadows: bool = True
    dtype: Literal["float32", "float64"] = "float64"
    #: light bounced once off the scene itself (concave objects); None = direct light only
    interreflection: InterreflectionConfig | None = None


class SceneConfig(_Strict):
    """A whole scene file. Build the runtime objects with :meth:`build_scene`."""

    format: Literal["polarshape-scene/1"] = SCENE_FORMAT
    camera: CameraConfig
    sensor: SensorConfig = SensorConfig()
    objects: list[ObjectConfig] = Field(min_length=1)
    lights: list[LightConfig] = Field(min_length=1)
    render: RenderConfig = RenderConfig()
    #: folder relative paths are resolved against (set by :func:`load_scene_config`)
    base_dir: Path | None = Field(None, exclude=True)

    @field_validator("lights", mode="before")
    @classmethod
    def _rings(cls, value: Any) -> Any:
        return _expand_rings(value)

    @model_validator(mode="after")
    def _point_lights_in_front(self) -> SceneConfig:
        """A point light at or beyond the nearest object's centre (z forward) lights its far side."""
        centres = [(getattr(o.shape, "center", None) or getattr(o.shape, "point", None), j)
                   for j, o in enumerate(self.objects)]  # meshes: no centre before loading
        known = [(float(c[2]), j) for c, j in centres if c is not None]
        if not known:
            return self
        nearest, j = min(known)
        behind = [f"lights[{k}].position z = {light.position[2]:g} m" for k, light in enumerate(self.lights)
                  if light.position is not None and light.position[2] >= nearest]
        if behind:
            raise ValueError(
                f"{', '.join(behind)} is at or beyond the centre of the nearest object (objects[{j}], z = {nearest:g} m): "
                "behind the object seen from the camera: z is forward, away from the camera (camera frame: x right, "
                "y down); give the light a smaller z, between the camera (z = 0) and the object"
            )
        return self

    def build_scene(self) -> Scene:
        """Camera model, shapes (meshes are loaded and tessellated here), materials, lights."""
        objects = tuple(obj.to_object(self.base_dir) for obj in self.objects)
        return Scene(self.camera.to_camera(), objects, tuple(light.to_light() for light in self.lights))


def _format_errors(err: ValidationError) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        lines.append(f"  {loc}: {msg}" if loc else f"  {msg}")  # a check of the whole scene has no location
    return "\n".join(lines)


def parse_scene_config(data: dict[str, Any], *, base_dir: Path | None = None, source: str = "scene") -> SceneConfig:
    """Validate a scene mapping; raises ValueError listing each bad field by its path."""
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a scene file must be a YAML mapping with camera, objects and lights")
    try:
        return SceneConfig.model_validate({**data, "base_dir": base_dir}, context={"base_dir": base_dir})
    except ValidationError as err:
        raise ValueError(f"{source} is not a valid scene:\n{_format_errors(err)}") from err


def load_scene_config(path: str | Path) -> SceneConfig:
    """Read and validate a scene YAML file (relative paths inside resolve against its folder)."""
    path = Path(path)
    data = load_yaml(path, error=ConfigError)  # unreadable, not UTF-8, not YAML, or a key given twice
    return parse_scene_config(data, base_dir=path.resolve().parent, source=str(path))
