"""Scene files (YAML) for the simulated camera: validated once here, turned into typed objects.

A scene file holds ``camera``, ``sensor``, ``objects`` and ``lights`` (see configs/scenes/*.yaml,
whose comments document every field). Units: metres, microseconds, degrees only where a field
name says ``_deg``. Frames: the camera frame (OpenCV: x right, y down, z forward). Relative file
paths (meshes, texture images) are relative to the scene file's folder.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from polarshape.acquisition.camera import PIXEL_FORMATS
from polarshape.acquisition.noise import SensorModel
from polarshape.brdf.fmbrdf import check_param
from polarshape.imaging.mosaic import MosaicLayout
from polarshape.scene.cameras import CameraModel, OrthographicCamera, PerspectiveCamera
from polarshape.scene.geometry import BlobShape, MeshShape, PlaneShape, Shape, SphereShape, TorusShape
from polarshape.scene.lights import DirectionalLight, Light, PointLight
from polarshape.scene.materials import BaekMaterial, FMBRDFMaterial, LambertianMaterial, Material
from polarshape.scene.objects import Scene, SceneObject
from polarshape.scene.textures import AlbedoTexture, make_texture

SCENE_FORMAT = "polarshape-scene/1"

Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _resolve(path: str, base_dir: Path | None) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() or base_dir is None else base_dir / p


# --- camera -----------------------------------------------------------------------------------


class IntrinsicsConfig(_Strict):
    """Pinhole intrinsics in raw-mosaic pixels."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


class MosaicConfig(_Strict):
    """The 2×2 polariser layout as the maker labels it (capture-format.md ``camera.mosaic``)."""

    layout: tuple[tuple[float, float], tuple[float, float]] = ((90.0, 45.0), (135.0, 0.0))
    angles: Literal["counterclockwise_on_screen", "clockwise_on_screen"] = "counterclockwise_on_screen"

    def to_layout(self) -> MosaicLayout:
        return MosaicLayout.from_maker(self.layout, self.angles)


class CameraConfig(_Strict):
    model: str = "simulated (polarshape)"
    projection: Literal["orthographic", "perspective"] = "orthographic"
    width: int = Field(256, gt=0, description="raw mosaic width, pixels (even)")
    height: int = Field(256, gt=0, description="raw mosaic height, pixels (even)")
    pixel_size_m: float | None = Field(None, gt=0, description="orthographic: metres per raw pixel")
    principal_point: tuple[float, float] | None = None
    intrinsics: IntrinsicsConfig | None = None
    mosaic: MosaicConfig = MosaicConfig()
    pixel_format: str = "PolarizeMono12"
    exposure_us: float = Field(10000.0, gt=0)
    gain_db: float = 0.0

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
        if self.projection == "orthographic" and self.pixel_size_m is None:
            raise ValueError("an orthographic camera needs camera.pixel_size_m (metres per raw pixel)")
        if self.projection == "perspective" and self.intrinsics is None:
            raise ValueError("a perspective camera needs camera.intrinsics {fx, fy, cx, cy} (raw-mosaic pixels)")
        return self

    def to_camera(self) -> CameraModel:
        if self.projection == "orthographic":
            assert self.pixel_size_m is not None
            cx, cy = self.principal_point if self.principal_point is not None else (None, None)
            return OrthographicCamera(self.width, self.height, self.pixel_size_m, cx, cy)
        assert self.intrinsics is not None
        k = self.intrinsics
        return PerspectiveCamera(self.width, self.height, k.fx, k.fy, k.cx, k.cy)


# --- sensor -----------------------------------------------------------------------------------


class SensorConfig(_Strict):
    """See :class:`polarshape.acquisition.noise.SensorModel`; plus the noise seed."""

    full_well_e: float = Field(10500.0, gt=0)
    read_noise_e: float = Field(2.5, ge=0)
    e_per_count_12bit: float | None = Field(None, gt=0)
    black_level_12bit: float = Field(0.0, ge=0, lt=4095)
    electrons_per_radiance: float = Field(80000.0, gt=0)
    reference_exposure_us: float = Field(10000.0, gt=0)
    shot_noise: Literal["poisson", "gaussian", "none"] = "poisson"
    seed: int = 0

    def to_model(self) -> SensorModel:
        return SensorModel(**self.model_dump(exclude={"seed"}))


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


ShapeConfig = Annotated[SphereConfig | PlaneConfig | BlobConfig | TorusConfig | MeshConfig, Field(discriminator="type")]


# --- materials and textures -------------------------------------------------------------------


