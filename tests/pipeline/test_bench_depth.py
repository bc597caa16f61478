"""Depth metrics of a photos-only run against the sensor's (pipeline/bench/depth.py), on the
exact room of tests/stages/exact_room.py: every figure is worked out from the exact depth."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.bench.depth import depth_metrics, sensor_depth
from stages.common.capture import Capture
from stages.common.io import write_label_png
from tests.stages.exact_room import room_capture

S = 2.0  # the photos-only run's lengths are half the metres


def _stage(run: Path, stage: str) -> Path:
    d = run / stage / "k"
    d.mkdir(parents=True)
    return d


def _runs(tmp: Path, with_sources: bool) -> tuple[Path, Path, dict]:
    """(photos run, reference run, what was planted): the reference holds the exact room;
    the photos-only run half-size maps of it in half-metres with planted holes and errors."""
    frames = room_capture(tmp / "room")
    cap = Capture.load(frames)
    ref, photos = tmp / "ref", tmp / "photos"
    for st in ("ingest", "align"):
        cap.save(_stage(ref, st) / "frames.json")
    sem = _stage(ref, "semantics")
    labelled = []
    for f in cap.frames:
        d = sensor_depth(cap, f.stem)  # [48, 64] metres
        lab = np.full(d.shape, 3, np.uint8)  # object
        lab[24:, :] = 0  # "floor": the lower half; "wall": the top rows
        lab[:8, :] = 1
        write_label_png(sem / f"{f.stem}.png", lab)
        labelled.append(replace(f, label=sem / f"{f.stem}.png"))
    classes = {0: "floor", 1: "wall", 3: "object"}
    replace(cap.with_frames(tuple(labelled)), classes=classes).save(sem / "frames.json")
    # the photos-only run: poses at half scale, maps at half size and in half-metres; its
    # SfM tracks every 4th pixel of the full-size maps, those of the lower half 10 cm off
    moved = []
    tracks = _stage(photos, "align") / "tracks"
    tracks.mkdir()
    for f in cap.frames:
        p = np.asarray(f.pose, np.float64).copy()
        p[:3, 3] /= S
        exact = sensor_depth(cap, f.stem)
        t = np.zeros_like(exact)
        t[::4, ::4] = exact[::4, ::4]
        t[24:] = np.where(t[24:] > 0, t[24:] + 0.10, 0.0)
        np.save(tracks / f"{f.stem}.npy", (t / S).astype(np.float32))
        moved.append(replace(f, pose=p, depth=tracks / f"{f.stem}.npy"))
    moved_cap = replace(cap.with_frames(tuple(moved)), depth_scale=1.0, depth_invalid=())
    moved_cap.save(photos / "align" / "k" / "frames.json")
    dep = _stage(photos, "depth")
    (dep / "depth").mkdir()
    (dep / "sources").mkdir()
    want = {
        "pixels": 0,
        "read": 0,
        "near": 0,
        "tight": 0,
        "rel": [],
        "by": {1: [0, 0], 2: [0, 0], 3: [0, 0]},
    }
    for f in cap.frames:
        exact = sensor_depth(cap, f.stem)[1::2, 1::2]  # [24, 32] at the half-size centres
        got = exact.copy()
        got[:, :8] = 0  # a hole: the left quarter
        got[12:, 8:16] += 0.10  # off by 10 cm
        got[12:, 16:20] += 0.02  # off by 2 cm
        # a wrong plane pasted on the object rows 8-11 of the plane columns 20-23: the depth of
        # z = 0.3 m (a decoy table top) along those pixels' rays, where it lies before the
        # camera and more than 10 cm before what the view sees (17 pixels of the 8 views)
        K = f.intrinsics.scaled(32, 24).K
        v, u = np.mgrid[8:12, 20:24]
        r = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
        rz = r @ np.asarray(f.pose)[2, :3]
        t = (0.3 - np.asarray(f.pose)[2, 3]) / np.where(np.abs(rz) > 1e-6, rz, np.nan)
        seen = got[8:12, 20:24]
        paste = np.isfinite(t) & (t > 0) & (seen > 0) & (t < seen - 0.1)
        got[8:12, 20:24] = np.where(paste, t, seen)
        code = np.where(got > 0, 1, 0).astype(np.uint8)
        code[:, 16:24] = np.where(got[:, 16:24] > 0, 2, 0)  # planes
        code[:, 24:] = np.where(got[:, 24:] > 0, 3, 0)  # field
        np.save(dep / "depth" / f"{f.stem}.npy", (got / S).astype(np.float32))
        if with_sources:
            write_label_png(dep / "sources" / f"{f.stem}.png", code)
        ok = (got > 0) & (exact > 0)
        err = np.abs(got - exact)[ok]
        want["pixels"] += got.size
        want["read"] += int((got > 0).sum())
        want["near"] += int((err < 0.05).sum())
        want["tight"] += int((err < 0.03).sum())
        want["rel"].append(err / exact[ok])
        for c in (1, 2, 3):
            sel = ok & (code == c)
            want["by"][c][0] += int((np.abs(got - exact)[sel] < 0.05).sum())
            want["by"][c][1] += int(sel.sum())
    # the plane fill's planes in the photos-only run's world (half-metres): the room's floor
    # and walls, and a table top nothing lies on
    planes = [
        {"kind": "floor", "normal": [0, 0, 1], "offset": 0.0, "support": 9},
        {"kind": "wall", "normal": [1, 0, 0], "offset": 0.0, "support": 9},
        {"kind": "wall", "normal": [1, 0, 0], "offset": 4.0 / S, "support": 9},
        {"kind": "wall", "normal": [0, 1, 0], "offset": 0.0, "support": 9},
        {"kind": "wall", "normal": [0, 1, 0], "offset": 3.0 / S, "support": 9},
        {"kind": "top", "normal": [0, 0, 1], "offset": 0.3 / S, "support": 9},
    ]
    facts = {"plane_fill": {"planes": planes}}
    report = {"stages": [{"name": "depth", "key": "k", "facts": facts}]}
    (photos / "report.json").write_text(json.dumps(report))
    return photos, ref, want


@pytest.mark.parametrize("with_sources", [True, False])
def test_depth_metrics_against_exact_depth(tmp_path, with_sources):
    photos, ref, want = _runs(tmp_path, with_sources)
    m = depth_metrics(photos, ref)
    assert m["scale"] == pytest.approx(S, rel=1e-9)  # from the poses: metres again
    assert m["views"] == 8
    assert m["coverage"] == pytest.approx(100.0 * want["read"] / want["pixels"], abs=0.01)
    assert m["coverage"] < 76.0  # the left quarter is a hole
    assert m["within_5cm"] == pytest.approx(100.0 * want["near"] / m["compared"], abs=0.01)
    assert m["within_3cm"] == pytest.approx(100.0 * want["tight"] / m["compared"], abs=0.01)
    rel = np.concatenate(want["rel"])
    assert m["absrel"] == pytest.approx(rel.mean(), abs=1e-4)
    if with_sources:
        for c, name in ((1, "stereo"), (2, "planes"), (3, "field")):
            near, n = want["by"][c]
            assert m["sources"][name]["within_5cm"] == pytest.approx(100.0 * near / n, abs=0.01)
        assert m["sources"]["field"]["within_5cm"] == 100.0  # untouched columns
        assert m["sources"]["stereo"]["within_5cm"] < 60.0  # the 10 cm error lies there
    else:  # no sources/: every reading is stereo's
        assert m["sources"]["stereo"]["coverage"] == m["coverage"]
        assert m["sources"]["planes"]["coverage"] == 0.0
    # the classes: rows 0-3 of the half-size maps are wall, 12- floor, the rest object; the
    # hole is a quarter of every class's pixels
    for name in ("floor", "wall", "object"):
        assert m["classes"][name]["coverage"] == pytest.approx(75.0, abs=3.0)
    assert m["classes"]["wall"]["within_5cm"] == 100.0  # the errors lie in rows 12-
    # floor rows: columns 8-15 of the 24 read are 10 cm off, 16-19 2 cm (within)
    assert m["classes"]["floor"]["within_5cm"] == pytest.approx(100.0 * 16 / 24, abs=0.01)
    cross = m["source_classes"]
    if with_sources:  # the floor's 10 cm error is all stereo's; the planes' 2 cm within 3
        assert cross["stereo"]["floor"]["within_5cm"] == 0.0
        assert cross["planes"]["floor"]["within_3cm"] == 100.0
        assert cross["stereo"]["wall"]["within_5cm"] == 100.0
        # a source's share of a class's pixels: 8 of the 32 columns each
        assert cross["planes"]["floor"]["coverage"] == pytest.approx(25.0, abs=3.0)
    else:
        assert cross["stereo"]["floor"] == m["classes"]["floor"]
        assert cross["planes"]["floor"]["compared"] == 0
    # per plane: the plane-filled pixels whose depth is a plane's along their rays. The maps
    # here are the render read at every second pixel, half a pixel off the half-size rays,
    # so the room's own surfaces match their planes only where depth changes slowly; the
    # decoy was pasted along those rays exactly, and the 2 cm block, the counter and the
    # box are no plane's
    if with_sources:
        per = {(p["kind"], tuple(p["normal"]), p["offset"]): p for p in m["planes"]}
        wrong = per.pop(("top", (0, 0, 1), 0.3 / S))  # pasted where nothing lies on it
        assert wrong["fills"] > 0 and wrong["within_5cm"] == 0.0
        assert per[("floor", (0, 0, 1), 0.0)]["fills"] > 0
        assert per and all(p["within_3cm"] == 100.0 for p in per.values())
        n_planes = round(m["sources"]["planes"]["coverage"] * m["pixels"] / 100)
        fills = sum(p["fills"] for p in per.values()) + wrong["fills"]
        assert fills + m["planes_unmatched"] == n_planes
        assert m["planes_unmatched"] > 0
    else:
        assert m["planes"] == [] and m["planes_unmatched"] == 0


def test_depth_metrics_ratio_bands_and_tracks(tmp_path):
    """median_ratio is 1 where the readings are exact and above 1 where they lie beyond the
    sensor; the bands split the readings by sensor depth; the SfM tracks (the align stage's
    depth maps) are scored on their own: half of them planted 10 cm off."""
    photos, ref, _ = _runs(tmp_path, True)
    m = depth_metrics(photos, ref)
    assert m["sources"]["field"]["median_ratio"] == pytest.approx(1.0, abs=1e-4)  # untouched
    # stereo: half of its readings 10 cm beyond (the median between 1 and those)
    assert m["sources"]["stereo"]["median_ratio"] > 1.0
    assert sum(b["compared"] for b in m["bands"].values()) == m["compared"]
    t = m["tracks"]
    assert t is not None and t["compared"] > 0
    assert t["within_5cm"] == pytest.approx(50.0, abs=0.01)  # every track read; half off
    assert t["median_ratio"] >= 1.0
    assert sum(b["compared"] for b in t["bands"].values()) == t["compared"]
    # per class of the reference's labels: the planted error is the floor's (the lower half)
    by = t["classes"]
    assert set(by) == {"floor", "wall", "object"}
    assert sum(c["compared"] for c in by.values()) == t["compared"]
    assert by["floor"]["within_5cm"] == 0.0 and by["floor"]["median_ratio"] > 1.0
    assert by["wall"]["within_5cm"] == by["object"]["within_5cm"] == 100.0


def test_sensor_depth_is_read_as_the_reference_plan_read_it(tmp_path):
    """The reference's sensor depth comes from its align stage's frames (the poses stage moves
    it into the colour camera when SfM estimates that camera's intrinsics), not from the
    ingested maps in the depth camera's pixels: ingest's maps here are planted 1 m off."""
    photos, ref, want = _runs(tmp_path, True)
    ing = Capture.load(ref / "ingest" / "k" / "frames.json")
    far = []
    for f in ing.frames:
        np.save(tmp_path / f"{f.stem}-far.npy", (sensor_depth(ing, f.stem) + 1.0).astype("f4"))
        far.append(replace(f, depth=tmp_path / f"{f.stem}-far.npy"))
    ing.with_frames(tuple(far)).save(ref / "ingest" / "k" / "frames.json")
    m = depth_metrics(photos, ref)
    assert m["within_5cm"] == pytest.approx(100.0 * want["near"] / m["compared"], abs=0.01)
    assert m["within_3cm"] == pytest.approx(100.0 * want["tight"] / m["compared"], abs=0.01)
