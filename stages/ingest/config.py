"""Configuration and the input / output contract of the ingest stage (reading a capture
and choosing its frames)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal


@dataclass(frozen=True)
class IngestConfig:
    impl: str = "auto"  # implementation, a key of stages.ingest.IMPLS
    kind: str = "auto"  # capture layout, a key of stages.ingest.READERS, or "auto" to detect
    frames: int = 0  # 0 = all; N = N views spread evenly, first and last included; 1 = middle
    max_side: int = 0  # 0 = keep; else downscale so the longer image side is <= this (pixels)
    photo_max_side: int = 640  # photos without given intrinsics and video frames: longer side
    #                            downscaled once to this working size (pixels; 0 = keep;
    #                            max_side wins when set); their intrinsics scale with them
    video_frames: int = 0  # video: frames kept, the sharpest of each of N equal windows;
    #                        0 = by its length (2 a second, 20 to 100)
    # "full": decode every selected file; "quick": headers and paths only
    check: Literal["full", "quick"] = "full"


@dataclass(frozen=True)
class IngestInputs:
    capture: Path  # capture folder in any layout of stages.ingest.READERS (or transforms.json)


@dataclass(frozen=True)
class IngestOutputs:
    STATS: ClassVar[str | None] = "ingest.json"  # its stats file: the report's facts
    frames: Path  # frames.json written by Capture.save

    @classmethod
    def at(cls, out: Path) -> IngestOutputs:
        return cls(frames=Path(out) / "frames.json")
