"""report.json: what each stage did (ran, cached, skipped, why, how long) and the metrics."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from stages.common.io import write_json


@dataclass
class StageRecord:
    name: str
    impl: str
    status: str  # ran | cached | skipped
    reason: str = ""
    seconds: float = 0.0
    peak_rss_mb: float | None = None
    key: str | None = None
    facts: dict[str, Any] = field(default_factory=dict)


@dataclass
class Report:
    scene: str
    capture: str
    config: dict
    stages: list[StageRecord] = field(default_factory=list)
    metrics: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    plan: dict[str, Any] = field(default_factory=dict)  # classes' areas and the components
    started: float = field(default_factory=time.time)

    def add(self, rec: StageRecord) -> None:
        self.stages.append(rec)

    def to_json(self) -> dict:
        return {
            "scene": self.scene,
            "capture": self.capture,
            "seconds_total": round(time.time() - self.started, 3),
            "stages": [asdict(s) for s in self.stages],
            "metrics": self.metrics,
            "outputs": self.outputs,
            "plan": self.plan,
            "config": self.config,
        }

    def write(self, path: Path) -> None:
        write_json(path, self.to_json())


def peak_rss_reset() -> None:
    """Reset the kernel's peak-RSS mark of this process (Linux), so each stage gets its own."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_rss_mb() -> float | None:
    """Peak resident memory of this process since the last reset, in MB (Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        return None
    return None
