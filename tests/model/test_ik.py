"""Batched damped-least-squares IK (`evojax_motion.model.ik`): accuracy, limits, redundancy,
failure.

One batched `solve_ik` call (one compile) holds four groups of rows, each checked by its own test:
reachable targets under two posture preferences, starts outside tight per-row joint boxes, and
unreachable targets.
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.ik import solve_ik, solve_ik_trajectory
from evojax_motion.model.robot import load_robot

TOL_REACH = 1e-3  # [m] accuracy required for reachable targets
TOL_LIMIT = 1e-6  # [rad] iterates are clipped: no violation beyond float32 rounding
TOL_STATIONARY = 2e-3  # |N W (q - q_pref)| / |W (q - q_pref)| at a converged redundant solution
UNREACHABLE_SLACK = 0.01  # [m] hand distance beyond the geometric optimum (unreachable targets)
MAX_STEP_ALONG_PATH = 0.05  # [rad] joint change between neighbouring samples of a ~1 cm-step path
BOX = 0.15  # [rad] half-width of the tight joint boxes
N_PREF, N_BOX, N_FAR = 24, 12, 4  # rows: 2 x N_PREF preferences, N_BOX boxes, N_FAR unreachable
W_PREF = np.array([1.0, 0.25, 0.25, 0.25, 0.25, 0.5, 0.5], np.float32)  # waist held hardest
# models/mahru_arm.xml: waist axis through x = y = 0, shoulder 0.19 m to its right at z = 1.40
SHOULDER_OFFSET, SHOULDER_Z = 0.19, 1.40
FRONT_X = 0.15  # [m] reachable test targets lie in front of the trunk (x > FRONT_X)
REACH = 0.2817 + 0.2689 + np.hypot(0.015, 0.06)  # upper arm + forearm + hand site


def _postures(robot, key, n, fraction):
    """Random postures in the middle ``fraction`` of every joint range."""
    mid, half = (robot.lower + robot.upper) / 2, (robot.upper - robot.lower) / 2 * fraction
    return np.asarray(
        jax.random.uniform(key, (n, robot.n_joints), minval=mid - half, maxval=mid + half)
    )


def _mj_site(robot, q):
    """C MuJoCo's site position for one posture (an independent forward kinematics)."""
    d = mujoco.MjData(robot.mj_model)
    d.qpos[robot.qpos_adr] = q
    mujoco.mj_kinematics(robot.mj_model, d)
    return d.site_xpos[robot.site_id].copy()


@pytest.fixture(scope="module")
def arm():
    robot = load_robot("mahru_arm")
    dyn = make_dynamics(robot, backend="rnea")
    fk = jax.jit(jax.vmap(lambda q: dyn.site_pose(q)[0]))
    return robot, dyn, fk


