"""The run configuration of ``polarshape run CONFIG.yaml``: validated once here (pydantic v2, strict).

A minimal file is a few lines; every other key has a default (configs/default.yaml lists them all
with comments)::

    input:
      type: simulated                  # capture | simulated | session
      scene: scenes/sphere.yaml        # relative paths are relative to this file's folder
    recovery:
      model: auto                      # auto | fmbrdf | lambertian

Validation is strict: an unknown key, a value of the wrong type (``"3"`` for a number, ``1`` for a
boolean) or out of range fails at once with a :class:`ConfigError` that names each key path
(``recovery.max_outer_iterations``), what is wrong, the allowed values or keys, and what was given.
Inner code takes the typed :class:`RunConfig`, never the raw mapping.
"""

from __future__ import annotations

import difflib
import os
import types
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from polarshape.errors import ConfigError
from polarshape.io.yamlfile import load_yaml, resolve_config_path
from polarshape.nearfield import NearFieldOptions
from polarshape.recover.options import InitialNormalsOptions, RecoveryOptions, ValidationOptions

__all__ = [
    "RUN_FORMAT",
    "BatchConfig",
    "ConfigError",
    "ExportConfig",
    "InitialNormalsOptions",
    "InputConfig",
    "IntegrationConfig",
    "MeshConfig",
    "NearFieldOptions",
    "PreprocessConfig",
    "RecoveryOptions",
    "ReportConfig",
    "RunConfig",
    "load_batch_config",
    "load_run_config",
    "parse_batch_config",
    "parse_run_config",
]

#: Version string of the run-configuration format.
RUN_FORMAT = "polarshape-run/1"


class _Strict(BaseModel):
    # allow_inf_nan=False: every float must be finite (``.inf``/``.nan`` is an error naming its key path)
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


class InputConfig(_Strict):
    """Where the capture comes from.

    ``capture``: an existing capture folder (``path``). ``simulated``: the simulated camera renders
    ``scene`` first. ``session``: a capture session (``polarshape capture`` YAML: Aravis, fake GigE
    or simulated camera with a light rig) records one first. Simulated and session captures are
    written to ``<result>/capture`` when ``save_capture`` is true.
    """

    type: Literal["capture", "simulated", "session"] = Field(description="where the capture comes from")
    path: str | None = Field(None, description="capture: the capture folder (holding capture.yaml)")
    scene: str | None = Field(None, description="simulated: the scene YAML (configs/scenes/*.yaml)")
    session: str | None = Field(None, description="session: the capture-session YAML (configs/sessions/*.yaml)")
    seed: int | None = Field(None, ge=0, description="simulated: noise seed (default: the scene's sensor.seed)")
    save_capture: bool = Field(True, description="simulated/session: keep the capture in <result>/capture")

    @field_validator("path", "scene", "session")
    @classmethod
    def _paths(cls, value: str | None, info: ValidationInfo) -> str | None:
        return resolve_config_path(value, info)

    @model_validator(mode="after")
    def _consistent(self) -> InputConfig:
        needed = {"capture": "path", "simulated": "scene", "session": "session"}[self.type]
        if getattr(self, needed) is None:
            raise ValueError(f"input.{needed} is required when input.type is {self.type!r}")
        for key in ("path", "scene", "session"):
            if key != needed and getattr(self, key) is not None:
                raise ValueError(
                    f"input.{key} does not apply to input.type {self.type!r} (it takes input.{needed}); remove it"
                )
        if self.seed is not None and self.type != "simulated":
            raise ValueError("input.seed applies to input.type 'simulated' only; remove it")
        target = Path(getattr(self, needed))
        if self.type == "capture":
            if not target.is_dir() and not (target.name == "capture.yaml" and target.is_file()):
                raise ValueError(f"input.path {target} is not a capture folder (a folder holding capture.yaml)")
        elif not target.is_file():
            raise ValueError(f"input.{needed} {target} not found (relative paths start at the config file's folder)")
        return self


