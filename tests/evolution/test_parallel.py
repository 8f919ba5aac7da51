"""The sharded generation step (parallel.py): padding, statistics, the same database as one
device on 4 forced CPU devices, and the same again from 2 processes of 2 devices (multi-host).

XLA fixes the CPU device count when JAX starts, so the multi-device runs execute this file as a
script in subprocesses with ``--xla_force_host_platform_device_count`` (`_child_single`,
`_child_multihost`) and the tests check the JSON they print. They run in float64: XLA's
reductions are not batch-size invariant, so the per-device batches (2 conditions) may round
differently from the one-device batch (5) in the last bit, and in float32 a short Adam run can
amplify that to 0.01-0.1 rad (docs/scaling.md); in float64 the same effect stays far below the
tolerances below, which still catch any padding or slot-layout mistake (those change results by
whole neighbours).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

N_DEVICES = 4  # forced CPU devices of the subprocess
N_HUMAN, T_SAMPLES, M_COND = 30, 16, 5  # m = 5 on 4 devices: 3 padded, one device all padding
TOL_Q_F64 = 1e-9  # [rad] sharded vs one-device survivors, float64
TOL_COST_REL_F64 = 1e-9  # relative, eq. 5 cost of the survivors and the mean statistics, float64
COLLECTIVES = ("all-gather", "all-reduce", "all-to-all", "collective-permute", "reduce-scatter")


# ------------------------------------------------------------------ settings, padding, stats


@pytest.mark.parametrize("value", [0, -2, True, 1.5, "all"])
def test_settings_reject_bad_devices(value):
    from evojax_motion.settings.evolution import ParallelSettings

    with pytest.raises(ValueError, match=r"^devices: expected"):
        ParallelSettings(devices=value)


def test_settings_defaults_and_device_resolution():
    import jax

    from evojax_motion.errors import UserError
    from evojax_motion.evolution.sharding import resolve_devices
    from evojax_motion.settings.evolution import ParallelSettings

    assert ParallelSettings().devices is None and ParallelSettings(devices=8).devices == 8
    assert resolve_devices(None) == jax.devices()
    assert resolve_devices(1) == jax.devices()[:1]
    with pytest.raises(UserError, match=r"^parallel\.devices: expected 1 to"):
        resolve_devices(jax.device_count() + 1)


@pytest.mark.parametrize("m, multiple, expected", [(5, 4, 8), (8, 4, 8), (1, 3, 3), (7, 1, 7)])
def test_padded_count(m, multiple, expected):
    from evojax_motion.evolution.sharding import padded_count

    assert padded_count(m, multiple) == expected


def _conditions(m, t=4, j=3, seed=0):
    from evojax_motion.compiler.interpolation import Boundary
    from evojax_motion.evolution.conditions import Conditions

    rng = np.random.default_rng(seed)

    def r(*shape):
        return rng.normal(size=shape).astype(np.float32)

    return Conditions(
        target=r(m, 3),
        boundary=Boundary(q0=r(m, j), qf=r(m, j), qd0=r(m, j), qdf=r(m, j), duration=r(m)),
        ik_error=r(m),
        n_human_inside=np.arange(m, dtype=np.int32),
        human_q=r(m, t, j),
    )


def test_pad_conditions_copies_the_last_and_marks_it():
    import jax

    from evojax_motion.evolution.sharding import is_padding, pad_conditions

    cond = _conditions(5)
    padded, n_real = pad_conditions(cond, 4)
    assert n_real == 5
    for name, a, b in zip(
        cond._fields, jax.tree_util.tree_leaves(cond), jax.tree_util.tree_leaves(padded)
    ):
        b = np.asarray(b)
        assert b.shape == (8, *a.shape[1:]), name
        assert b[:5].tobytes() == a.tobytes(), name  # the real conditions, bit for bit
    np.testing.assert_array_equal(np.asarray(is_padding(padded)), [False] * 5 + [True] * 3)
    assert np.isnan(np.asarray(padded.target)[5:]).all()
    np.testing.assert_array_equal(
        np.asarray(padded.boundary.qf)[5:], np.repeat(cond.boundary.qf[-1:], 3, 0)
    )
    same, n = pad_conditions(cond, 5)  # already a multiple: untouched
    assert same is cond and n == 5


def test_padded_slots_are_never_neighbours():
    """The padded slots are empty and have a NaN condition: even with fewer valid entries than k,
    the neighbour search never selects or counts them."""
    from evojax_motion.compiler.basis import select_neighbours
    from evojax_motion.evolution.sharding import pad_database
    from evojax_motion.motion.database import make_database

    rng = np.random.default_rng(1)
    db = make_database(rng.normal(size=(3, 4, 2)), np.ones(3), rng.normal(size=(3, 3)) * 0.01)
    db = db._replace(valid=np.array([True, True, False]))
    grown = pad_database(db, 3)
    for a, b in zip(db, grown):
        assert np.asarray(b)[:3].tobytes() == np.asarray(a).tobytes()
    assert not np.asarray(grown.valid)[3:].any() and np.isinf(np.asarray(grown.cost)[3:]).all()
    assert np.isnan(np.asarray(grown.condition)[3:]).all()
    assert (np.asarray(grown.generation)[3:] == 0).all()

    # the padded copies of a *valid* last row, with the padding's validity forced on, would be
    # candidates; with the NaN condition they are not even then
    forced = grown._replace(valid=np.ones(6, bool))
    nb = select_neighbours(forced.condition, forced.valid, np.zeros((2, 3), np.float32), 5, 1.0)
    mask, index = np.asarray(nb.mask), np.asarray(nb.index)
    assert mask.sum(axis=1).tolist() == [3, 3] and (index[mask] < 3).all()
    assert np.asarray(nb.n_inside).tolist() == [3, 3]


def _stats(**values):
    from evojax_motion.evolution.stats import GenerationStats

    base = dict.fromkeys(GenerationStats._fields, np.float32(1.5))
    base.update(values)
    return GenerationStats(**{k: np.asarray(v) for k, v in base.items()})


def test_unpad_stats_removes_exactly_the_padding():
    from evojax_motion.evolution.sharding import unpad_stats

    stats = _stats(
        n_rejected_nonfinite=np.int32(4),
        n_short=np.int32(5),
        n_valid=np.int32(3),
        converged_fraction=np.float32(2 / 8),
    )
    out = unpad_stats(stats, 5, 3)
    assert int(out.n_rejected_nonfinite) == 1 and int(out.n_short) == 2
    assert float(out.converged_fraction) == np.float32(2 / 5)
    for name in ("n_valid", "db_cost_mean", "offspring_cost_mean", "bc_residual_max"):
        assert float(getattr(out, name)) == float(getattr(stats, name)), name
    assert unpad_stats(stats, 8, 0) is stats


def test_combine_stats_weights_by_offspring_past_every_rejection():
    """Two devices' statistics (a mapped axis named like the mesh's): counts add up, and the
    mean over accepted offspring weighs each device by ``n_local`` less all its rejections
    (torque and velocity ones included)."""
    import jax

    from evojax_motion.evolution.sharding import CONDITION_AXIS, combine_stats
    from evojax_motion.evolution.stats import GenerationStats

    n_local = 10
    a = _stats(n_rejected_torque=np.int32(3), n_rejected_velocity=np.int32(2),
               offspring_cost_mean=np.float32(1.0))  # fmt: skip
    b = _stats(n_rejected_torque=np.int32(0), n_rejected_velocity=np.int32(0),
               offspring_cost_mean=np.float32(4.0))  # fmt: skip
    both = GenerationStats(*(np.stack([x, y]) for x, y in zip(a, b)))
    out = jax.vmap(lambda s: combine_stats(s, n_local), axis_name=CONDITION_AXIS)(both)
    assert int(out.n_rejected_torque[0]) == 3 and int(out.n_rejected_velocity[0]) == 2
    other = sum(float(getattr(a, f)) for f in ("n_rejected_nonfinite", "n_rejected_limits",
                                                "n_rejected_bc"))  # fmt: skip
    acc_a, acc_b = n_local - other - 5, n_local - other
    expected = (1.0 * acc_a + 4.0 * acc_b) / (acc_a + acc_b)
    np.testing.assert_allclose(float(out.offspring_cost_mean[0]), expected, rtol=1e-6)


# ------------------------------------------ sharded vs one device, 4 forced CPU devices


def _last_json(res) -> dict:
    assert res.returncode == 0, res.stderr[-4000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def sharded_run():
    from multiprocess_support import cpu_devices_env  # (not in the subprocess: no tests/ there)

    cmd = [sys.executable, __file__, "single"]
    env = cpu_devices_env(N_DEVICES, x64=True)
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    return _last_json(res)


@pytest.mark.slow
def test_sharded_generations_match_one_device(sharded_run):
    """Generations 1 (empty slots) and 2 (survivors among the neighbours, padded slots beside
    them), each from the same input database on 1 and on 4 devices."""
    out = sharded_run
    assert out["devices"] == N_DEVICES and out["m_pad"] == 8
    assert out["bfgs_lowers"] == [True, True]  # CPU fast path under the sharded wrappers
    for gen in out["generations"]:
        g = gen["generation"]
        assert gen["human_rows_bitwise"], g
        assert gen["untouched_fields_bitwise"], g  # duration, condition, origin of every slot
        assert gen["valid_equal"] and gen["generation_equal"], g
        assert gen["q_max_abs_diff"] <= TOL_Q_F64, g
        assert gen["cost_max_rel_diff"] <= TOL_COST_REL_F64, g
        for name, (ref, got) in gen["stats"].items():
            if isinstance(ref, int):
                assert got == ref, (g, name)  # counts: exact, padding removed
            elif ref is None:
                assert got is None, (g, name)  # NaN mean (nothing to average) on both
            else:
                assert abs(got - ref) <= TOL_COST_REL_F64 * max(1.0, abs(ref)), (g, name)
    first = out["generations"][0]
    # condition 0 ends beyond a joint limit, condition 1 has a NaN final posture: the real
    # rejections are counted, the 3 padded conditions are not
    assert first["stats"]["n_rejected_limits"][0] == 1
    assert first["stats"]["n_rejected_nonfinite"] == [1, 1]
    assert first["stats"]["n_valid"][0] == M_COND - 2


@pytest.mark.slow
def test_sharded_program_gathers_only_the_new_slots(sharded_run):
    """The compiled program's collectives: all-gathers of the m_pad new slots and all-reduces of
    scalar statistics; no resharding (all-to-all, collective-permute), and in particular no
    all-gather of the (m, N) distance matrix (what automatic partitioning does for top_k)."""
    hlo = sharded_run["collectives"]
    assert hlo["all-to-all"] == [] and hlo["collective-permute"] == [], hlo
    assert hlo["all-gather"], hlo
    for shape in hlo["all-gather"]:
        assert shape[0] == sharded_run["m_pad"] or shape == [], hlo
    for shape in hlo["all-reduce"]:
        assert shape == [], hlo


@pytest.mark.slow
def test_inputs_kept_on_the_devices_give_the_same_database(sharded_run):
    """Database and conditions put on the devices once (`replicate`, as `train` does) and each
    generation's database fed to the next as the step returned it: the chained databases of
    numpy inputs, bit for bit, on one device and on 4."""
    assert sharded_run["resident_digests"] == {
        "1": sharded_run["one_device_digests"],
        "4": sharded_run["sharded_digests"],
    }


@pytest.mark.slow
def test_two_processes_give_the_same_database(sharded_run):
    """Multi-host path: 2 processes x 2 CPU devices joined by `initialize_distributed` (gloo
    collectives, localhost) take process 0's inputs (`same_on_every_process`; process 1 starts
    from a perturbed copy), put them on the devices once (`replicate`) and run the same 4-way
    sharded step on them, each generation's database fed back as returned; both read back the
    database of the single-process 4-device run from numpy inputs, bit for bit."""
    from multiprocess_support import process_envs

    procs = [
        subprocess.Popen(
            [sys.executable, __file__, "multihost"],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for env in process_envs(2, N_DEVICES // 2, x64=True)
    ]
    outs = []
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=600)
        outs.append(
            _last_json(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr))
        )
    assert [o["process"] for o in outs] == [{"index": i, "count": 2, "devices": 4} for i in (0, 1)]
    for o in outs:
        assert o["digests"] == sharded_run["sharded_digests"]


# ----------------------------------------------------------------------- subprocess body


def _problem():
    """The tiny float64 problem of the subprocess runs: ``(step args, db0, conditions)``."""
    import jax
    import jax.numpy as jnp

    from evojax_motion.compiler.interpolation import Boundary
    from evojax_motion.evolution.conditions import Conditions
    from evojax_motion.evolution.step import init_evolved_slots
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import load_robot
    from evojax_motion.motion.database import Database, make_database
    from evojax_motion.motion.objective import torque_cost
    from evojax_motion.motion.timegrid import make_time_grid
    from evojax_motion.settings.compiler import BasisSettings, OptimSettings
    from evojax_motion.settings.evolution import EvolutionSettings

    assert jax.config.read("jax_enable_x64")
    f64 = np.float64
    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot, "rnea", dtype=f64)
    grid = make_time_grid(T_SAMPLES)
    # synthetic humans: rest-to-rest minimum-jerk reaches to noisy comfortable postures
    rng = np.random.default_rng(0)
    lo, hi, j = robot.lower, robot.upper, robot.n_joints
    comfort = np.clip(robot.rest + np.radians([0, 45, 10, 10, 60, 0, 0]), lo + 0.1, hi - 0.1)
    qf = np.clip(comfort + rng.normal(0, 0.2, (N_HUMAN, j)), lo + 0.05, hi - 0.05)
    s = np.asarray(grid.s, f64)
    mj = 10 * s**3 - 15 * s**4 + 6 * s**5
    q = robot.rest + (qf - robot.rest)[:, None, :] * mj[None, :, None]
    dur = rng.uniform(0.6, 0.9, N_HUMAN)
    hand = np.asarray(jax.vmap(lambda x: dyn.site_pose(x)[0])(jnp.asarray(q[:, -1])))
    cost = np.asarray(jax.jit(jax.vmap(lambda a, d: torque_cost(dyn, grid, a, d)))(q, dur))
    humans = make_database(q, dur, hand, cost=cost)
    humans = Database(*(a.astype(f64) if a.dtype == np.float32 else a for a in humans))
    # conditions near the humans' hands; 0 ends beyond a joint limit, 1 has a NaN final posture
    i = np.arange(M_COND)
    bqf = qf[i].copy()
    bqf[0, 4] = hi[4] + 0.3
    bqf[1] = np.nan
    zero = np.zeros((M_COND, j))
    cond = Conditions(
        target=hand[i] + 0.01,
        boundary=Boundary(
            q0=np.broadcast_to(robot.rest, (M_COND, j)).astype(f64),
            qf=bqf,
            qd0=zero,
            qdf=zero,
            duration=dur[i],
        ),
        ik_error=np.zeros(M_COND),
        n_human_inside=np.zeros(M_COND, np.int32),
        human_q=q[i],
    )
    db0 = jax.tree_util.tree_map(np.asarray, init_evolved_slots(humans, cond))
    args = (
        dyn, grid, lo, hi, N_HUMAN, BasisSettings(radius=0.15, neighbours=6),
        OptimSettings(method="adam", max_iters=10),
        EvolutionSettings(conditions=M_COND, generations=2, min_neighbours=3),
    )  # fmt: skip
    return args, db0, cond


def _generation(step, db, cond, g: int):
    """One generation: ``(db (numpy), stats dict)``."""
    from evojax_motion.motion.database import Database

    db, stats = step(db, cond, np.int32(g))
    return Database(*(np.asarray(a) for a in db)), {
        k: np.asarray(v).item() for k, v in stats._asdict().items()
    }


def _run(step, db0, cond):
    """Two chained generations: ``[(db, stats), (db, stats)]``."""
    first = _generation(step, db0, cond, 1)
    return [first, _generation(step, first[0], cond, 2)]


def _run_resident(step, db0, cond, devices: int) -> list[str]:
    """`_digests` of two chained generations with the inputs put on ``devices`` once and the
    database fed back as the step returned it (device arrays, not numpy)."""
    from evojax_motion.evolution.sharding import replicate
    from evojax_motion.motion.database import Database

    db, cond = replicate((db0, cond), devices)
    runs = []
    for g in (1, 2):
        db, _ = step(db, cond, np.int32(g))
        runs.append((Database(*(np.asarray(a) for a in db)), None))
    return _digests(runs)


def _digests(runs) -> list[str]:
    import hashlib

    return [hashlib.sha256(b"".join(a.tobytes() for a in db)).hexdigest() for db, _ in runs]


def _child_multihost() -> dict:
    """One of 2 processes (2 devices each): the 4-way sharded step on the global mesh."""
    import jax

    from evojax_motion.evolution.sharding import (
        initialize_distributed,
        make_sharded_generation_step,
        same_on_every_process,
    )

    info = initialize_distributed()
    args, db0, cond = _problem()
    if info["process_index"] == 1:  # a host that computed other bits: process 0's copy wins
        db0 = db0._replace(q=db0.q + 1e-3)
    db0, cond = same_on_every_process((db0, cond))
    step = make_sharded_generation_step(*args, devices=jax.device_count())
    process = {"index": info["process_index"], "count": info["process_count"]}
    digests = _run_resident(step, db0, cond, jax.device_count())
    return {"process": {**process, "devices": info["devices"]}, "digests": digests}


def _child_single() -> dict:
    """One-device vs sharded (4 devices), 2 generations, float64; returns the comparison."""
    import re

    import jax

    from evojax_motion.evolution.sharding import make_sharded_generation_step, padded_count
    from evojax_motion.evolution.step import make_generation_step
    from evojax_motion.settings.compiler import OptimSettings

    assert jax.device_count() == N_DEVICES
    args, db0, cond = _problem()
    # Each generation is compared on the same input (the one-device database): chained runs
    # would compound rounding-level differences through survivor selection and PCA.
    ref = _run(make_generation_step(*args), db0, cond)
    sharded = make_sharded_generation_step(*args, devices=N_DEVICES)
    compiled = sharded.lower(db0, cond, np.int32(1)).compile()
    inputs = [db0, ref[0][0]]
    got = [_generation(compiled, db, cond, g) for g, db in enumerate(inputs, start=1)]
    chained = [got[0], _generation(compiled, got[0][0], cond, 2)]  # as the 2 processes run it

    def shape_of(line):
        m = re.search(r"= \(?[a-z0-9]+\[([0-9,]*)\]", line)
        return [int(x) for x in m.group(1).split(",") if x] if m else None

    hlo = compiled.as_text()
    collectives = {
        op: [shape_of(ln) for ln in hlo.splitlines() if re.search(rf" {op}(-start)?\(", ln)]
        for op in COLLECTIVES
    }

    def plain(x):
        return None if isinstance(x, float) and not np.isfinite(x) else x

    gens = []
    for g, ((a, sa), (b, sb)) in enumerate(zip(ref, got), start=1):
        n = N_HUMAN
        both = a.valid[n:] & b.valid[n:]
        qa, qb = a.q[n:][both], b.q[n:][both]
        ca, cb = a.cost[n:][both], b.cost[n:][both]
        gens.append({
            "generation": g,
            "human_rows_bitwise": all(x[:n].tobytes() == y[:n].tobytes() for x, y in zip(a, b)),
            "untouched_fields_bitwise": all(
                getattr(a, f).tobytes() == getattr(b, f).tobytes()
                for f in ("duration", "condition", "origin")
            ),
            "valid_equal": bool((a.valid == b.valid).all()),
            "generation_equal": bool((a.generation == b.generation).all()),
            "q_bitwise": a.q.tobytes() == b.q.tobytes(),
            "q_max_abs_diff": float(np.abs(qa - qb).max(initial=0.0)),
            "cost_max_rel_diff": float(np.abs(ca / cb - 1.0).max(initial=0.0)),
            "stats": {k: [plain(sa[k]), plain(sb[k])] for k in sa},
        })  # fmt: skip
    # BFGS compiles through the CPU fast path, whose compiler options JAX accepts on the top-level
    # jit only: the sharded wrappers (one device: a jit around the step; several: the step
    # inlined per device) must carry them (tracing a nested jit with options raises).
    bfgs = (*args[:6], OptimSettings(method="bfgs", max_iters=3), args[7])
    lowered = [
        make_sharded_generation_step(*bfgs, devices=d).lower(db0, cond, np.int32(1)) is not None
        for d in (1, N_DEVICES)
    ]
    # (the 4-device step is `sharded` itself: its trace is kept, not made again)
    resident = {
        "1": _run_resident(make_sharded_generation_step(*args, devices=1), db0, cond, 1),
        str(N_DEVICES): _run_resident(sharded, db0, cond, N_DEVICES),
    }
    return {
        "bfgs_lowers": lowered,
        "one_device_digests": _digests(ref),
        "resident_digests": resident,
        "devices": jax.device_count(),
        "m_pad": padded_count(M_COND, N_DEVICES),
        "generations": gens,
        "collectives": collectives,
        "sharded_digests": _digests(chained),
    }


if __name__ == "__main__":
    print(json.dumps(_child_multihost() if sys.argv[1:] == ["multihost"] else _child_single()))
