"""Surface stage: normal integration into depth, meshes from depth maps and point clouds."""

from polarshape.surface.integrate import IntegrationReport, check_normal_map, integrate_normals, surface_gradients
from polarshape.surface.mesh import depth_to_mesh, poisson_mesh, write_mesh

__all__ = [
    "IntegrationReport",
    "check_normal_map",
    "depth_to_mesh",
    "integrate_normals",
    "poisson_mesh",
    "surface_gradients",
    "write_mesh",
]