class PreprocessConfig(_Strict):
    """Raw mosaics → Stokes images (super-pixel resolution) and the object mask."""

    mask: Literal["auto", "capture", "threshold"] = Field(
        "auto", description="capture = the capture's mask.png (required); threshold = brightest s0 above "
        "mask_threshold; auto = the capture's mask if it has one, else threshold"
    )
    mask_threshold: float = Field(0.02, ge=0.0, lt=1.0, description="fraction of full scale for the threshold mask")
    dark_threshold: float = Field(
        0.005, ge=0.0, lt=1.0, description="observations with s0 below this fraction of full scale are not used"
    )
    erode_px: int = Field(0, ge=0, le=64, description="erode the mask by this many super-pixels (drops mixed edge pixels)")
    saturation_margin_counts: int = Field(0, ge=0, description="counts below full scale still treated as saturated")
    min_component_px: int = Field(16, ge=1, description="mask components smaller than this (super-pixels) are dropped")
    demosaic: Literal["bilinear", "superpixel"] = Field(
        "bilinear", description="Stokes estimate: bilinear (each polariser image interpolated to every site, then "
        "sampled at sample_at) or superpixel (the plain 2x2 estimate, at the centre only)"
    )
    sample_at: Literal["centre", "top_left", "top_right", "bottom_left", "bottom_right"] = Field(
        "centre", description="where in each 2x2 block the normals are estimated: the block centre, or one site "
        "(e.g. top_left, the IMX250MZR's 90 degree site)"
    )
    albedo_edges: bool = Field(
        True, description="find texture (albedo) steps from every light (polarshape.recover.edges): blocks next to "
        "one take their own four sites' estimate, blocks on one are left out and marked in mixed.png; mono only"
    )
    polarisation_check: bool = Field(
        True, description="refuse frames without the polarisation signal a raw mosaic of an object carries (a "
        "demosaiced or plain image saved as a frame; polarshape.recover.diagnose.check_polarisation_signal); "
        "false for raw mosaics of an unpolarised scene"
    )

    @model_validator(mode="after")
    def _site_needs_bilinear(self) -> PreprocessConfig:
        if self.demosaic == "superpixel" and self.sample_at != "centre":
            raise ValueError(f"preprocess.sample_at {self.sample_at!r} needs preprocess.demosaic 'bilinear' "
                             "(the superpixel estimate is at the block centre)")
        return self


class IntegrationConfig(_Strict):
    """Normal integration (polarshape.surface.integrate.integrate_normals)."""

    method: Literal["smooth", "bilateral"] = "smooth"
    pixel_size_m: float | None = Field(
        None, gt=0, description="orthographic: metres per super-pixel (null: from the simulated scene if known, "
        "else 1 = depth in super-pixel units)"
    )
    reference_depth_m: float = Field(
        1.0, gt=0, description="median depth given to each surface piece (the normals fix depth only up to it); "
        "point lights are located from a plane at this depth"
    )
    bilateral_k: float = Field(2.0, gt=0, le=100)
    max_iter: int = Field(100, ge=1, le=10000)


class InterreflectionConfig(_Strict):
    """``interreflection:``: light the object sends onto itself (concave objects), estimated from the
    recovered surface and material and taken out of the photos before a re-fit
    (:mod:`polarshape.surface.interreflection`)."""

    mode: Literal["auto", "on", "off"] = Field(
        "auto", description="auto: re-fit only when the estimated bounce is more than min_fraction of the light on "
        "at least min_area of the object (a concavity); on: always; off: never"
    )
    iterations: int = Field(3, ge=1, le=10, description="estimate-and-re-fit rounds")
    samples: int = Field(32, ge=4, le=1024, description="hemisphere rays per pixel")
    max_pixels: int = Field(16384, ge=256, description="the bounce is rendered on a lattice of at most this many pixels")
    albedo_scale: float | None = Field(
        None, gt=0, description="the capture's albedo units per physical albedo (fraction of full scale per unit light "
        "that a white Lambertian reflector of albedo 1 gives, from a reference target); null: fitted"
    )
    min_fraction: float = Field(0.02, ge=0.0, lt=1.0, description="auto: bounce / observed s0 that counts")
    min_area: float = Field(0.01, ge=0.0, le=1.0, description="auto: share of the object where it must count")

    @model_validator(mode="after")
    def _on_needs_scale(self) -> InterreflectionConfig:
        if self.mode == "on" and self.albedo_scale is None:
            raise ValueError("mode: on takes the bounce out, which needs albedo_scale (the capture's albedo per physical "
                             "albedo, from a white reference target); give it, or use mode: auto to mark the pixels")
        return self


