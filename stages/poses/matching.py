"""Which image pairs SIFT matches are sought between, and the matching (pycolmap).

- exhaustive: every pair, n (n - 1) / 2.
- sequential: each image with those 1, 2, 4 ... 2^(overlap - 1) steps on in capture order
  (pycolmap 4's sequential pairing with quadratic overlap): a walk that comes back to where
  it started is not closed unless it is a power of two long.
- retrieval: the sequential pairs, plus each image with its `neighbours` most similar images
  outside its window (the loop pairs). Similarity is the dot product of VLAD vectors
  (Jégou et al., CVPR 2010): RootSIFT descriptors, their residuals to visual words summed per
  word, normalised per word, square-rooted and normalised. The words are a seeded k-means of
  the capture's own descriptors, so no vocabulary is downloaded. The pairs grow as
  n (min(overlap, log2 n) + neighbours), not n^2. Every dot product it takes is exact
  (`snap`), so the words and pairs do not depend on how many threads BLAS sums with.

The sequential pairs are pycolmap's own sequential pairing; the loop pairs then go to its
`match_image_pairs` as a list. Two-view geometry is verified by pycolmap as for any pairing.

A capture long enough that SfM maps one view in two first (`poses.keyframes`, sfm.py) and
registers the rest to that model with its poses held leaves out the sequential pairs
between two of those other views more than two steps apart (`keyframe_pairs`): no mapping
reads them, and each of those views is registered through its neighbours one and two steps
on. The sequential pairs then go to `match_image_pairs` as a list too.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np  # noqa: I001  (numpy must be loaded before pycolmap, see stages/__init__.py)
import pycolmap

from stages.poses.config import MatchingConfig, PosesConfig, RetrievalConfig

log = logging.getLogger(__name__)

MIN_INLIERS = 15  # a pair with this many verified matches counts as matched (COLMAP's own)
CHUNK = 4096  # descriptors assigned to words at a time (bounds the distance matrix)
GRID = 2.0**-20  # retrieval's vectors are multiples of this (snap)


def kind_for(cfg: MatchingConfig, n: int) -> str:
    """The kind of matching used for n images ("auto" resolved)."""
    if cfg.kind != "auto":
        return cfg.kind
    if n <= cfg.exhaustive_max_images:
        return "exhaustive"
    return "sequential" if n <= cfg.retrieval_above else "retrieval"


def sequential_pairs(n: int, overlap: int) -> set[tuple[int, int]]:
    """(i, j), i < j: j - i a power of two below 2^overlap (pycolmap 4's sequential pairing
    with quadratic overlap, which this module runs; tests/stages/test_sfm_matching.py holds
    them equal)."""
    steps = {2**k for k in range(overlap)}
    return {(i, i + d) for i in range(n) for d in steps if i + d < n}


def keyframe_stride(n: int, at_least: int) -> int:
    """The largest power of two k with n >= k * at_least: one view in k leaves at least
    `at_least` of n (1: map every view; also when at_least is 0)."""
    k = 1
    while at_least > 0 and n >= 2 * k * at_least:
        k *= 2
    return k


def keyframe_pairs(n: int, overlap: int) -> set[tuple[int, int]]:
    """The sequential pairs of n images but those between two odd-numbered images (the
    views that mapping one in two, or fewer, leaves to be registered) more than two steps
    apart. Every subset mapped first (every 2nd, 4th ... view: even-numbered) keeps all its
    pairs; an odd view keeps its pairs with the views one and two steps on and back.
    Mapping every view (the keyframes' fallback) then has those pairs alone for the odd
    views, which join the rest through their neighbours. At 480 views, overlap 10: 3809
    sequential pairs -> 2383."""
    return {(i, j) for i, j in sequential_pairs(n, overlap) if i % 2 == 0 or j - i <= 2}


def snap(x: np.ndarray) -> np.ndarray:
    """x rounded to a multiple of GRID (2^-20), float64.

    Why: a matmul's sums run in an order set by BLAS's kernel and thread count (OpenBLAS
    takes OMP_NUM_THREADS / OPENBLAS_NUM_THREADS, else the machine's cores, when numpy
    loads), so float32 distances differed in their last bits between one and two threads,
    nearest words flipped and the retrieved pairs with them (70 views: words up to 3e-3
    apart, 270 against 273 loop pairs, another model). Between rows of norm <= 1 on this grid
    each product is a multiple of 2^-40 and every partial sum is at most 1 (Cauchy-Schwarz):
    53 bits hold it exactly, so float64 gives the same bits in any order, FMA or not. A
    multiple of 2^-20 in [-1, 1] is also exact in float32 (24 bits), which stores it."""
    return np.rint(np.asarray(x, np.float64) / GRID) * GRID


def root_sift(d: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelović & Zisserman 2012): L1-normalise, square-root; rows of unit
    length on the GRID (snap), stored as float32 (exact)."""
    x = d.astype(np.float64)
    x /= np.maximum(x.sum(1, keepdims=True), 1e-12)
    return snap(np.sqrt(x)).astype(np.float32)


def assign(x: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Index of the nearest word of each row of x, CHUNK rows at a time; x and words on the
    GRID with rows of norm <= 1 (snap), so the distances are exact (ties: the first word)."""
    w = words.astype(np.float64)
    ww = (w**2).sum(1)
    out = np.empty(len(x), np.int64)
    for s in range(0, len(x), CHUNK):
        c = np.asarray(x[s : s + CHUNK], np.float64)
        out[s : s + CHUNK] = np.argmin(ww[None] - 2.0 * c @ w.T, axis=1)
    return out


def train_words(descs: list[np.ndarray], cfg: RetrievalConfig, seed: int) -> np.ndarray:
    """Visual words [k, 128] on the GRID: Lloyd's k-means of at most cfg.sample RootSIFT
    descriptors (root_sift), spread evenly over the images, from k distinct seeded rows, each
    mean snapped; an emptied word keeps its place."""
    rng = np.random.default_rng(seed)
    per = max(1, cfg.sample // max(1, len(descs)))
    parts = [d[rng.choice(len(d), min(per, len(d)), replace=False)] for d in descs if len(d)]
    x = np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 128))
    k = min(cfg.words, len(x))
    if k == 0:
        return np.zeros((0, 128), np.float64)
    words = x[rng.choice(len(x), k, replace=False)]
    for _ in range(cfg.iterations):
        a = assign(x, words)
        sums = np.zeros_like(words)
        np.add.at(sums, a, x)  # multiples of GRID: exact (float64 both: numpy's fast path)
        counts = np.bincount(a, minlength=k)
        filled = counts > 0
        words[filled] = snap(sums[filled] / counts[filled, None])
    return words


def vlad(d: np.ndarray, words: np.ndarray) -> np.ndarray:
    """The image's VLAD vector [k * 128], unit length, on the GRID (zeros for an image with
    no features). Norms are numpy's own sums, not BLAS's dot, whose order may follow its
    threads."""
    r = np.zeros((len(words), 128), np.float64)  # [k, 128] residuals summed per word
    if len(d) and len(words):
        a = assign(d, words)
        np.add.at(r, a, d.astype(np.float64) - words[a])  # multiples of GRID: exact
        r /= np.maximum(np.sqrt((r**2).sum(1, keepdims=True)), 1e-12)  # per word
    v = np.sign(r.ravel()) * np.sqrt(np.abs(r.ravel()))
    return snap(v / max(float(np.sqrt((v**2).sum())), 1e-12))


def loop_pairs(vecs: np.ndarray, window: set[tuple[int, int]], neighbours: int) -> set:
    """Each image with its `neighbours` most similar images (dot product of vecs [n, D], rows
    of norm <= 1, snapped to the GRID: exact) among those it is not already paired with in
    `window`; (i, j), i < j."""
    n = len(vecs)
    v = snap(vecs)
    sim = v @ v.T
    np.fill_diagonal(sim, -np.inf)
    for i, j in window:
        sim[i, j] = sim[j, i] = -np.inf
    out = set()
    for i in range(n):
        row = sim[i]
        k = min(neighbours, int(np.isfinite(row).sum()))
        if k <= 0:
            continue
        for j in np.argpartition(-row, k - 1)[:k]:
            out.add((min(i, int(j)), max(i, int(j))))
    return out


def read_descriptors(db: Path, names: list[str]) -> list[np.ndarray]:
    """Each image's SIFT descriptors [N, 128] (uint8) from the database, in `names` order."""
    d = pycolmap.Database.open(db)
    try:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        return [np.asarray(d.read_descriptors(ids[nm]).data) for nm in names]
    finally:
        d.close()


def retrieval_pairs(
    db: Path, names: list[str], cfg: MatchingConfig, seed: int
) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
    """(sequential pairs, loop pairs) of the images `names` (indices into it): the loop
    pairs are the most similar outside the sequential pairs and the next `overlap` views."""
    seq = sequential_pairs(len(names), cfg.overlap)
    n = len(names)  # the loop pairs look beyond the next `overlap` views too
    near = {(i, j) for i in range(n) for j in range(i + 1, min(n, i + cfg.overlap + 1))}
    descs = [root_sift(d) for d in read_descriptors(db, names)]
    words = train_words(descs, cfg.retrieval, seed)
    vecs = np.stack([vlad(d, words) for d in descs]) if descs else np.zeros((0, 1))
    return seq, loop_pairs(vecs, seq | near, cfg.retrieval.neighbours)


def _match_list(
    db: Path,
    names: list[str],
    pairs: set[tuple[int, int]],
    mo: pycolmap.FeatureMatchingOptions,
    vo: pycolmap.TwoViewGeometryOptions,
    file: str,
) -> None:
    """Match and verify the pairs (indices into names), given to pycolmap as a list file
    beside the database."""
    lst = Path(db).parent / file
    lst.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in sorted(pairs)))
    ip = pycolmap.ImportedPairingOptions()
    ip.match_list_path = str(lst)
    pycolmap.match_image_pairs(
        db,
        matching_options=mo,
        pairing_options=ip,
        verification_options=vo,
        device=pycolmap.Device.cpu,
    )


