"""Numerical stability: the units and the offset of the world, and determinism.

Scale and offset: the same room with the world mapped by x -> s x + o (poses' translations
scaled and shifted, depth scaled, written as float32 .npy metres: uint16 millimetres overflow
at s = 1e3 and round away at s = 1e-3) must give the same plan up to that similarity, once
every config value in metres is scaled with it (`metre_fields`, found from the config
comments). Two places are not scale-invariant by design and are set aside in those runs:
`fusion.raycast` (the clean depth is written as uint16 mm, stages/fusion/tsdf.py `_raycast`)
and `stages.common.io.MAX_DEPTH_M` (an absolute 20 m sensor-range cut); a strict xfail shows
what the default ray-cast path does at s = 1e-3. Degenerate inputs: test_degenerate.py.
"""

from __future__ import annotations

import dataclasses
import glob
import inspect
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import stages.common.io as sio
from pipeline.config import stage_configs
from stages.common.blueprint import Blueprint, Grid
from stages.common.capture import UNKNOWN, read_layout
from stages.common.io import read_depth, write_json
from tests.runs import VOXEL, assert_finite_outputs, run_ok, small_room


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return small_room(tmp_path_factory.mktemp("stab") / "room")


# ---- scale and offset ---------------------------------------------------------------------
_FLOAT_FIELD = re.compile(r"^\s+(\w+): float(?: \| None)? = ([^#]*)(#.*)?$")


def metre_fields() -> dict[str, dict[str, int]]:
    """stage -> {field: power of the length unit} for every float config field whose comment
    gives metres ("metres", "(m)": 1; "m²": 2). These move with the world's unit.

    A field's comment is its trailing comment and the comment lines that continue it, or,
    when it has none, the comment lines right above it (both styles are in use).
    """
    out: dict[str, dict[str, int]] = {}
    for stage, cls in stage_configs().items():
        for c in [cls, *(type(getattr(cls(), f.name)) for f in dataclasses.fields(cls))]:
            if not dataclasses.is_dataclass(c):
                continue
            prefix = stage if c is cls else f"{stage}.{_field_of(cls, c)}"
            lines = inspect.getsource(c).splitlines()
            for i, line in enumerate(lines):
                m = _FLOAT_FIELD.match(line)
                if not m:
                    continue
                text, step = (m.group(3), 1) if m.group(3) else ("", -1)
                j = i + step
                while 0 <= j < len(lines) and lines[j].lstrip().startswith("#"):
                    text += " " + lines[j]
                    j += step
                if "m²" in text:
                    out.setdefault(prefix, {})[m.group(1)] = 2
                elif re.search(r"\bmetres\b|\(m\)", text.replace("millimetres", "")):
                    out.setdefault(prefix, {})[m.group(1)] = 1
    return out


def _field_of(cls: type, sub: type) -> str:
    return next(f.name for f in dataclasses.fields(cls) if type(getattr(cls(), f.name)) is sub)


def scaled_sets(s: float) -> list[str]:
    """--set options scaling every metre-valued config field (and the fusion voxel) by s."""
    defaults = {name: cls() for name, cls in stage_configs().items()}
    sets = []
    for prefix, fields in metre_fields().items():
        obj = defaults[prefix.split(".")[0]]
        for part in prefix.split(".")[1:]:
            obj = getattr(obj, part)
        for name, power in fields.items():
            v = VOXEL if (prefix, name) == ("fusion", "voxel") else getattr(obj, name)
            if v is not None:
                sets += ["--set", f"{prefix}.{name}={v * s**power!r}"]
    return sets


def test_metre_fields_found():
    """The comment scan finds the length settings of every stage that has them."""
    f = metre_fields()
    assert {"voxel", "depth_min", "depth_max"} <= set(f["fusion"])
    assert {"cell", "pad", "floor_band", "ceiling_cut"} <= set(f["project"])
    assert "plane_dist" in f["align"]
    assert "cell" not in f.get("blueprint.blunf", {})  # the field works in [-1, 1]