class MeshConfig(_Strict):
    """Meshes from the depth map (grid) and, optionally, screened Poisson reconstruction."""

    frame: Literal["opengl", "opencv"] = Field(
        "opengl", description="frame of mesh.ply/mesh.obj/mesh_poisson.ply: opengl = x right, y up, z toward the "
        "viewer (what Blender, MeshLab, three.js show upright and facing you); opencv = the camera frame (x right, "
        "y down, z into the scene, like normals.npy and depth.npy)"
    )
    colors: Literal["albedo", "none"] = Field(
        "albedo", description="vertex colours of mesh.ply/mesh.obj/mesh_poisson.ply"
    )
    obj: bool = Field(True, description="also write mesh.obj")
    poisson: bool = Field(False, description="also write mesh_poisson.ply (open3d screened Poisson)")
    poisson_depth: int = Field(8, ge=4, le=12, description="Poisson octree depth")
    watertight: bool = Field(
        True, description="true: close the one-view surface with its mirror image behind it (a watertight solid); "
        "false: trim the surface Poisson extrapolates away from the data (an open surface)"
    )
    repair: bool = Field(
        True, description="clean mesh_poisson.ply with open3d (merge vertices closer than 1 % of an edge, drop "
        "degenerate/duplicated triangles and non-manifold edges): removes Poisson's self-intersecting slivers"
    )


class ExportConfig(_Strict):
    """Result-file options (normal_map.png is 16-bit RGBA, alpha 0 outside the mask)."""

    normal_convention: Literal["opencv", "opengl"] = Field(
        "opencv", description="normal_map.png convention: opencv = camera frame (x right, y down, z forward); "
        "opengl = x right, y up, z toward the viewer"
    )
    exr: bool = Field(True, description="write normals.exr (float32 OpenEXR, channels R, G, B = normal, A = mask)")


class ReportConfig(_Strict):
    """The report: report.html with PNG plots (or report.png, one summary figure)."""

    enabled: bool = True
    format: Literal["html", "png"] = "html"
    max_curve_pixels: int = Field(20000, ge=100, description="pixels sampled for the fit-curve plots")


class RunConfig(_Strict):
    """Everything ``polarshape run`` needs (see configs/default.yaml for a documented example)."""

    format: Literal["polarshape-run/1"] = RUN_FORMAT
    input: InputConfig
    output: str | None = Field(None, description="result folder (the command line's --out wins)")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="auto = cuda when available, else cpu")
    dtype: Literal["float32", "float64"] = "float32"
    seed: int = Field(0, ge=0, description="seed of every random choice of the pipeline (subsampling)")
    progress: bool = Field(True, description="progress bars on the terminal")
    preprocess: PreprocessConfig = PreprocessConfig()
    initial_normals: InitialNormalsOptions = InitialNormalsOptions()
    recovery: RecoveryOptions = RecoveryOptions()
    validation: ValidationOptions = ValidationOptions()
    interreflection: InterreflectionConfig = InterreflectionConfig()
    nearfield: NearFieldOptions = NearFieldOptions()
    integration: IntegrationConfig = IntegrationConfig()
    mesh: MeshConfig = MeshConfig()
    export: ExportConfig = ExportConfig()
    report: ReportConfig = ReportConfig()

    @field_validator("output")
    @classmethod
    def _output(cls, value: str | None, info: ValidationInfo) -> str | None:
        return resolve_config_path(value, info)


# --- error messages ----------------------------------------------------------------------------


def _model_of(annotation: Any) -> type[BaseModel] | None:
    """The BaseModel class inside an annotation (``X`` or ``X | None``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            found = _model_of(arg)
            if found is not None:
                return found
    return None


def _model_at(loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The config section that holds the key at ``loc`` (RunConfig for a top-level key)."""
    model: type[BaseModel] | None = RunConfig
    for part in loc[:-1]:
        if model is None or part not in model.model_fields:
            return None
        model = _model_of(model.model_fields[part].annotation)
    return model


def _format_error(err: dict[str, Any]) -> str:
    loc = tuple(err["loc"])
    path = ".".join(str(p) for p in loc) or "(top level)"
    kind = err["type"]
    msg = str(err["msg"]).removeprefix("Value error, ")
    given = err.get("input")
    if kind == "extra_forbidden":
        section = _model_at(loc)
        allowed = list(section.model_fields) if section is not None else []
        close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"{path}: unknown key{hint}; allowed keys here: {', '.join(allowed)}"
    if kind == "missing":
        return f"{path}: required key missing; add it"
    if kind == "model_type":
        section = _model_of(_model_at(loc + ("_",)))  # type: ignore[arg-type]
        keys = f" with keys {', '.join(section.model_fields)}" if section is not None else ""
        return f"{path}: must be a mapping{keys}; got {given!r}"
    text = f"{path}: {msg}"
    if kind.startswith(("int", "float", "bool", "string", "literal")) or kind in (
        "greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"
    ):
        text += f"; got {given!r}"
    return text[:600]