def verified(db: Path, names: list[str]) -> dict[tuple[int, int], int]:
    """(i, j) -> verified matches, i < j indices into `names`, of the pairs with MIN_INLIERS."""
    d = pycolmap.Database.open(db)
    try:
        at = {name: i for i, name in enumerate(names)}
        index = {im.image_id: at[im.name] for im in d.read_all_images()}
        pair_ids, inliers = d.read_two_view_geometry_num_inliers()
    finally:
        d.close()
    out = {}
    for pid, k in zip(pair_ids, inliers, strict=True):
        if k >= MIN_INLIERS:
            a, b = (index[x] for x in pycolmap.pair_id_to_image_pair(pid))
            out[(min(a, b), max(a, b))] = int(k)
    return out


def closure(good: dict[tuple[int, int], int], loops: set[tuple[int, int]], n: int) -> dict:
    """Facts of the matched pairs: how many, the longest gap in capture order among them
    (a walk that returns to its start: about n), and the loop pairs among them."""
    facts = {
        "verified_pairs": len(good),
        "longest_gap": max((j - i for i, j in good), default=0),
        "images": n,
    }
    if loops:
        facts["loop_pairs_verified"] = sum(p in good for p in loops)
    return facts


def match(cfg: PosesConfig, db: Path, names: list[str], threads: int) -> dict:
    """Match SIFT features between the chosen pairs. Returns the facts: kind, detail, pairs
    tried, loop_pairs (retrieval), and closure()'s."""
    n = len(names)
    # deterministic: one thread, as extraction and mapping (two threads verify the pairs in a
    # varying order, and the same photos gave two models: 14 059 against 14 076 points)
    threads = 1 if cfg.deterministic else threads
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = threads
    mo.use_gpu = False
    vo = pycolmap.TwoViewGeometryOptions()
    if cfg.deterministic:  # each pair's RANSAC from the seed, whichever thread runs it
        vo.ransac.random_seed = cfg.seed
    m = cfg.matching
    kind = kind_for(m, n)
    log.info("sfm: %s matching", kind)
    facts: dict = {"kind": kind, "exhaustive_pairs": n * (n - 1) // 2}
    if kind == "exhaustive":
        pycolmap.match_exhaustive(
            db, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu
        )
        facts |= {"detail": f"all {n * (n - 1) // 2} pairs", "pairs": n * (n - 1) // 2}
        return facts | closure(verified(db, names), set(), n)
    loops: set[tuple[int, int]] = set()
    steps = f"steps 1, 2, 4 ... 2^{m.overlap - 1} (quadratic overlap)"
    kf = cfg.keyframes
    if kf.skip_pairs and cfg.mapper != "global" and keyframe_stride(n, kf.at_least) > 1:
        # the incremental mapper maps one view in two (or fewer) first: the pairs between
        # the other views but the nearest are left out (keyframe_pairs)
        pairs = keyframe_pairs(n, m.overlap)
        _match_list(db, names, pairs, mo, vo, "keyframe-pairs.txt")
        facts["pairs_left_out"] = len(sequential_pairs(n, m.overlap) - pairs)
        steps += " but between two views registered to the keyframes' model more than 2 apart"
    else:
        # the sequential pairs by pycolmap's own pairing (as before retrieval existed: the
        # same database, the same model), then the loop pairs from a list
        po = pycolmap.SequentialPairingOptions()
        po.overlap = m.overlap
        po.quadratic_overlap = True
        po.loop_detection = False
        po.num_threads = threads
        pycolmap.match_sequential(
            db,
            matching_options=mo,
            pairing_options=po,
            verification_options=vo,
            device=pycolmap.Device.cpu,
        )
    detail = f"{steps}, no loop detection"
    if kind == "retrieval":
        loops = retrieval_pairs(db, names, m, cfg.seed)[1]
        r = m.retrieval
        detail = (
            f"{steps} and {r.neighbours} retrieved a view (VLAD over {r.words} words of the "
            "capture's own SIFT)"
        )
        facts["loop_pairs"] = len(loops)
        _match_list(db, names, loops, mo, vo, "pairs.txt")
    d = pycolmap.Database.open(db)
    try:
        facts["pairs"] = int(d.num_matched_image_pairs())
    finally:
        d.close()
    facts["detail"] = detail
    return facts | closure(verified(db, names), loops, n)
