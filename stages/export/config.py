"""Configuration and the input / output contract of the export stage."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar


@dataclass(frozen=True)
class ExportConfig:
    impl: str = "files"  # the only implementation: write the run's user-facing files
    title: str = ""  # title drawn above the plan picture and the SVG ("" = none)
    tolerance: float = 0.02  # vector plans: polygon simplification tolerance (metres)
    min_area: float = 0.02  # components.json and report: components smaller (m²) left out


FILES = (
    "blueprint.png",
    "blueprint.npz",
    "blueprint.svg",
    "blueprint.geojson",
    "blueprint.dxf",
    "mesh.ply",
    "transforms.json",
    "components.json",
)


@dataclass(frozen=True)
class ExportInputs:
    blueprint: Path  # blueprint.npz of the product's method
    mesh: Path  # fused mesh.ply
    frames: Path  # frames.json with the final (aligned) poses
    layout: Path | None = None  # the layout stage's plan.json, drawn over blueprint.png (None:
    #                             the classes alone)


@dataclass(frozen=True)
class ExportOutputs:
    STATS: ClassVar[str | None] = "export.json"  # its stats file: the report's facts
    folder: Path
    files: tuple[str, ...] = FILES

    @classmethod
    def at(cls, out: Path) -> ExportOutputs:
        return cls(Path(out))
