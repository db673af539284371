"""Recovery: initial normals from photometric stereo and polarisation cues."""

from polarshape.recover.photometric import PSReason, RobustPSResult, lambertian_ps, robust_lambertian_ps
from polarshape.recover.polarization_cues import (
    PolarizationNormals,
    azimuth_candidates,
    diffuse_dolp,
    disambiguate_azimuth,
    normal_azimuth,
    normals_from_angles,
    normals_from_polarization,
    select_closest_normal,
    specular_dolp,
    stokes_to_aolp_dolp,
    zenith_from_diffuse_dolp,
    zenith_from_specular_dolp,
)

__all__ = [
    "PSReason",
    "PolarizationNormals",
    "RobustPSResult",
    "azimuth_candidates",
    "diffuse_dolp",
    "disambiguate_azimuth",
    "lambertian_ps",
    "normal_azimuth",
    "normals_from_angles",
    "normals_from_polarization",
    "robust_lambertian_ps",
    "select_closest_normal",
    "specular_dolp",
    "stokes_to_aolp_dolp",
    "zenith_from_diffuse_dolp",
    "zenith_from_specular_dolp",
]
