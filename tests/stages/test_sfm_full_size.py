"""The poses stage reads the capture's full-size images while the frames stay downscaled."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from stages.common.capture import Capture
from stages.common.io import read_depth, read_json
from stages.evaluate.poses import pose_metrics
from stages.ingest import IMPLS as INGEST
from stages.ingest.config import IngestConfig, IngestInputs
from stages.poses import IMPLS, PosesConfig, PosesInputs
from stages.poses.fullsize import max_side, sfm_frames
from stages.poses.sfm import sparse_depth
from stages.synth import make_room


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """12 views (30 degrees apart) of a procedural room at 240x180, ingested at 60x45.
    Returns (capture, the ingest stage's frames.json)."""
    tmp = tmp_path_factory.mktemp("fullsize")
    room = make_room(tmp / "room", views=12, seed=0, size=(240, 180))
    frames = INGEST["auto"](IngestConfig(max_side=60), IngestInputs(room), tmp / "ingest").frames
    return room, frames


def test_sift_reads_originals_at_most_full_size_max_side(small: tuple[Path, Path]) -> None:
    working = Capture.load(small[1]).frames
    seen = sfm_frames(working, full=True)
    assert seen[0].image == working[0].original and seen[0].intrinsics.width == 240
    assert max_side(1600, 480, seen, working) == 480  # the cap (pycolmap keeps 240 as is)
    assert max_side(1600, 32, seen, working) == 60  # never below the working size
    assert max_side(1600, 0, seen, working) == 1600  # no cap: max_image_size
    assert max_side(1600, 480, working, working) == 1600  # no original read: as before
    assert sfm_frames(working, full=False) == working


def _sfm(frames: Path, out: Path, **cfg) -> tuple[Capture, dict]:
    out.mkdir()
    o = IMPLS["sfm"](PosesConfig(threads=1, max_features=1024, **cfg), PosesInputs(frames), out)
    return Capture.load(o.frames), read_json(o.sfm)


def test_ingest_keeps_the_full_size_image(small: tuple[Path, Path]) -> None:
    room, frames = small
    f = Capture.load(frames).frames[0]
    assert (f.intrinsics.width, f.intrinsics.height) == (60, 45)
    assert f.original == room / "images" / "0000.png" and f.image != f.original


def test_self_calibrated_sfm_on_full_size_images_at_the_working_size(
    small: tuple[Path, Path], tmp_path: Path
) -> None:
    """SIFT on the 240x180 originals registers every view (at 60x45 none: the second run);
    the focal, keypoints, sparse depth and written model come back at 60x45. Measured: 12 of
    12, ATE 1.2 cm, scale from depth x1.002, focal 46.96 px against 47.09, the sparse depth of
    1904 pixels within 0.5 % (median) of the sensor's."""
    room, frames = small
    got, facts = _sfm(frames, tmp_path / "out", self_calibrate=True)
    true = Capture.load(frames).frames[0].intrinsics  # the synth's exact focal, at 60x45
    gt = {s: np.asarray(p) for s, p in read_json(room / "gt" / "poses.json").items()}
    m = pose_metrics({f.stem: f.pose for f in got.frames}, gt)  # type: ignore[misc]
    want = {"full_size": 12, "sizes": [[240, 180]], "working": [[60, 45]], "max_side": 480}
    assert facts["images"] == want
    assert m["registered"] == 12 and m["ate_rmse_m"] < 0.03
    # the scale from depth reads the 60x45 depth maps under the keypoints: scaled wrongly,
    # they would sample the wrong pixels (or none), and the scale would be off
    assert facts["scale_from"]["method"] == "depth"
    assert m["align_scale"] == pytest.approx(1.0, abs=0.01)
    est = got.frames[0].intrinsics
    assert (est.width, est.height, est.cx, est.cy) == (60, 45, true.cx, true.cy)
    assert est.fx == pytest.approx(true.fx, rel=0.01)
    assert facts["camera"]["estimated"][0]["fx"] == est.fx
    # the written model is in the frames' pixels: each view's sparse depth lands where its
    # (resized) sensor depth says the same
    rec = pycolmap.Reconstruction(tmp_path / "out" / "sparse")
    by_stem = {im.name.split("_", 1)[1].split(".")[0]: im for im in rec.images.values()}
    rel = []
    for f in got.frames:
        d = sparse_depth(rec, by_stem[f.stem], f.intrinsics)  # [45, 60]
        ref = read_depth(f.depth, 1000.0, (65535,))  # type: ignore[arg-type]
        ok = (d > 0) & (ref > 0)
        rel.append(np.abs(d[ok] / ref[ok] - 1.0))
    rel_all = np.concatenate(rel)
    assert len(rel_all) > 200 and np.median(rel_all) < 0.02, np.median(rel_all)
    # the same views read at 60x45 do not register
    with pytest.raises(Exception, match="only 0 of 12 images registered"):
        _sfm(frames, tmp_path / "small", self_calibrate=True, full_size_images=False)
