"""pycolmap loaded before numpy/zlib corrupts the heap (it exports its own deflate/inflate).

Every project module is reached through `stages` or `pipeline`, whose package __init__ imports
numpy first; this checks that PNG and savez_compressed still work after pycolmap is imported
that way, in a fresh interpreter (the failure is a hard abort, not an exception).
"""

import subprocess
import sys

SCRIPT = """
import stages
import pycolmap
import numpy as np
from PIL import Image
a = (np.arange(64 * 64 * 3) % 251).astype(np.uint8).reshape(64, 64, 3)
Image.fromarray(a).save("{d}/x.png")
np.savez_compressed("{d}/x.npz", a=a)
assert (np.asarray(Image.open("{d}/x.png")) == a).all()
assert (np.load("{d}/x.npz")["a"] == a).all()
print("ok")
"""


def test_pycolmap_after_stages_keeps_zlib_working(tmp_path):
    r = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(d=tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "ok"