def transformed(src: Path, dst: Path, s: float, o: tuple[float, float, float]) -> Path:
    """A copy of capture src with the world mapped by x -> s x + o (and its GT plan)."""
    o_ = np.asarray(o, np.float64)
    dst.mkdir(parents=True)
    for sub in ("images", "labels"):
        shutil.copytree(src / sub, dst / sub)
    shutil.copyfile(src / "labels.json", dst / "labels.json")
    (dst / "depth").mkdir()
    for p in sorted((src / "depth").iterdir()):
        d = read_depth(p).astype(np.float64) * s  # [H, W] metres in the new unit
        np.save(dst / "depth" / f"{p.stem}.npy", d.astype(np.float32))
    cams = json.loads((src / "cameras.json").read_text())
    for e in cams["frames"].values():
        pose = np.asarray(e["pose"], np.float64)
        pose[:3, 3] = s * pose[:3, 3] + o_
        e["pose"] = pose.tolist()
    write_json(dst / "cameras.json", cams)
    gt = Blueprint.load(src / "gt" / "blueprint.npz")
    g = gt.grid
    (dst / "gt").mkdir()
    grid = Grid((s * g.origin[0] + o_[0], s * g.origin[1] + o_[1]), s * g.cell, g.shape)
    Blueprint(gt.labels, grid, gt.classes).save(dst / "gt" / "blueprint.npz")
    return dst


def _plans(out: Path) -> dict[str, Blueprint]:
    """method -> plan of a finished run."""
    plans = {}
    for d in glob.glob(f"{out}/blueprint/*/"):
        method = json.loads(Path(d, "meta.json").read_text())["impl"]
        plans[method] = Blueprint.load(Path(d, "blueprint.npz"))
    return plans


def _align_T(out: Path) -> np.ndarray:
    return np.asarray(json.loads(next(out.glob("align/*/align.json")).read_text())["T"])


def read_through(
    ref_out: Path, out: Path, s: float, o, method: str
) -> tuple[Blueprint, np.ndarray]:
    """(reference plan, the other run's plan read at the reference cell centres mapped through
    the similarity): aligned ref -> capture world (T0^-1) -> s x + o -> aligned other (T1)."""
    ref, other = _plans(ref_out)[method], _plans(out)[method]
    c = ref.grid.centers().reshape(-1, 2)  # [N, 2]
    p = np.c_[c, np.zeros(len(c)), np.ones(len(c))].T  # [4, N] floor points, aligned world
    x = np.linalg.solve(_align_T(ref_out), p)  # [4, N] capture world
    x[:3] = s * x[:3] + np.asarray(o, np.float64)[:, None]
    q = (_align_T(out) @ x)[:2].T  # [N, 2] in the other run's aligned world
    return ref, other.sample(q).reshape(ref.grid.shape)


def area_fractions(labels: np.ndarray) -> dict[int, float]:
    return {int(k): float((labels == k).mean()) for k in np.unique(labels)}


# (s, o): 1e-3 and 1e3 change the unit; 1e4 m moves the room far from the origin.
SIMILARITIES = {
    "scale_1e-3": (1e-3, (0.0, 0.0, 0.0)),
    "scale_1e3": (1e3, (0.0, 0.0, 0.0)),
    "offset_1e4": (1.0, (1e4, -1e4, 1e4)),
}
NO_RAYCAST = ["--set", "fusion.raycast=false"]


@pytest.fixture(scope="module")
def reference(room, tmp_path_factory) -> Path:
    """The room through the same .npy depth path at s = 1, o = 0."""
    base = tmp_path_factory.mktemp("ref")
    cap = transformed(room, base / "cap", 1.0, (0.0, 0.0, 0.0))
    run_ok(cap, base / "run", *scaled_sets(1.0), *NO_RAYCAST)
    return base


OFFSET_XFAIL = pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason="two causes, measured: (1) stages/project/points.py stores world xyz as float32 in "
    "points.npz: at 1e4 m a coordinate keeps ~1 mm, which moves a few % of the points to the "
    "next 2 cm cell (storage alone: ~97 % of the MVR cells agree; 1e5 m: 77 %; 1e6 m: 7 %; "
    "with align.manhattan=false, MVR ~93 %, BluNF ~96 %); (2) align's Manhattan yaw turns "
    "the world about the origin, so the room is also turned about a point 14 km away: the "
    "whole-cell offset becomes a sub-cell one (plan re-gridded; MVR ~87 %, BluNF ~95 %) and "
    "evaluate, which takes a plan built from given poses to be in the GT frame, scores it "
    "pAcc ~54 instead of ~80",
)


