"""benchmarks/catch_success.py on a tiny run: the thrower model against the ballistic closed
form and its ranges, the counts' bookkeeping, and the result files through make_report."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import catch_success  # noqa: E402

TINY = ROOT / "configs" / "tiny.yaml"
GRAVITY = np.array([0.0, 0.0, -9.81])
TOL_AIM_M = 1e-5  # the closed-form flight reaches the aim point (float32 release velocity)
THROWS = 3


def test_throws_reach_their_aim_within_the_thrower_model():
    conditions = np.array([[0.4, -0.2, 0.9], [0.3, 0.1, 1.1], [0.5, 0.0, 1.0]])
    p0, v0, aim, flight = catch_success.sample_throws(conditions, GRAVITY, 200, jax.random.key(3))
    t = flight[:, None]
    at = p0.astype(np.float64) + v0 * t + 0.5 * GRAVITY * t**2
    np.testing.assert_allclose(at, aim, atol=TOL_AIM_M * 10 * np.abs(v0).max())
    m = catch_success.THROWER
    dist = np.hypot(p0[:, 0], p0[:, 1])
    assert np.all((dist >= m["distance_m"][0] - 1e-5) & (dist <= m["distance_m"][1] + 1e-5))
    assert np.all((p0[:, 2] >= 1.0 - 1e-6) & (p0[:, 2] <= 2.0 + 1e-6))
    assert np.all((flight >= 0.5) & (flight <= 1.2))
    near = np.min(np.abs(aim[:, None, :] - conditions[None]).max(axis=2), axis=1)
    assert np.all(near <= catch_success.AIM_JITTER + 1e-9)
    again = catch_success.sample_throws(conditions, GRAVITY, 200, jax.random.key(3))
    np.testing.assert_array_equal(again[0], p0)  # explicit key: the same throws


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    from evojax_motion.online.generation import load_online_model
    from evojax_motion.run.training import run_training
    from evojax_motion.settings import load_config

    cfg = load_config(TINY)
    out = tmp_path_factory.mktemp("tiny") / "run"
    run_training(cfg, out, progress=False)
    model = load_online_model(out)
    return catch_success.run(model, cfg, str(out), THROWS, 0, 2)


@pytest.mark.slow
def test_counts_add_up_and_the_report_renders(tiny_result, tmp_path):
    import make_report

    for name, d in tiny_result["databases"].items():
        assert d["throws"] == THROWS
        assert d["reachable"] + d["unreachable"] == THROWS, name
        assert d["planned"] + d["infeasible_plans"] == d["reachable"], name
        assert 0 <= d["caught"] <= d["planned"], name
        assert d["success_rate"] == pytest.approx(d["caught"] / max(d["reachable"], 1))
        if d["planned"]:
            assert d["cost"]["median"] > 0
            assert 0.0 <= d["at_torque_limit"] <= 1.0
    assert (
        tiny_result["databases"]["human-only"]["entries"]
        < (tiny_result["databases"]["learned"]["entries"])
    )
    result = {**tiny_result, "machine": catch_success.machine_info()}
    catch_success.write_result(
        tmp_path / "catch_success_test", result, catch_success.markdown(result)
    )
    page = make_report.render(tmp_path)
    assert "Catch success in physics" in page
    assert "`catch_success_test.json`" in page


@pytest.mark.slow
def test_the_run_report_reads_the_result_beside_the_run(tiny_result, tmp_path):
    """The result file beside a run (`report.run_folder.CATCH_FILE`) is read back as written and
    drawn; one that is not such a result is a named problem of the run folder."""
    import json

    from evojax_motion.report.figures import plot_catch_success
    from evojax_motion.report.run_folder import CATCH_FILE, load_run

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(TINY.read_text())
    (run / CATCH_FILE).write_text(json.dumps(tiny_result))
    data = load_run(run)
    for name, d in tiny_result["databases"].items():
        assert data.catch["databases"][name]["caught"] == d["caught"]
    assert CATCH_FILE not in data.problems
    png = plot_catch_success(data.catch, tmp_path / "catch.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    (run / CATCH_FILE).write_text(json.dumps({"databases": {"learned": {"caught": 1}}}))
    bad = load_run(run)
    assert bad.catch is None and "benchmarks/catch_success.py" in bad.problems[CATCH_FILE]
