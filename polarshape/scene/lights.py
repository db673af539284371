"""Light sources of the simulator: per surface point, the unit direction L to the light, the
irradiance at normal incidence E, and how far a shadow ray must stay clear.

Camera frame (OpenCV: x right, y down, z forward), metres. Lights are unpolarised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity.

    Attributes:
        direction: (x, y, z) unit vector from the scene toward the light (L), camera frame;
            normalised on construction. A light beside the camera has z < 0.
        intensity: irradiance at normal incidence (relative units; 1 = the sensor's reference).
    """

    direction: tuple[float, float, float]
    intensity: float = 1.0

    def __post_init__(self) -> None:
        if len(self.direction) != 3:
            raise ValueError(f"light direction must be [x, y, z], got {list(self.direction)}")
        norm = math.sqrt(sum(float(c) ** 2 for c in self.direction))
        if not norm > 0:
            raise ValueError(f"light direction must be non-zero, got {list(self.direction)}")
        if not self.intensity >= 0:
            raise ValueError(f"light intensity must be >= 0, got {self.intensity}")
        object.__setattr__(self, "direction", tuple(float(c) / norm for c in self.direction))

    def illuminate(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For (..., 3) points: L (..., 3) unit, E (...) irradiance, and the shadow-ray length
        (...) (``inf``: anything along L blocks the light)."""
        light = torch.tensor(self.direction, dtype=points.dtype, device=points.device).expand_as(points)
        irradiance = torch.full(points.shape[:-1], float(self.intensity), dtype=points.dtype, device=points.device)
        return light, irradiance, torch.full_like(irradiance, math.inf)


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light.

    Attributes:
        position: (x, y, z) metres, camera frame.
        intensity: irradiance at normal incidence at 1 m; falls off as 1/r².
    """

    position: tuple[float, float, float]
    intensity: float = 1.0

    def __post_init__(self) -> None:
        if len(self.position) != 3:
            raise ValueError(f"light position must be [x, y, z] metres, got {list(self.position)}")
        if not self.intensity >= 0:
            raise ValueError(f"light intensity must be >= 0, got {self.intensity}")
        object.__setattr__(self, "position", tuple(float(c) for c in self.position))

    def illuminate(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For (..., 3) points: L (..., 3) unit toward the light, E = intensity / r² (...), and
        the distance r to the light (...) (shadow rays stop there)."""
        to_light = torch.tensor(self.position, dtype=points.dtype, device=points.device) - points  # (..., 3)
        dist = to_light.norm(dim=-1).clamp_min(torch.finfo(points.dtype).tiny)
        return to_light / dist[..., None], self.intensity / dist**2, dist


Light = DirectionalLight | PointLight


def light_from_dict(entry: dict[str, object]) -> Light:
    """A light from a capture.yaml / scene.yaml entry ``{direction: [...]} | {position: [...]}``
    with optional ``intensity``. Raises ValueError naming the missing or conflicting key."""
    has_dir, has_pos = "direction" in entry, "position" in entry
    if has_dir == has_pos:
        raise ValueError(f"a light needs exactly one of 'direction' or 'position', got keys {sorted(entry)}")
    intensity = float(entry.get("intensity", 1.0))  # type: ignore[arg-type]
    if has_dir:
        return DirectionalLight(tuple(entry["direction"]), intensity)  # type: ignore[arg-type]
    return PointLight(tuple(entry["position"]), intensity)  # type: ignore[arg-type]


def light_to_dict(light: Light) -> dict[str, object]:
    """The capture.yaml form of a light (without its frame path)."""
    if isinstance(light, DirectionalLight):
        return {"direction": list(light.direction), "intensity": float(light.intensity)}
    return {"position": list(light.position), "intensity": float(light.intensity)}

