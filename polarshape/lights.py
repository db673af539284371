"""Light sources: per surface point, the unit direction L to the light and the irradiance E.

Shared by the simulator (rendering, shadow rays) and by recovery (per-pixel L and E of a capture's
lights). Camera frame (OpenCV: x right, y down, z forward), metres. Lights are unpolarised.

Every light answers the same call, ``illuminate(points)``, so that call sites never need to know the
light type (pytorch3d's ``lighting.py`` is the model); :class:`Lights` batches K of them:
``Lights.illuminate(points (..., 3)) -> L (K, ..., 3), E (K, ...)`` for directional and point lights
alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = ["DirectionalLight", "Light", "Lights", "PointLight", "light_from_dict", "light_to_dict", "ring_lights"]


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


@dataclass(frozen=True)
class Lights:
    """K lights, illuminated together.

    Attributes:
        lights: the K lights, in frame order.
    """

    lights: tuple[Light, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "lights", tuple(self.lights))
        if not self.lights:
            raise ValueError("lights: at least one light is needed")

    def __len__(self) -> int:
        return len(self.lights)

    def __iter__(self):  # noqa: ANN204 - an iterator of Light
        return iter(self.lights)

    def __getitem__(self, index: int) -> Light:
        return self.lights[index]

    @property
    def has_point_lights(self) -> bool:
        """True when L and E depend on where the surface is (any point light)."""
        return any(isinstance(light, PointLight) for light in self.lights)

    def illuminate(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per-point light directions and irradiance of every light.

        Args:
            points: (..., 3) surface points, metres, camera frame (directional lights ignore where
                they are, but the shape sets the batch).

        Returns:
            L (K, ..., 3) unit vectors surface → light, E (K, ...) irradiance at normal incidence.
        """
        lit = [light.illuminate(points)[:2] for light in self.lights]
        return torch.stack([l for l, _ in lit]), torch.stack([e for _, e in lit])

    def behind(self, depth_z: float) -> list[int]:
        """Indices of the lights that cannot light the camera's side of a surface at depth ``depth_z``
        (metres along +z, away from the camera): point lights with z ≥ ``depth_z``, directional
        lights pointing away from the camera (z > 0; z = 0 is grazing and allowed)."""
        return [
            k for k, light in enumerate(self.lights)
            if (isinstance(light, PointLight) and light.position[2] >= depth_z)
            or (isinstance(light, DirectionalLight) and light.direction[2] > 0)
        ]

    def coincident(self, max_angle_deg: float = 0.5, max_distance_m: float = 1e-3) -> list[tuple[int, int, float]]:
        """Pairs of lights that light the scene from (nearly) one place: a copied entry, or a rig
        that did not move. Directional lights closer than ``max_angle_deg``, point lights closer
        than ``max_distance_m``; a directional and a point light are never compared.

        Returns:
            (i, j, separation) with i < j, in frame order: degrees for directional lights, metres
            for point lights.
        """
        pairs: list[tuple[int, int, float]] = []
        for i, a in enumerate(self.lights):
            for j in range(i + 1, len(self.lights)):
                b = self.lights[j]
                if isinstance(a, DirectionalLight) and isinstance(b, DirectionalLight):
                    cos = sum(x * y for x, y in zip(a.direction, b.direction))
                    angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
                    if angle < max_angle_deg:
                        pairs.append((i, j, angle))
                elif isinstance(a, PointLight) and isinstance(b, PointLight):
                    dist = math.dist(a.position, b.position)
                    if dist < max_distance_m:
                        pairs.append((i, j, dist))
        return pairs

    def intensities(self) -> list[float]:
        """The K lights' intensities (directional: irradiance; point: irradiance at 1 m)."""
        return [float(light.intensity) for light in self.lights]

    @classmethod
    def from_entries(cls, entries: Iterable[Any]) -> Lights:
        """Lights from capture.yaml / scene.yaml entries: dicts with ``direction`` or ``position``
        (exactly one) and ``intensity`` (:func:`light_from_dict`), or schema entries with a
        ``to_light()`` (:class:`polarshape.io.capture.LightSpec`)."""
        return cls(tuple(e.to_light() if hasattr(e, "to_light") else light_from_dict(e) for e in entries))


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



def ring_lights(count: int, radius_m: float, distance_m: float, intensity: float = 1.0, *,
                center_xy: tuple[float, float] = (0.0, 0.0), phase_deg: float = 0.0) -> tuple[PointLight, ...]:
    """A ring of LEDs: ``count`` point lights evenly spaced on a circle of ``radius_m`` in the plane
    z = ``distance_m`` (camera frame, metres; 0 = a ring around the lens), centred on
    ``center_xy``, the first at azimuth ``phase_deg`` (from +x toward +y, image down).

    Raises:
        ValueError: count < 1, radius ≤ 0, distance < 0, intensity < 0, or a non-finite value.
    """
    values = (radius_m, distance_m, intensity, phase_deg, *center_xy)
    if not all(math.isfinite(float(v)) for v in values):
        raise ValueError(f"ring: every value must be finite; got radius_m={radius_m}, distance_m={distance_m}, "
                         f"intensity={intensity}, phase_deg={phase_deg}, center_xy={list(center_xy)}")
    if count < 1 or not radius_m > 0 or distance_m < 0:
        raise ValueError(f"ring: need count >= 1, radius_m > 0 and distance_m >= 0 (metres in front of the camera); "
                         f"got count={count}, radius_m={radius_m}, distance_m={distance_m}")
    phase = math.radians(phase_deg)
    return tuple(
        PointLight((center_xy[0] + radius_m * math.cos(phase + 2 * math.pi * i / count),
                    center_xy[1] + radius_m * math.sin(phase + 2 * math.pi * i / count), float(distance_m)), intensity)
        for i in range(count)
    )
