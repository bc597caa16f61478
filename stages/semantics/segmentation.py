"""What the geometry's segmentation found: each triangle's class and instance, and counts."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stages.common.classes import FLOOR


@dataclass
class Segmentation:
    """Per-triangle class and instance, with what was found."""

    cls: np.ndarray  # [T] uint8 class id or UNKNOWN
    instance: np.ndarray  # [T] int32 object instance (1.., by decreasing area); 0 = none
    area: np.ndarray  # [T] triangle areas (m²)
    planes: list[dict] = field(default_factory=list)  # accepted planes: kind, normal, d, area
    rejected: list[dict] = field(default_factory=list)  # vertical planes that were not walls
    noise_clusters: int = 0  # clusters below object_min_area (unknown)
    noise_triangles: int = 0  # triangles DBSCAN calls noise (unknown)
    floating_clusters: int = 0  # clusters above object_max_gap (unknown)
    resting_clusters: int = 0  # clusters above it that rest on a standing object (objects)
    hidden_stand_clusters: int = 0  # clusters above it with nothing seen under them (objects)
    hanger_triangles: int = 0  # by a surface hanging before a wall, its frame (unknown)
    outside_triangles: int = 0  # object triangles outside the room (outside_unknown)
    floor_z: float = 0.0  # median height of the floor triangles (0 when no floor was found)
    object_base_z: float = 0.0  # height object clusters' lowest points are measured from

    @property
    def has_floor(self) -> bool:
        """Whether any triangle is labelled floor (a floor plane was found)."""
        return bool((self.cls == FLOOR).any())
