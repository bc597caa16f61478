"""The real captures from their photos alone (slow): the plan from the colour images and
intrinsics only, scored against the plan the same frames give with their sensor depth (and
the kitchen's poses), as `python -m pipeline.bench.real` scores it (reference cells beyond
the reference's points excluded). Each test holds the figures measured at its settings, less
a noise margin (the SfM and RANSAC samples move a plan by a point or two between runs).
Small settings keep each near three minutes of one core: 20 frames at 240 px, 50 NeRF steps,
the MVR plan.

The office has no poses: the reference's come from SfM too (with depth for the scale), so
the pose errors between its two runs say nothing and only registration is held. The bars
are held against the sensor depth at the dataset's poses (res["dataset_poses"]); the test
also holds the measuring stick (the sensor depth at SfM poses: metric, near the dataset's
poses) and the depth metrics. SfM reads
its renders' own 600x340 images (poses.full_size_images) while the rest works at 240 px:
from the 240x136 images alone 9 of these 20 frames registered (three models), too few for a
plan."""

from __future__ import annotations

import pytest

from tests.conftest import shared_capture

MARGIN = 3.0  # points below the measured figure that still pass
# the semantics settings that find the office's walls in the mesh (README, photos-only
# accuracy); configs/phone.yaml adds the walls found in the readings (semantics.point_walls.enabled)
# and the floor filled inside the hull of the surface and the cameras (floor_fill_hull)
WALLS = ["semantics.walls.min_height=0.7", "semantics.walls.min_area=0.5"]

# measured on the 7-Scenes kitchen, these settings, four runs with SfM on the 240 px images
# (19 of 20 registered, ATE 4.8-4.9 cm, scale x1.057-1.063 from the priors): fwIoU 40.8 /
# 38.3 / 38.1 / 38.9, floor 40.8 / 34.8 / 35.4 / 35.4, wall 0.0, object 43.2 / 41.7 / 41.3 /
# 42.4; one with SfM on the originals at 480 px (poses.full_size_images: 20 of 20, ATE 4.4
# cm, x1.026, the floor a fitted plane): 38.1, floor 32.4, object 42.4; again: 37.8, floor
# 32.2, object 41.9. The bars are the lowest of each.
# Its photos-only mesh holds no floor (stereo finds nothing on the plain floor; the surface
# starts at the counters): the floor is filled at z = 0 where views look down through free
# space, inside the hull of the surface and the cameras (semantics.floor_fill.no_plane);
# without that fill, in the same runs, fwIoU 30.8 / - / 29.5 / 30.2, floor 0.0, object
# unchanged, 90 % of the reference's floor cells unknown (now 40-46 %; 7-8 % of its object
# cells became floor). Before the align stage found the floor under the counter tops (sparse
# SfM points: 2 % of them on the floor) it gave 10.2 / 3.2 / 0.0 / 13.2; with the stereo
# readings alone (depth.field.fill=false) 0.1: stereo covers 26 % of its pixels, so
# the default (auto) trains the field. Wall stays at 0: no wall plane is found; the
# reference's wall cells are unknown (55-64 %) or object (21-34 %) in the photos-only plan.
# With the walls found in the readings (phone.yaml's semantics.point_walls), two runs (SfM on
# the 480 px originals), each against its own run without them (same SfM, stereo, fusion):
# fwIoU 37.6 -> 38.4 and 38.2 -> 39.8, wall 0 -> 26.2 and 0 -> 39.2 (the wall behind the
# counters; a degree of turn between the two runs' frames moves its thin band of cells),
# floor 32.8 -> 32.9 and 33.9 -> 34.1, object 41.4 -> 41.0 and 41.9 -> 41.8; a third run
# (this test, both captures in 3.9 minutes, 210 CPU-s): 39.4, wall 38.7, floor 32.9, object
# 41.6. The bars are the lowest of every run (fwIoU and floor: the earlier runs'); wall is
# held at 15 (found at all: 0 without).
# With the stated focal checked (poses.self_calibrate auto: the kitchen's one K, 585 px, is
# its depth camera's; the colour focal adopted ~526 px), one run: fwIoU 52.8, floor 41.1,
# wall 41.7, object 57.7 (the sensor at SfM poses against at the dataset's: rotation 1.61
# degrees, ATE 4.9 cm); depth within 5 cm 59.8 %, SfM tracks 86.5 %. The bars hold the gain
# less the spread of the earlier runs (about 3 points) beside MARGIN; wall stays at 15.
KITCHEN = {"fwiou": 49.0, "floor": 37.0, "object": 53.0, "wall": 15.0}