@pytest.mark.parametrize(
    "name", ["scale_1e-3", "scale_1e3", pytest.param("offset_1e4", marks=OFFSET_XFAIL)]
)
def test_plan_invariant_under_similarity(reference, room, tmp_path, monkeypatch, name):
    """Same plan up to x -> s x + o, every metre setting scaled with the world.

    Tolerances. The inputs of every stage differ only by float rounding (relative ~1e-7),
    which can flip a point lying on a cell border or a near-tie of the trained field, and
    nothing else: MVR (a vote, no randomness) must agree on >= 99.5 % of the cells known
    to either plan, BluNF on >= 99 % of all cells, and no class may gain or lose more than
    0.5 % of the plan's area. Measured at 1e-3 and 1e3: MVR 100 %, BluNF 99.98-99.99 %,
    area fractions equal to 1e-4; for scale, BluNF with another seed agrees on only ~87 %
    at these 60 steps, so the bound is far tighter than the method's own noise.
    """
    s, o = SIMILARITIES[name]
    if s > 20:  # the 20 m sensor-range cut would drop every reading of a kilometre-size room
        monkeypatch.setattr(sio, "MAX_DEPTH_M", math.inf)
    cap = transformed(room, tmp_path / "cap", s, o)
    report = run_ok(cap, tmp_path / "run", *scaled_sets(s), *NO_RAYCAST)
    assert_finite_outputs(tmp_path / "run")
    ref_report = json.loads((reference / "run" / "report.json").read_text())

    ref, mvr = read_through(reference / "run", tmp_path / "run", s, o, "mvr")
    known = (ref.labels != UNKNOWN) | (mvr != UNKNOWN)
    mvr_agree = float((mvr == ref.labels)[known].mean())
    ref_b, blunf = read_through(reference / "run", tmp_path / "run", s, o, "blunf")
    agree = float((blunf == ref_b.labels).mean())
    fr0, fr1 = area_fractions(ref_b.labels), area_fractions(blunf)
    worst = max(abs(fr0.get(k, 0.0) - fr1.get(k, 0.0)) for k in set(fr0) | set(fr1))
    print(f"{name}: mvr {mvr_agree:.4f}, blunf {agree:.4f}, area fractions within {worst:.4f}")
    assert mvr_agree >= 0.995, f"MVR agrees on {mvr_agree:.2%} of the known cells"
    assert agree >= 0.99, f"BluNF agrees on {agree:.2%} of the cells"
    assert worst <= 0.005, f"a class area fraction moved by {worst:.4f}"
    # Against the equally transformed ground truth: the same scores (1 % of cells = 1 point).
    for method, m in report["metrics"]["blueprint"].items():
        m0 = ref_report["metrics"]["blueprint"][method]
        for k in ("pacc", "completeness"):
            assert abs(m[k] - m0[k]) <= 1.0, (method, k, m[k], m0[k])


@pytest.mark.xfail(
    strict=True,
    raises=AssertionError,
    reason="stages/fusion/tsdf.py _raycast writes the clean depth as uint16 millimetres "
    "(write_depth_png): at s = 1e-3 a 3 m reading becomes 3 mm and rounds to 1 mm steps, so "
    "the projected points land in the wrong cells (at s = 1e3 it clips at 65.5 m)",
)
def test_default_raycast_depth_survives_small_units(reference, room, tmp_path):
    s = 1e-3
    cap = transformed(room, tmp_path / "cap", s, (0.0, 0.0, 0.0))
    run_ok(cap, tmp_path / "run", *scaled_sets(s))  # fusion.raycast left on (the default)
    ref, mvr = read_through(reference / "run", tmp_path / "run", s, (0, 0, 0), "mvr")
    known = (ref.labels != UNKNOWN) | (mvr != UNKNOWN)
    agree = float((mvr == ref.labels)[known].mean())
    print(f"raycast on at s=1e-3: MVR agrees on {agree:.2%} of the known cells")
    assert agree >= 0.99


PERIOD = 0.6  # metres: a multiple of every grid the project stage anchors at world multiples