@pytest.fixture(scope="module")
def batch(arm):
    """Inputs and result of the shared solve; ``rows[name]`` are the row indices of each group."""
    robot, dyn, fk = arm
    j = robot.n_joints
    rest = np.asarray(robot.rest, np.float32)
    # reachable targets in front of the body, where the catch targets are (behind the back some
    # random targets sit past box-constrained local minima from the rest posture)
    cand = _postures(robot, jax.random.key(0), 8 * N_PREF, 0.4)
    reach_q = cand[np.asarray(fk(cand))[:, 0] > FRONT_X][:N_PREF]
    box_q = _postures(robot, jax.random.key(1), N_BOX, 0.4)
    far_dir = np.array([[1.0, 0, 0], [0.6, -0.8, 0], [0.7, 0, 0.7], [0.3, -0.3, 0.905]])
    far = np.array([0.0, -SHOULDER_OFFSET, SHOULDER_Z]) + 1.2 * far_dir  # ~2 reaches away
    pref_b = rest.copy()
    pref_b[3] += 0.6  # humeral rotation: swivels the elbow

    targets = np.concatenate([fk(reach_q), fk(reach_q), fk(box_q), far])
    # box rows start outside their box (a corner 0.6 rad away) and prefer that corner
    corner = box_q + 0.6 * np.sign(np.asarray(jax.random.normal(jax.random.key(2), box_q.shape)))
    q_init = np.concatenate([np.tile(rest, (2 * N_PREF, 1)), corner, np.tile(rest, (N_FAR, 1))])
    q_pref = np.concatenate(
        [
            np.tile(rest, (N_PREF, 1)),
            np.tile(pref_b, (N_PREF, 1)),
            corner,
            np.tile(rest, (N_FAR, 1)),
        ]
    )
    w_pref = np.tile(W_PREF, (len(targets), 1))
    w_pref[-N_FAR:] = 0.0  # unreachable rows: pure least squares
    lower = np.tile(robot.lower, (len(targets), 1))
    upper = np.tile(robot.upper, (len(targets), 1))
    box = slice(2 * N_PREF, 2 * N_PREF + N_BOX)
    lower[box], upper[box] = box_q - BOX, box_q + BOX
    args = dict(
        targets=targets, q_init=q_init, lower=lower, upper=upper, q_pref=q_pref, w_pref=w_pref
    )
    res = solve_ik(
        dyn,
        args["targets"],
        args["q_init"],
        args["lower"],
        args["upper"],
        q_pref=args["q_pref"],
        w_pref=args["w_pref"],
    )
    starts = np.cumsum([0, N_PREF, N_PREF, N_BOX, N_FAR])
    rows = {
        name: np.arange(a, b) for name, a, b in zip(("a", "b", "box", "far"), starts, starts[1:])
    }
    assert q_init.shape == (starts[-1], j) and len(reach_q) == N_PREF
    return args, res, rows, pref_b


def test_reaches_reachable_targets_within_limits(arm, batch):
    robot, _, _ = arm
    args, res, rows, _ = batch
    near = np.concatenate([rows["a"], rows["b"]])
    q, err = np.asarray(res.q), np.asarray(res.pos_error)
    assert np.max(err[near]) < TOL_REACH
    assert np.all(np.asarray(res.converged)[near])
    for i in near[::8]:  # pos_error is what C MuJoCo measures
        assert abs(np.linalg.norm(_mj_site(robot, q[i]) - args["targets"][i]) - err[i]) < 1e-5
    assert np.all(q >= args["lower"] - TOL_LIMIT) and np.all(q <= args["upper"] + TOL_LIMIT)


def test_respects_tight_joint_boxes(batch):
    """Started 0.6 rad outside a +-0.15 rad box that contains a solution: stays in, reaches it."""
    args, res, rows, _ = batch
    box = rows["box"]
    q = np.asarray(res.q)[box]
    assert np.all(np.abs(args["q_init"][box] - (args["lower"][box] + BOX)) > BOX)  # outside
    assert np.all(q >= args["lower"][box] - TOL_LIMIT)
    assert np.all(q <= args["upper"][box] + TOL_LIMIT)
    assert np.max(np.asarray(res.pos_error)[box]) < TOL_REACH


def test_unreachable_target_reports_its_error(arm, batch):
    robot, _, _ = arm
    args, res, rows, _ = batch
    far = rows["far"]
    yaw = np.linspace(robot.lower[0], robot.upper[0], 2001)
    shoulders = np.stack(
        [SHOULDER_OFFSET * np.sin(yaw), -SHOULDER_OFFSET * np.cos(yaw), np.full_like(yaw, 1.4)], -1
    )
    # the best any posture can do: the nearest shoulder position, then the arm fully stretched
    best = np.linalg.norm(args["targets"][far, None] - shoulders, axis=-1).min(axis=1) - REACH
    err = np.asarray(res.pos_error)[far]
    assert not np.any(np.asarray(res.converged)[far])
    assert np.all(err >= best - 1e-4)  # an honest error: no posture does better
    # and the error-dependent damping brings the hand to (nearly) the best point
    assert np.all(err <= best + UNREACHABLE_SLACK)


