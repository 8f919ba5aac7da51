"""benchmarks/linearity.py: the latency model's fit, its bound and the what-ifs, on made-up runs."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.linearity import analyse, batch_chunks, fit_latency, latency_bound

FIT_RTOL = 1e-9  # an exact model, least squares in float64


def test_batch_chunks_match_the_optimisers_split():
    assert batch_chunks(1000, 3072) == 1
    assert batch_chunks(3072, 3072) == 1
    assert batch_chunks(3073, 3072) == 2
    assert batch_chunks(100_000, 3072) == 33
    assert batch_chunks(100_000, None) == 1
    assert batch_chunks(1000, 600, starts=2) == 4


def test_fit_recovers_latency_and_per_condition_cost():
    lat, per = 4.5e-3, 3.1e-6
    m = [1000, 10_000, 30_000, 100_000]
    ch = [batch_chunks(x, 3072) for x in m]
    fit = fit_latency(m, ch, [c * lat + x * per for x, c in zip(m, ch)])
    assert fit["L_s"] == pytest.approx(lat, rel=FIT_RTOL)
    assert fit["C_s"] == pytest.approx(per, rel=FIT_RTOL)
    assert max(abs(e) for e in fit["relative_residuals"]) < FIT_RTOL


def test_fit_refuses_sizes_that_cannot_separate_the_two_costs():
    with pytest.raises(ValueError, match="two or more sizes"):
        fit_latency([1000, 2000], [1, 2], [1.0, 2.0])  # chunks proportional to conditions


def test_latency_bound_is_where_the_ratio_meets_the_tolerance():
    per, small, large, tol = 3e-6, (1000, 1), (100_000, 33), 0.2
    bound = latency_bound(per, small, large, tol)

    def ratio(lat):
        return ((small[1] * lat + small[0] * per) / small[0]) / (
            (large[1] * lat + large[0] * per) / large[0]
        )

    assert ratio(bound) == pytest.approx(1 + tol, rel=1e-12)
    assert ratio(0.9 * bound) < 1 + tol < ratio(1.1 * bound)
    # A larger size with proportionally more batches is never slower per condition.
    assert latency_bound(per, (1000, 1), (10_000, 10), tol) == float("inf")


def _run(m, seconds, prepare_us, finish_us, dynamics_us, other_us):
    busy = prepare_us + finish_us
    return {
        "conditions": m,
        "seconds_per_generation": seconds,
        "machine": {"date": "2000-01-02", "device_kind": "test"},
        "trace": {
            "busy_us_per_generation": busy,
            "stages": {
                "prepare": {"busy_us_per_generation": prepare_us},
                "finish": {"busy_us_per_generation": finish_us},
            },
            "by_source": [
                {"source": "dynamics_rnea:_s_mul", "us_per_generation": dynamics_us},
                {"source": "compile_optim:_cholesky_solve", "us_per_generation": other_us},
            ],
        },
    }


def test_what_ifs_remove_a_part_at_both_sizes():
    small = _run(1000, 8e-3, 2000.0, 5000.0, 1500.0, 1000.0)  # 1 ms not busy
    large = _run(100_000, 0.46, 137_000.0, 314_000.0, 172_000.0, 42_000.0)  # 9 ms not busy
    r = analyse([large, small], 3072, 0.2)  # any order
    assert [s["conditions"] for s in r["sizes"]] == [1000, 100_000]
    assert r["ratio"] == pytest.approx((8e-3 / 1000) / (0.46 / 100_000))
    rows = {w["part"]: w for w in r["what_if"]["groups"] + r["what_if"]["functions"]}
    # The rest of the last stage: finish minus the dynamics, 3,500 and 142,000 us.
    rest = rows["last stage without the dynamics"]
    assert rest["us_small"] == pytest.approx(3.5)
    assert rest["ratio_without"] == pytest.approx(
        ((8000 - 3500) / 1000) / ((460_000 - 142_000) / 1e5)
    )
    idle = rows["device not busy"]
    assert (idle["us_small"], idle["us_large"]) == pytest.approx((1.0, 0.09))
    both = rows["last stage without the dynamics, and not busy"]
    assert both["ratio_without"] == pytest.approx(
        ((8000 - 4500) / 1000) / ((460_000 - 151_000) / 1e5)
    )
    chol = rows["`compile_optim:_cholesky_solve`"]
    assert chol["ratio_without"] == pytest.approx(7.0 / 4.18)