def parse_run_config(data: Any, source: str = "config", base_dir: str | os.PathLike[str] | None = None) -> RunConfig:
    """Validate a parsed run-configuration mapping.

    Args:
        data: the mapping (e.g. ``yaml.safe_load`` of the file).
        source: name used in error messages (the file name).
        base_dir: folder that relative paths are relative to (the config file's folder).

    Raises:
        ConfigError: naming every invalid key path, the problem and the allowed values.
    """
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: a run configuration must be a YAML mapping with at least an 'input' section; "
            f"got {type(data).__name__}"
        )
    context = {"base_dir": Path(base_dir) if base_dir is not None else None}
    try:
        return RunConfig.model_validate(data, context=context)
    except ValidationError as err:
        raise _config_error(err, source) from None


def _config_error(err: ValidationError, source: str) -> ConfigError:
    """One :class:`ConfigError` listing every problem of ``err`` (key path, problem, allowed values)."""
    lines = [f"{source}: {err.error_count()} problem(s):"]
    lines += [f"  - {_format_error(e)}" for e in err.errors()]
    return ConfigError("\n".join(lines))


def load_run_config(path: str | os.PathLike[str]) -> RunConfig:
    """Read and validate a run configuration YAML file (relative paths start at its folder).

    Raises:
        ConfigError: missing/unreadable file, invalid YAML, a key given twice, or any invalid key (see
            module docstring).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found (see configs/default.yaml for an example)")
    data = load_yaml(path, error=ConfigError)
    return parse_run_config(data, str(path), base_dir=path.resolve().parent)


# --- batch configurations (polarshape batch) -----------------------------------------------------


class BatchConfig(RunConfig):
    """A run configuration without ``input``, for ``polarshape batch CONFIG CAPTURES...``: each capture
    gets ``input: {type: capture, path: <capture>}`` (:meth:`for_capture`); every other key is
    validated as in a run configuration, with the same messages."""

    input: None = Field(None, description="not in a batch configuration: the captures are given on the command line")

    @field_validator("input", mode="before")
    @classmethod
    def _no_input(cls, value: Any) -> None:
        raise ValueError("a batch configuration has no input: the captures are given on the command line "
                         "(polarshape batch CONFIG CAPTURES... --out DIR); remove the input section")

    def for_capture(self, capture: str | os.PathLike[str], source: str = "batch configuration") -> RunConfig:
        """The run configuration of one capture folder of the batch.

        Raises:
            ConfigError: ``capture`` is not a capture folder (``input.path``, named with ``source``).
        """
        data = self.model_dump(exclude={"input"})
        data["input"] = {"type": "capture", "path": str(Path(capture).absolute())}
        return parse_run_config(data, f"{source} for capture {capture}")


def parse_batch_config(data: Any, source: str = "config", base_dir: str | os.PathLike[str] | None = None
                       ) -> BatchConfig:
    """Validate a parsed batch-configuration mapping (a run configuration without ``input``; see
    :func:`parse_run_config` for the arguments).

    Raises:
        ConfigError: naming every invalid key path (``input`` included: a batch has none), the problem
            and the allowed values.
    """
    if data is None:
        data = {}  # an empty file: every default
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a batch configuration must be a YAML mapping (a run configuration without "
                          f"input); got {type(data).__name__}")
    context = {"base_dir": Path(base_dir) if base_dir is not None else None}
    try:
        return BatchConfig.model_validate(data, context=context)
    except ValidationError as err:
        raise _config_error(err, source) from None


def load_batch_config(path: str | os.PathLike[str]) -> BatchConfig:
    """Read and validate a batch configuration YAML file (relative paths start at its folder).

    Raises:
        ConfigError: as :func:`load_run_config`, and an ``input`` section (a batch takes its captures
            from the command line).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found (a run configuration without input; see "
                          "configs/default.yaml)")
    data = load_yaml(path, error=ConfigError)
    return parse_batch_config(data, str(path), base_dir=path.resolve().parent)
