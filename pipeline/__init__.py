"""Orchestration: config, planner, content-hash cache, report and the command line.

numpy is imported first: pycolmap loaded before numpy/zlib corrupts the heap."""

import numpy  # noqa: F401  (must precede any pycolmap import; see tests/test_import_order.py)
