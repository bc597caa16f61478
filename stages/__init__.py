"""Pipeline stages: each `stages/<stage>/<impl>.py` exposes `run(cfg, inputs, out) -> Outputs`.

numpy is imported before anything else on purpose: pycolmap exports its own zlib symbols and,
when loaded first, corrupts later PNG / savez_compressed calls (`free(): invalid pointer`).
"""

import numpy  # noqa: F401  (must precede any pycolmap import; see tests/test_import_order.py)
