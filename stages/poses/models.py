"""What SfM made of the photos: which photos each model holds, which it left out, and the
warnings a reader of the report needs (photos of two places, or many photos dropped).

SfM keeps only its largest model; when the photos fall into several models (two rooms, or
one room photographed in two parts that do not overlap) the others are silently lost, and
with `poses.min_registered_frac` lowered the run goes on with half the capture.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

SPLIT_MIN_IMAGES = 3  # a second model holding at least this many photos is warned about
DROPPED_WARN_FRAC = 0.2  # warn when more than this fraction of the photos is left out
MAX_SPANS = 20  # frame spans listed per group (the report stays small); the rest counted


def spans(indices: list[int], stems: list[str]) -> list[str]:
    """Runs of consecutive capture indices as "first..last (n)" (a lone frame by its stem),
    at most MAX_SPANS of them, then "+ k more frames"."""
    out: list[str] = []
    idx = sorted(indices)
    i = 0
    while i < len(idx):
        j = i
        while j + 1 < len(idx) and idx[j + 1] == idx[j] + 1:
            j += 1
        a, b = stems[idx[i]], stems[idx[j]]
        out.append(a if i == j else f"{a}..{b} ({j - i + 1})")
        i = j + 1
    if len(out) > MAX_SPANS:
        rest = sum(_count(s) for s in out[MAX_SPANS:])
        out = [*out[:MAX_SPANS], f"+ {rest} more frames"]
    return out


def _count(span: str) -> int:
    return int(span.rsplit("(", 1)[1].rstrip(")")) if span.endswith(")") else 1


def describe(models: list[list[int]], stems: list[str]) -> dict:
    """Facts for sfm.json about the models SfM made.

    Args:
        models: per model, the capture indices of the photos it registered; the first is
            the model kept (the largest).
        stems: the capture's frame stems, in capture order.
    Returns:
        {"groups": [{"frames": n, "spans": [...], "kept": bool}, ...],
         "left_out": spans of the photos in no kept model, "warnings": [one line, ...]}
    """
    n = len(stems)
    groups = [
        {"frames": len(m), "spans": spans(m, stems), "kept": k == 0} for k, m in enumerate(models)
    ]
    kept = set(models[0]) if models else set()
    left = [i for i in range(n) if i not in kept]
    in_other = sorted({i for m in models[1:] for i in m} - kept)
    warnings = []
    big = [m for m in models if len(m) >= SPLIT_MIN_IMAGES]
    if len(big) > 1:
        parts = "; ".join(", ".join(spans(m, stems)) for m in big)
        warnings.append(
            f"SfM made {len(big)} models it could not join ({parts}): the photos may show "
            f"different places, or parts that no photo links; only the largest "
            f"({len(models[0])} photos) is used"
        )
    if n and len(left) > DROPPED_WARN_FRAC * n:
        warnings.append(
            f"{len(left)} of {n} photos ({100 * len(left) / n:.0f} %) are left out of the "
            f"model ({len(in_other)} in other models, {len(left) - len(in_other)} in none): "
            f"{', '.join(spans(left, stems))}"
        )
    for w in warnings:
        log.warning("sfm: %s", w)
    return {"groups": groups, "left_out": spans(left, stems), "warnings": warnings}
