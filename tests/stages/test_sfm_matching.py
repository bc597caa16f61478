"""The poses stage's image pairs (stages/poses/matching.py): sequential, retrieval, loops."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stages.common.io import read_json
from stages.ingest import load
from stages.poses import IMPLS, PosesConfig, PosesInputs
from stages.poses.config import MatchingConfig, RetrievalConfig
from stages.poses.matching import (
    assign,
    kind_for,
    loop_pairs,
    root_sift,
    sequential_pairs,
    train_words,
    vlad,
)
from stages.synth.make import make_room

ROOT = Path(__file__).resolve().parents[2]


def test_sequential_pairs_are_colmaps_quadratic_overlap() -> None:
    # overlap 3: steps 1, 2, 4 (pycolmap 4 pairs powers of two only with quadratic overlap;
    # the real run below holds the database's pairs equal to these)
    got = sequential_pairs(10, 3)
    want = {(i, j) for i in range(10) for j in range(i + 1, 10) if j - i in (1, 2, 4)}
    assert got == want
    assert max(j - i for i, j in sequential_pairs(100, 10)) == 64  # 2^6: 2^7 is past the end
    assert len(sequential_pairs(1, 5)) == 0


def test_auto_is_exhaustive_for_few_images_then_sequential_then_retrieval() -> None:
    m = MatchingConfig()
    assert kind_for(m, 40) == "exhaustive" and kind_for(m, 41) == "sequential"
    assert kind_for(m, 150) == "sequential" and kind_for(m, 151) == "retrieval"
    assert kind_for(MatchingConfig(kind="sequential"), 5) == "sequential"


def test_loop_pairs_take_the_most_similar_outside_the_window() -> None:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(12, 32))
    v[11] = v[0] + 0.01 * rng.normal(size=32)  # the walk's end looks like its start
    v[1] = v[0]  # and its next view too, but that pair is in the window already
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    window = sequential_pairs(12, 1)  # (i, i + 1)
    got = loop_pairs(v, window, 1)
    assert (0, 11) in got and (1, 11) in got  # each's most similar outside its window
    assert not got & window
    assert all(i < j for i, j in got)


def test_vlad_tells_a_place_from_another() -> None:
    # two "places" whose descriptors come from distinct halves of the descriptor space
    rng = np.random.default_rng(1)
    a = rng.integers(0, 60, size=(400, 128)).astype(np.uint8)
    b = rng.integers(0, 60, size=(400, 128)).astype(np.uint8)
    b[:, :64] += 120
    views = [root_sift(x[rng.choice(400, 200, replace=False)]) for x in (a, a, b, b)]
    cfg = RetrievalConfig(words=8, sample=400, iterations=10)
    w = train_words(views, cfg, seed=0)
    assert np.array_equal(w, train_words(views, cfg, seed=0))  # seeded
    vec = np.stack([vlad(x, w) for x in views])
    assert np.allclose(np.linalg.norm(vec, axis=1), 1.0)
    sim = vec @ vec.T
    assert sim[0, 1] > sim[0, 2] and sim[2, 3] > sim[1, 3]
    assert np.all(np.isfinite(vlad(np.zeros((0, 128), np.float32), w)))


def _descriptors(n: int, per: int, seed: int = 0) -> list[np.ndarray]:
    """n images' RootSIFT of `per` uniform random SIFT descriptors: many rows lie near the
    border between two words, where a float32 sum's last bit picks the word."""
    rng = np.random.default_rng(seed)
    return [root_sift(rng.integers(0, 256, (per, 128)).astype(np.uint8)) for _ in range(n)]


def test_retrieval_distances_do_not_depend_on_the_summation_order() -> None:
    # Permuting the 128 dimensions of descriptors and words changes only the order in which
    # every dot product is summed. Exact distances give the same words, permuted; float32
    # ones (before snap) gave other words for 5 of 5 permutations of this set.
    views = _descriptors(20, 500)
    cfg = RetrievalConfig(words=64, sample=10000, iterations=10)
    w = train_words(views, cfg, seed=0)
    x = np.concatenate(views)
    perm = np.random.default_rng(1).permutation(128)
    assert np.array_equal(train_words([v[:, perm] for v in views], cfg, seed=0), w[:, perm])
    assert np.array_equal(assign(x[:, perm], w[:, perm]), assign(x, w))


