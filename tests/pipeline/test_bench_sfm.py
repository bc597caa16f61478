"""pipeline.bench.sfm: plain pycolmap and the poses stage on the same photos, one table."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.bench.sfm import compare, main, table
from stages.synth import make_room


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """24 views of 192x144 (15 degrees apart on a loop): both SfM runs register it."""
    return make_room(tmp_path_factory.mktemp("sfm") / "cap", views=24, seed=0, size=(192, 144))


def test_compare_gives_both_rows_and_their_ratios(room: Path) -> None:
    res = compare(room, 0, 1, 1, ["poses.max_features=2048"], config=None)
    assert res["total"] == 24
    for who in ("ours", "ref"):
        assert res[f"{who}_registered"] >= 20, res
        assert 0 < res[f"{who}_cpu_s"] and 0 < res[f"{who}_s"]
        assert res[f"{who}_ate_m"] < 0.05  # exact renders of a textured room: millimetres
        assert len(res["runs"][who]) == 1
    assert res["ratio_s"] == pytest.approx(res["ours_s"] / res["ref_s"])
    assert res["ratio_ate"] == pytest.approx(res["ours_ate_m"] / res["ref_ate_m"])
    assert 0.05 < res["ratio_cpu"] < 20
    rows = table(res).splitlines()
    assert rows[2].startswith("| pycolmap") and rows[3].startswith("| poses stage")
    assert rows[4].startswith("| ratio") and f"{res['ratio_s']:.2f}x" in rows[4]


def test_bad_arguments_exit_with_one_line(room: Path, capsys) -> None:
    assert main([str(room), "--repeats", "0"]) == 2
    assert "repeats" in capsys.readouterr().err
    assert main([str(room), "--set", "poses.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