def test_null_space_resolves_redundancy_toward_preference(arm, batch):
    """Same targets, two preferences: both reached, each result a stationary point of
    ``sum_j w_j (q_j - pref_j)^2`` on the solution manifold (its projected gradient vanishes)."""
    robot, dyn, _ = arm
    args, res, rows, _ = batch
    q = np.asarray(res.q)
    assert np.median(np.abs(q[rows["b"], 3] - q[rows["a"], 3])) > 0.1  # the preference matters

    def projected_gradient(q, pref):
        jac = jax.jacfwd(lambda x: dyn.site_pose(x)[0])(q)
        null = jnp.eye(q.shape[0]) - jnp.linalg.pinv(jac) @ jac
        g = W_PREF * (q - pref)
        return jnp.linalg.norm(null @ g) / (jnp.linalg.norm(g) + 1e-9)

    near = np.concatenate([rows["a"], rows["b"]])
    free = np.all((q > robot.lower + 0.01) & (q < robot.upper - 0.01), axis=1)[near]
    ratio = np.asarray(jax.vmap(projected_gradient)(q[near], args["q_pref"][near]))
    assert free.sum() > len(near) // 2
    assert np.max(ratio[free]) < TOL_STATIONARY


def test_no_recompile_for_new_values(arm, batch):
    _, dyn, _ = arm
    args, res, _, _ = batch
    before = solve_ik._cache_size()
    again = solve_ik(
        dyn,
        args["targets"] + 0.001,
        args["q_init"],
        args["lower"],
        args["upper"],
        q_pref=args["q_pref"] + 0.01,
        w_pref=args["w_pref"],
    )
    assert solve_ik._cache_size() == before
    assert not np.array_equal(np.asarray(again.q), np.asarray(res.q))


def test_trajectory_tracks_a_path_smoothly(arm, batch):
    """Straight paths between solved postures: every sample reached, no branch jumps."""
    robot, dyn, fk = arm
    _, res, rows, _ = batch
    t, b = 40, 8
    q_from, q_to = np.asarray(res.q)[rows["a"][:b]], np.asarray(res.q)[rows["a"][b : 2 * b]]
    start, end = fk(q_from), fk(q_to)
    s = np.linspace(0.0, 1.0, t)[None, :, None]
    paths = start[:, None] + s * (end - start)[:, None]  # (B, T, 3)
    out = solve_ik_trajectory(
        dyn, paths, q_from, robot.lower, robot.upper, q_pref=q_from, w_pref=W_PREF
    )
    assert out.q.shape == (b, t, robot.n_joints) and out.pos_error.shape == (b, t)
    assert np.max(out.pos_error) < TOL_REACH and np.all(out.converged)
    step_cm = np.max(np.linalg.norm(np.diff(paths, axis=1), axis=-1)) * 100
    steps = np.abs(np.diff(np.asarray(out.q), axis=1))
    assert np.max(steps) < MAX_STEP_ALONG_PATH * max(step_cm, 1.0)  # one smooth branch


def test_continuous_joints_have_no_limits_in_ik():
    """Continuous joints (limits -inf/+inf) pass through the clamping and clipping untouched:
    targets of postures past a half turn are reached from starts 0.2 rad away, with finite
    iterates, limited joints inside their limits and continuous ones not wrapped."""
    robot = load_robot(Path(__file__).resolve().parents[1] / "assets" / "continuous_arm.xml")
    assert robot.continuous.any() and np.isinf(robot.lower[robot.continuous]).all()
    dyn = make_dynamics(robot, backend="rnea")
    fk = jax.jit(jax.vmap(lambda q: dyn.site_pose(q)[0]))
    q_true = robot.sample_postures(np.random.default_rng(0), 16, margin=0.02).astype(np.float32)
    targets = np.asarray(fk(q_true))
    start = q_true + 0.2 * np.random.default_rng(1).choice([-1.0, 1.0], q_true.shape)
    res = solve_ik(dyn, targets, start.astype(np.float32), robot.lower, robot.upper, iters=100)
    q = np.asarray(res.q)
    assert np.isfinite(q).all()
    assert np.asarray(res.converged).all(), np.asarray(res.pos_error).max()
    np.testing.assert_allclose(np.asarray(fk(q)), targets, atol=TOL_REACH)
    limited = ~robot.continuous
    assert (q[:, limited] >= robot.lower[limited] - TOL_LIMIT).all()
    assert (q[:, limited] <= robot.upper[limited] + TOL_LIMIT).all()
    assert np.abs(q[:, robot.continuous]).max() > np.pi  # beyond the half turn, not wrapped
