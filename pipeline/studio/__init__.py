"""The studio: a run opened in the browser to click, edit and see the edited NeRF render."""

from __future__ import annotations

from pathlib import Path


def serve(run: Path, host: str = "127.0.0.1", port: int = 8080) -> int:
    """`blunf studio RUN`: serve the page until interrupted (viser imported only here)."""
    from pipeline.studio.app import serve as _serve

    return _serve(run, host, port)
