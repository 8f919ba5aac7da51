"""benchmarks/train_loop.py: a training loop's own cost from its metrics rows (made up here)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.train_loop import loop_times


def test_loop_times_average_the_checkpointed_generations_in():
    # Steps of 10 ms; a 30 ms checkpoint after generations 3 and 6 (every 3rd), 1 ms otherwise.
    rows, t = [], 100.0
    for g in range(1, 7):
        t += 0.010 + (0.030 if g % 3 == 0 else 0.001)
        rows.append({"generation": g, "seconds": 0.010, "finished_at": t})
    got = loop_times(rows)
    # Intervals 2..6 end with generations 2..6: (11 + 40 + 11 + 11 + 40) / 5 = 22.6 ms.
    assert got["wall_s"] == pytest.approx(0.0226)
    assert got["generations_per_s"] == pytest.approx(1 / 0.0226)


def test_loop_times_need_two_generations():
    with pytest.raises(ValueError, match="two or more"):
        loop_times([{"finished_at": 1.0}])
