"""`blunf synth --realism`: plain walls, smooth floors, exposure, blur and noise do what they
say, and the default room stays what it was."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from pipeline.cli import main
from stages.common.errors import BlunfError
from stages.common.io import read_image, read_json
from stages.synth import make_room
from stages.synth.realism import PRESETS, Realism
from stages.synth.render import Tracer, View, camera_path, intrinsics_for, render
from stages.synth.room import CEILING, FLOOR, WALL, build_room

SIZE = (128, 96)


@pytest.fixture(scope="module")
def scene() -> tuple[Tracer, np.ndarray]:
    room = build_room(3)
    return Tracer(room.parts), camera_path(room, 8, 3)


def _shot(scene, k: int = 0, realism: Realism | None = None, seed: int = 0) -> View:
    tracer, poses = scene
    rng = np.random.default_rng(seed)
    return render(tracer, poses[k], intrinsics_for(*SIZE), realism=realism, rng=rng)


def _grey(v: View) -> np.ndarray:
    return v.rgb.astype(np.float64).mean(-1)


def _detail(v: View, cls: tuple[int, ...]) -> float:
    """Std (grey levels) of the image minus its 2-pixel blur, inside the classes' pixels
    away from their edges: the fine detail stereo and SIFT match on."""
    g = _grey(v)
    inside = ndimage.binary_erosion(np.isin(v.label, cls), iterations=3)
    assert inside.sum() > 100
    return float((g - ndimage.gaussian_filter(g, 2.0))[inside].std())


def _linear(rgb: np.ndarray) -> np.ndarray:
    """Display values back to linear intensity (the renderer's gamma 2.2)."""
    return (rgb.astype(np.float64) / 255.0) ** 2.2


def test_plain_walls_and_ceiling_carry_no_detail_floor_little(scene) -> None:
    tex, plain = _shot(scene, 2), _shot(scene, 2, Realism(surfaces="plain"))
    assert _detail(tex, (WALL, CEILING)) > 8.0  # the textured room: strong detail
    assert _detail(plain, (WALL, CEILING)) < 0.6  # plain paint: quantisation only
    assert _detail(plain, (FLOOR,)) < _detail(tex, (FLOOR,)) / 5  # a smooth floor
    assert _detail(plain, (FLOOR,)) > _detail(plain, (WALL, CEILING))  # ... with some grain
    # furniture keeps its texture; the geometry and labels are the same
    obj = tex.label > CEILING
    assert obj.sum() > 100 and np.array_equal(tex.rgb[obj], plain.rgb[obj])
    assert np.array_equal(tex.depth, plain.depth) and np.array_equal(tex.label, plain.label)


def test_exposure_differs_between_views_by_the_drawn_gain(scene) -> None:
    opts = Realism(exposure=0.5)
    gains = []
    for seed in range(4):
        clean, shot = _shot(scene, 1), _shot(scene, 1, opts, seed)
        gain = shot.camera["exposure_gain"]
        ok = (clean.rgb.max(-1) < 200) & (shot.rgb.max(-1) < 250) & (clean.rgb.min(-1) > 20)
        measured = _linear(shot.rgb)[ok].mean() / _linear(clean.rgb)[ok].mean()
        assert measured == pytest.approx(gain, rel=0.03)
        gains.append(gain)
    assert np.std(np.log2(gains)) > 0.1  # the views do not share one exposure


def test_blur_lowers_the_laplacian_variance(scene) -> None:
    clean, blurred = _shot(scene, 3), _shot(scene, 3, Realism(blur=4.0))
    lap = [ndimage.laplace(_grey(v)).var() for v in (clean, blurred)]
    assert lap[1] < 0.5 * lap[0]
    assert 1.0 <= blurred.camera["blur_px"] <= 4.0
    # blur moves light, it does not add any (in linear intensity, before the gamma)
    assert _linear(blurred.rgb).mean() == pytest.approx(_linear(clean.rgb).mean(), rel=0.01)
    assert np.array_equal(clean.depth, blurred.depth)


def test_noise_has_the_stated_spread_and_follows_the_seed(scene) -> None:
    clean = _shot(scene, 4)
    a, b = (_shot(scene, 4, Realism(noise=0.02), s) for s in (0, 1))
    assert np.array_equal(a.rgb, _shot(scene, 4, Realism(noise=0.02), 0).rgb)
    assert not np.array_equal(a.rgb, b.rgb)
    lin, ref = _linear(a.rgb), _linear(clean.rgb)
    mid = (ref > 0.1) & (ref < 0.5)
    # shot noise sd = 0.02 sqrt(I) (+ read noise 0.005): normalised residuals ~ N(0, 1)
    z = (lin - ref)[mid] / np.sqrt(0.02**2 * ref[mid] + 0.005**2)
    assert 0.8 < z.std() < 1.3 and abs(z.mean()) < 0.1


def test_default_is_unchanged(scene, tmp_path: Path) -> None:
    tracer, poses = scene
    intr = intrinsics_for(*SIZE)
    base = render(tracer, poses[0], intr)
    assert np.array_equal(base.rgb, render(tracer, poses[0], intr, realism=Realism()).rgb)
    assert base.camera == {}
    assert Realism.parse("none") == Realism() == Realism.parse("")
    a = make_room(tmp_path / "a", views=2, seed=3, size=(32, 24))
    b = make_room(tmp_path / "b", views=2, seed=3, size=(32, 24), realism=Realism())
    assert not (a / "gt" / "realism.json").exists()
    for f in sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file()):
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_honest_room_writes_what_it_drew(tmp_path: Path) -> None:
    assert main(["synth", str(tmp_path / "h"), "--views", "3", "--size", "32x24",
                 "--photos-only", "--realism", "honest,noise=0.01"]) == 0  # fmt: skip
    facts = read_json(tmp_path / "h" / "gt" / "realism.json")
    assert facts["options"] == {**PRESETS["honest"], "noise": 0.01}
    assert sorted(facts["views"]) == ["0000", "0001", "0002"]
    assert {"exposure_gain", "blur_px", "blur_deg"} <= set(facts["views"]["0001"])
    assert read_image(tmp_path / "h" / "images" / "0000.png").shape == (24, 32, 3)


def test_bad_realism_is_a_user_error(tmp_path: Path) -> None:
    for bad in ("shiny", "surfaces=glossy", "blur=-1", "noise=x", "focus=2"):
        with pytest.raises(BlunfError, match="realism"):
            Realism.parse(bad)
    assert main(["synth", str(tmp_path / "x"), "--realism", "shiny"]) == 2
    assert not (tmp_path / "x").exists()
    assert Realism.parse("honest,blur=0").blur == 0.0
    assert Realism.parse("honest").surfaces == "plain"