class FMBRDFConfig(_Strict):
    model: Literal["fmbrdf"]
    ior: float = 1.5
    k_s: float = 1.0
    k_b: float = 0.5
    alpha: float = 0.3
    beta: float = 2.0
    kappa: float = 0.0

    @model_validator(mode="after")
    def _in_range(self) -> FMBRDFConfig:
        for name in ("ior", "k_s", "k_b", "alpha", "beta", "kappa"):
            check_param(name, getattr(self, name))
        return self

    def to_material(self) -> Material:
        return FMBRDFMaterial(self.ior, self.k_s, self.k_b, self.alpha, self.beta, self.kappa)


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


MaterialConfig = Annotated[FMBRDFConfig | LambertianConfig | BaekConfig, Field(discriminator="model")]


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


class ObjectConfig(_Strict):
    shape: ShapeConfig
    material: MaterialConfig = FMBRDFConfig(model="fmbrdf")
    texture: TextureConfig | None = None
    in_mask: bool = True

    def to_object(self, base_dir: Path | None) -> SceneObject:
        shape = self.shape.to_shape(base_dir)
        texture = self.texture.to_texture(shape.center, base_dir) if self.texture is not None else None
        return SceneObject(shape, self.material.to_material(), texture, self.in_mask)


# --- lights -----------------------------------------------------------------------------------


class LightConfig(_Strict):
    """Exactly one of ``direction`` (unit vector to the light), ``position`` (metres) or
    ``zenith_deg`` + ``azimuth_deg`` (zenith from the camera axis toward the camera, −z; azimuth
    from +x toward +y, image down)."""

    direction: Vec3 | None = None
    position: Vec3 | None = None
    zenith_deg: float | None = Field(None, ge=0, lt=90)
    azimuth_deg: float | None = None
    intensity: float = Field(1.0, gt=0)

    @model_validator(mode="after")
    def _one_placement(self) -> LightConfig:
        by_angles = self.zenith_deg is not None or self.azimuth_deg is not None
        given = [self.direction is not None, self.position is not None, by_angles]
        if sum(given) != 1:
            raise ValueError("a light needs exactly one of direction, position, or zenith_deg + azimuth_deg")
        if given[2] and (self.zenith_deg is None or self.azimuth_deg is None):
            raise ValueError("a light given by angles needs both zenith_deg and azimuth_deg")
        if self.direction is not None:
            if not any(self.direction):
                raise ValueError("direction must be a non-zero vector toward the light")
            if not self.direction[2] < 0:
                raise ValueError(
                    f"direction {list(self.direction)} must have z < 0: it points from the object toward the light "
                    "in the camera frame (+z into the scene), so a light on the camera side has z < 0"
                )
        return self

    def to_light(self) -> Light:
        if self.position is not None:
            return PointLight(self.position, self.intensity)
        if self.direction is not None:
            return DirectionalLight(self.direction, self.intensity)
        assert self.zenith_deg is not None and self.azimuth_deg is not None
        z, a = math.radians(self.zenith_deg), math.radians(self.azimuth_deg)
        return DirectionalLight((math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), -math.cos(z)), self.intensity)


# --- the whole scene --------------------------------------------------------------------------


class RenderConfig(_Strict):
    shadows: bool = True
    dtype: Literal["float32", "float64"] = "float64"


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

    def build_scene(self) -> Scene:
        """Camera model, shapes (meshes are loaded and tessellated here), materials, lights."""
        objects = tuple(obj.to_object(self.base_dir) for obj in self.objects)
        return Scene(self.camera.to_camera(), objects, tuple(light.to_light() for light in self.lights))


def _format_errors(err: ValidationError) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        lines.append(f"  {loc}: {e['msg']}")
    return "\n".join(lines)


def parse_scene_config(data: dict[str, Any], *, base_dir: Path | None = None, source: str = "scene") -> SceneConfig:
    """Validate a scene mapping; raises ValueError listing each bad field by its path."""
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a scene file must be a YAML mapping with camera, objects and lights")
    try:
        return SceneConfig.model_validate({**data, "base_dir": base_dir})
    except ValidationError as err:
        raise ValueError(f"{source} is not a valid scene:\n{_format_errors(err)}") from err


def load_scene_config(path: str | Path) -> SceneConfig:
    """Read and validate a scene YAML file (relative paths inside resolve against its folder)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"cannot read scene file {path}: {exc.strerror}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"scene file {path} is not valid YAML: {exc}") from exc
    return parse_scene_config(data, base_dir=path.resolve().parent, source=str(path))