_CHILD = """
import hashlib
import numpy as np
from stages.poses.config import RetrievalConfig
from stages.poses.matching import loop_pairs, root_sift, sequential_pairs, train_words, vlad

rng = np.random.default_rng(0)  # as _descriptors(20, 800)
views = [root_sift(rng.integers(0, 256, (800, 128)).astype(np.uint8)) for _ in range(20)]
w = train_words(views, RetrievalConfig(words=64, sample=16000, iterations=8), seed=0)
v = np.stack([vlad(d, w) for d in views])
pairs = sorted(loop_pairs(v, sequential_pairs(20, 2), 3))
for a in (w.tobytes(), v.tobytes(), repr(pairs).encode()):
    print(hashlib.sha1(a).hexdigest())
"""


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="one core: BLAS runs one thread")
def test_retrieval_is_the_same_on_one_and_two_blas_threads() -> None:
    # OpenBLAS takes its thread count once, when numpy loads: each count is its own process.
    # Before the distances were exact (snap), these words, VLAD vectors and loop pairs all
    # differed between one and two threads (as the 70-view room's 270 and 273 loop pairs).
    runs = []
    for n in ("1", "2"):
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": n}
        env["OPENBLAS_NUM_THREADS"] = n
        cmd = [sys.executable, "-c", _CHILD]
        runs.append(subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True))
    (one, _), (two, _) = (p.communicate(timeout=120) for p in runs)
    assert [p.returncode for p in runs] == [0, 0]
    assert len(one.split()) == 3 and one == two  # words, VLAD vectors, loop pairs


def test_retrieval_closes_the_walk_and_registers_every_view(tmp_path: Path) -> None:
    # The procedural room's camera walks once round an ellipse: its last views look where
    # its first did. Sequential pairs with overlap 3 reach 4 views on (gap <= 4); only the
    # retrieved loop pairs can join the walk's two ends (gap n - 1 .. n - 4). The pairs
    # matched (the database's count) are this module's sequential pairs plus the loop pairs.
    n = 36
    room = make_room(tmp_path / "room", views=n, size=(160, 120), seed=0)
    (tmp_path / "ingest").mkdir()
    cap = load(room, tmp_path / "ingest")
    cap.save(tmp_path / "ingest" / "frames.json")
    m = MatchingConfig(kind="retrieval", overlap=3, retrieval=RetrievalConfig(neighbours=3))
    cfg = PosesConfig(impl="sfm", scale_from="none", threads=1, matching=m)
    out = tmp_path / "out"
    out.mkdir()
    IMPLS["sfm"](cfg, PosesInputs(tmp_path / "ingest" / "frames.json"), out)
    f = read_json(out / "sfm.json")
    p = f["match_pairs"]
    assert f["matching"] == "retrieval"
    assert f["registered"] == n and f["models"] == 1
    assert p["pairs"] == len(sequential_pairs(n, 3)) + p["loop_pairs"]
    assert p["pairs"] < p["exhaustive_pairs"] / 2  # cheaper than every pair
    assert p["loop_pairs_verified"] >= n // 2  # most retrieved pairs see the same surfaces
    assert p["longest_gap"] >= n - 4  # the walk's end matched with its start: the loop closes


def test_keyframe_pairs_leave_out_only_long_pairs_between_odd_views() -> None:
    """With keyframes, the sequential pairs between two odd-numbered views (registered to
    the keyframes' model, never mapped) more than two steps apart are left out; every pair
    of an even view, and each odd view's pairs one and two steps on, stay."""
    from stages.poses.matching import keyframe_pairs

    seq = sequential_pairs(480, 10)
    got = keyframe_pairs(480, 10)
    assert got < seq and (len(seq), len(got)) == (3809, 2383)
    assert all(i % 2 == 0 or j - i <= 2 for i, j in got)
    assert seq - got == {(i, j) for i, j in seq if i % 2 and j % 2 and j - i > 2}
    for k in (2, 4, 8):  # every subset mapped first keeps all its pairs
        sub = set(range(0, 480, k))
        assert {p for p in seq if sub.issuperset(p)} <= got
    odd = 101  # an odd view still has its neighbours one and two steps on and back
    assert {(100, 101), (101, 102), (99, 101), (101, 103)} <= got
    assert not any(odd in p and (p[1] - p[0]) > 2 and p[0] % 2 and p[1] % 2 for p in got)
