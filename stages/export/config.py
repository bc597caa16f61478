"""Export settings."""

from dataclasses import dataclass


@dataclass(frozen=True)
class ExportConfig:
    impl: str = "files"  # the only implementation: write the run's user-facing files
    title: str = ""  # title drawn above the plan picture and the SVG ("" = none)
    tolerance: float = 0.02  # vector plans: polygon simplification tolerance (metres)
    min_area: float = 0.02  # components.json and report: components smaller (m²) left out