@settings(max_examples=10, deadline=None)
@given(log_s=st.floats(-3.0, 3.0), k=st.tuples(*[st.integers(-160, 160)] * 3))
def test_projection_and_vote_invariant_property(room, tmp_path_factory, log_s, k):
    """Π then the MVR vote under random similarities: s in [1e-3, 1e3], o = k 0.6 s m.

    Stage-level (no fusion, no align: the floor stays where the capture puts it), so many
    similarities are cheap. The project stage anchors its grids at world multiples of their
    cell: the plan (project.cell, 2 cm) and the top-view occlusion grids (occlusion_cell,
    6 cm, shifted by half of it): an offset that is not a multiple of all of them re-grids
    the plan, so offsets are whole multiples of 0.6 m (measured: a 2 cm shift changes ~1 %
    of the MVR cells, 1.25 m ~50 %). |o| <= 96 m at s = 1: a coordinate there keeps ~1e-5 s
    in float32, 2000 times finer than a cell (see the offset xfail above for farther).
    >= 99 % of the cells known to either plan must agree.
    """
    from stages.blueprint import IMPLS as BP
    from stages.blueprint import BlueprintInputs
    from stages.blueprint.config import BlueprintConfig
    from stages.project import IMPLS as PROJ
    from stages.project import ProjectConfig, ProjectInputs

    s = 10.0**log_s
    off = tuple(s * PERIOD * x for x in k)
    base = tmp_path_factory.mktemp("prop")

    def plan(cap_dir: Path, scale: float) -> Blueprint:
        cap = read_layout(cap_dir)
        cap.save(cap_dir.parent / "frames.json")
        defaults = ProjectConfig()
        pcfg = ProjectConfig(
            **{f: getattr(defaults, f) * scale**p for f, p in metre_fields()["project"].items()}
        )
        (cap_dir.parent / "p").mkdir()
        pts = PROJ[pcfg.impl](
            pcfg, ProjectInputs(cap_dir.parent / "frames.json"), cap_dir.parent / "p"
        )
        (cap_dir.parent / "b").mkdir()
        b = BP["mvr"](
            BlueprintConfig(impl="mvr"), BlueprintInputs(pts.points, pts.grid), cap_dir.parent / "b"
        )
        return Blueprint.load(b.blueprint)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sio, "MAX_DEPTH_M", math.inf)  # the 20 m sensor-range cut (see the top)
        ref = plan(transformed(room, base / "a" / "cap", 1.0, (0.0, 0.0, 0.0)), 1.0)
        other = plan(transformed(room, base / "b" / "cap", s, off), s)
    c = ref.grid.centers().reshape(-1, 2)
    lab = other.sample(s * c + np.asarray(off[:2])).reshape(ref.grid.shape)
    known = (ref.labels != UNKNOWN) | (lab != UNKNOWN)
    agree = float((lab == ref.labels)[known].mean())
    assert agree >= 0.99, f"s={s:g}, o={off}: {agree:.2%} of the known cells agree"


@settings(max_examples=60, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=12),
        elements=st.floats(width=32, allow_nan=True, allow_infinity=True),
    )
)
def test_read_depth_never_returns_nan_inf_or_negative(tmp_path_factory, d):
    """Whatever a float .npy depth map holds, read_depth gives finite metres in [0, 20)."""
    p = tmp_path_factory.mktemp("d") / "d.npy"
    np.save(p, d)
    out = read_depth(p)
    assert out.shape == d.shape and out.dtype == np.float32
    assert np.all(np.isfinite(out)) and np.all(out >= 0) and np.all(out < sio.MAX_DEPTH_M)
    ok = np.isfinite(d) & (d >= 0) & (d < sio.MAX_DEPTH_M)
    assert np.array_equal(out[ok], d[ok]) and np.all(out[~ok] == 0)


def test_same_seed_same_bytes(reference, tmp_path):
    """A fresh run folder, same capture and config as the reference: identical bytes in
    blueprint.npz and in every method's plan."""
    run_ok(reference / "cap", tmp_path / "run", *scaled_sets(1.0), *NO_RAYCAST)
    a, b = reference / "run", tmp_path / "run"
    assert (a / "blueprint.npz").read_bytes() == (b / "blueprint.npz").read_bytes()
    plans = sorted(a.glob("blueprint/*/blueprint.npz"))
    assert len(plans) == 2  # blunf and mvr
    for p in plans:
        assert p.read_bytes() == (b / p.relative_to(a)).read_bytes(), p