# measured on Replica office0, these settings: fwIoU 26.4 / 25.6 / 29.9 / 28.3, floor 30.1 /
# 30.1 / 28.8 / 28.1, object 24.4 / 24.1 / 27.9 / 27.0 (20 of 20 registered, scale x1.244
# from the priors: the virtual camera rides at 1.76 m, not the 1.45 m of a hand-held phone;
# the last two runs with the photos-only depth step's field trained by its stereo coverage
# rule); the lowest are held. Wall (17.8 / 9.3 / 46.8 / 37.3: a few thin bands of cells) is
# too noisy to hold. With phone.yaml's point walls and the floor filled inside the hull of
# the surface and the cameras (floor_fill_hull, its rays unbounded), three runs: fwIoU 36.6 /
# 37.3 / 36.0, floor 45.7 / 46.0 / 45.4, wall 45.4 / 48.4 / 40.6, object 26.1 / 26.8 / 26.1
# (the first against 29.0, floor 28.7, wall 45.4, object 26.3 from the same SfM, stereo and
# fusion without them). The SfM samples moved the earlier runs' fwIoU over 4 points: the bars
# are the lowest less 2.0 (fwIoU 36.0) and 3.4 (floor 45.4) beside MARGIN; object keeps the
# earlier runs' lowest. With the plane fill on by default (23 % of its fills dropped by the
# check, so it stays), one run: fwIoU 41.8, floor 54.2, wall 40.1, object 29.1, depth within
# 5 cm 82.6 % at 77.5 % coverage (the kitchen's fill drops 34 % and is undone: 52.5 against
# the sensor at SfM poses, 53.9 at the dataset's).
OFFICE = {"fwiou": 34.0, "floor": 42.0, "object": 24.1}


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, capture, bars, registered",
    [
        ("kitchen", "7scenes-redkitchen", KITCHEN, 19),
        ("office", "replica-office0", OFFICE, 18),  # of 20 (measured: 20 each)
    ],
)
def test_photos_only_plan_against_the_sensor_plan(tmp_path, name, capture, bars, registered):
    from pipeline.bench.real import measure, summary

    src = shared_capture(capture)
    common = ["ingest.max_side=240", "run.methods=[mvr]"]
    photo = ["--config", "configs/phone.yaml"]
    for s in [*common, *WALLS, "depth.field.train.time_budget=0", "depth.field.train.max_steps=50"]:
        photo += ["--set", s]
    ref = [x for s in common for x in ("--set", s)]
    res = measure(src, tmp_path, photo, ref, frames=20)
    print(f"\n{name}: {summary(res)}")
    # the bars were measured against the sensor's depth at the dataset's poses (the office:
    # at its own SfM poses)
    old = res["dataset_poses"]
    got = {"fwiou": old["plan"]["fwiou"], **old["plan"]["per_class"]}
    assert res["poses"]["registered"] >= registered
    for key, value in bars.items():
        assert got[key] >= value - MARGIN, (key, got)
    # the measuring stick: the sensor's depth at SfM poses, whose scale the sensor gives
    # (kitchen against its dataset poses: x0.984 at 100 frames 640x480, 3.5 degrees, 4.7 cm)
    both = res["references"]["poses"]
    assert both["registered"] >= registered
    assert abs(both["align_scale"] - 1.0) < 0.05, both
    assert both["rot_err_deg_median"] < 8.0, both
    assert res["references"]["scale"]["method"] == "depth"
    # the depth metrics: every view, readings on a part of it, a share within 5 cm
    depth = res["depth"]
    assert depth["views"] >= registered
    assert 10.0 < depth["coverage"] <= 100.0 and depth["within_5cm"] > 5.0, depth
