"""How far a field-filled reading's weights may spread along its ray (render.ray_spread: their
standard deviation over the expected depth) before the fill drops it.

A fixed share (`depth.field.max_spread`) suits one field only: a well-trained field pins the
surfaces the photos show within a step or two and spreads its weights wide only where it
renders fog, over a plain floor or wall; a briefly trained field spreads them wide on every
ray, so the same share drops its whole fill. The field's readings that agree with stereo are
the surfaces it did learn: `depth.field.max_spread_agreeing` sets the limit to a multiple of
their median spread in this run, so each field is judged by its own converged readings.
"""

from __future__ import annotations

import numpy as np

MIN_AGREEING = 100  # fewer agreeing readings than this set no limit (too few to measure)
SAMPLE_EVERY = 2  # stereo-read blocks rendered to measure the agreement: every 2nd row, column


def at_blocks(prior: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A full-resolution map `prior` [H, W] at the centre pixel of each block of a map
    rendered at 1/k ([h, w], Intrinsics.scaled: block (r, c) covers rows r*k .. r*k+k-1)."""
    h, w = shape
    k = max(1, prior.shape[0] // h)
    rows = np.minimum(np.arange(h) * k + k // 2, prior.shape[0] - 1)
    cols = np.minimum(np.arange(w) * k + k // 2, prior.shape[1] - 1)
    return prior[rows[:, None], cols[None, :]]


def sample_blocks(need: np.ndarray) -> np.ndarray:
    """The blocks read by stereo alone (not in `need`) on every SAMPLE_EVERY-th row and
    column: where the field is rendered beside stereo to measure how it spreads there."""
    lattice = np.zeros(need.shape, bool)
    lattice[::SAMPLE_EVERY, ::SAMPLE_EVERY] = True
    return lattice & ~need


def agreeing(
    depth: np.ndarray, ok: np.ndarray, spread: np.ndarray, prior: np.ndarray, tol: float
) -> np.ndarray:
    """The spreads of one view's rendered readings (depth, ok: opacity high enough, spread:
    [h, w]) that agree with its stereo reading at the same block (`prior` [h, w], 0 = none)
    within `tol` of the stereo depth."""
    hit = ok & (prior > 0) & (np.abs(depth - prior) <= tol * prior)
    return spread[hit]


def spread_limit(agree: np.ndarray, times: float, fixed: float) -> tuple[float, dict]:
    """(the spread above which a filled reading is dropped, facts): `times` the median of the
    agreeing readings' spreads `agree` when times > 0 and there are at least MIN_AGREEING of
    them, never under `fixed` (depth.field.max_spread, 0 = none); `fixed` alone otherwise;
    inf when neither sets one."""
    n = int(len(agree))
    med = float(np.median(agree)) if n else None
    facts: dict = {
        "agreeing_readings": n,
        "agreeing_median": None if med is None else round(med, 4),
        "fixed": fixed,
        "times": times,
    }
    limit = fixed if fixed > 0 else float("inf")
    if times > 0 and med is not None and n >= MIN_AGREEING:
        limit = max(limit, times * med) if fixed > 0 else times * med
        facts["rule"] = f"{times:g} x the median spread of {n} readings agreeing with stereo"
    elif times > 0:
        facts["rule"] = f"too few readings agree with stereo ({n} < {MIN_AGREEING}): " + (
            f"the fixed {fixed:g}" if fixed > 0 else "no limit"
        )
    else:
        facts["rule"] = f"fixed {fixed:g}" if fixed > 0 else "no limit"
    facts["limit"] = round(limit, 4) if np.isfinite(limit) else None
    return limit, facts
