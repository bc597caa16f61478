"""`python -m pipeline` is the `blunf` command."""

import sys

from pipeline.cli import main

sys.exit(main())
