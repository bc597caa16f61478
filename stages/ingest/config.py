"""Configuration of the ingest stage (reading a capture and choosing its frames)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class IngestConfig:
    impl: str = "auto"  # implementation, a key of stages.ingest.IMPLS
    kind: str = "auto"  # capture layout, a key of stages.ingest.READERS, or "auto" to detect
    frames: int = 0  # 0 = all; N = N views spread evenly, first and last included; 1 = middle
    max_side: int = 0  # 0 = keep; else downscale so the longer image side is <= this (pixels)
    check: str = "full"  # "full": decode every selected file; "quick": headers and paths only
