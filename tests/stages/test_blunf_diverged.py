"""A plan field whose training diverges fails in one line; one that ends far below its usual
train accuracy is flagged in its facts (report.json); JSON is written strictly."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from stages.blueprint.blunf import LOW_ACCURACY, train
from stages.blueprint.config import BlunfConfig
from stages.common.errors import BlunfError
from stages.common.io import write_json


def _points() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """4000 points in [-1, 1]² of four classes split by two lines, and their 32x32 cells."""
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(4000, 2, generator=g) * 2 - 1  # [N, 2]
    y = (uv[:, 0] > 0).long() + 2 * (uv[:, 1] > 0.3).long()  # [N]
    cell = ((uv[:, 0] + 1) * 16).long() * 64 + ((uv[:, 1] + 1) * 16).long()  # [N]
    return uv, y, cell


def test_a_diverged_training_fails_in_one_line() -> None:
    uv, y, cell = _points()
    c = replace(BlunfConfig(steps=200, batch=1024), lr=1e30)
    with pytest.raises(BlunfError, match=r"blueprint.blunf: the training diverged .*lr"):
        train(c, uv, y, 4, 64, cell)


def test_a_low_train_accuracy_is_flagged() -> None:
    uv, y, cell = _points()
    _, good = train(BlunfConfig(steps=200, batch=1024), uv, y, 4, 64, cell)
    assert good["train_accuracy"] > 99 and not good["train_accuracy_low"]
    # two steps: the field has not learnt the four classes (about one point in three right)
    _, bad = train(BlunfConfig(steps=2, batch=1024), uv, y, 4, 64, cell)
    assert bad["train_accuracy"] < LOW_ACCURACY and bad["train_accuracy_low"]


def test_json_is_strict(tmp_path) -> None:
    p = tmp_path / "r.json"
    write_json(p, {"a": math.nan, "b": [np.float32(np.inf), 1.5], "c": np.array([np.nan, 2.0])})

    def refuse(name: str) -> float:
        raise AssertionError(f"{name} in strict JSON")

    assert json.loads(p.read_text(), parse_constant=refuse) == {
        "a": None,
        "b": [None, 1.5],
        "c": [None, 2.0],
    }
