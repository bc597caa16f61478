"""No alignment: the poses are kept as given (the world is assumed z up, floor at z = 0)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stages.align.config import AlignConfig, AlignInputs, AlignOutputs
from stages.align.planes import finish, load

log = logging.getLogger(__name__)


def run(cfg: AlignConfig, inputs: AlignInputs, out: Path) -> AlignOutputs:
    """Write the frames unchanged with T = identity."""
    log.debug("align none: %s", cfg)  # the full config: meta.json
    cap = load(inputs)
    info = {
        "method": "none",
        "inlier_fraction": None,
        "up_from": "none",
        "notes": "align.impl=none: poses kept as given",
    }
    return finish(cap, out, np.eye(3), None, info)
