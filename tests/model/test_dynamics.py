"""Inverse dynamics and forward kinematics (both backends) against C MuJoCo.

References: `mujoco.mj_inverse` (qfrc_inverse) and `mujoco.mj_kinematics` (site_xpos, site_xmat,
xpos) in float64 on the same compiled model, over random states inside the joint limits; central
finite differences for the gradients. Models: the two shipped robots and `assets/tree_arm.xml`,
a branching tree with hinge and slide joints, several joints on one body, off-axis inertias,
rotated frames, a joint reference angle, armature/damping/stiffness and an uncontrolled joint.
"""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from evojax_motion.errors import UserError
from evojax_motion.model.dynamics import BACKENDS, Dynamics, make_dynamics
from evojax_motion.model.rnea import FORMS, default_form, make_rnea
from evojax_motion.model.robot import load_robot, robot_from_mjcf_text

TOL_TAU_F32 = 1e-4  # max |tau - tau_ref| / max |tau_ref|, float32
TOL_TAU_F64 = 1e-10  # same, float64
TOL_SITE_POS_F32 = 1e-5  # [m]
TOL_SITE_ROT_F32 = 1e-5  # rotation matrix entries
TOL_KIN_F64 = 1e-12  # site and body positions [m], rotation entries, float64
TOL_GRAD_FD = 1e-6  # |grad - fd| / |fd| (norm over all entries), float64
FD_STEP = 1e-6
N_STATES = 1000
QD_SCALE, QDD_SCALE = 2.0, 10.0  # random velocities [rad/s], accelerations [rad/s^2]

ASSETS = Path(__file__).resolve().parents[1] / "assets"
# Not the model's joint order, and r_wrist is left out (held at its qpos0 = ref = 0.2).
TREE_JOINTS = ("l_elbow", "yaw", "lift", "l_sh1", "l_sh2", "r_slide", "r_sh", "r_elbow")
ROBOTS = {
    "mahru_arm": lambda: load_robot("mahru_arm"),
    "arm6": lambda: load_robot("arm6"),  # its gripper slide "finger" is not controlled
    "tree_arm": lambda: load_robot(ASSETS / "tree_arm.xml", joints=TREE_JOINTS, site="tip"),
}
# Published arms as users bring them (../shared/robots, skipped where absent) and a small model
# with continuous joints: the default RNEA form in float32 and float64 only (compile time).
SHARED_ROBOTS = Path(__file__).resolve().parents[3] / "shared" / "robots"
MORE_ROBOTS = {
    "continuous_arm": ASSETS / "continuous_arm.xml",  # continuous hinges, armature, damping
    "kinova_gen3": SHARED_ROBOTS / "kinova_gen3" / "gen3.xml",  # 4 continuous joints, meshes
    "xarm7_gripper": SHARED_ROBOTS / "ufactory_xarm7" / "xarm7.xml",  # armature, damping
}
MORE_SITES = {"xarm7_gripper": "link_tcp"}  # the others have one site


class Case:
    """A robot, random states and the C MuJoCo references for them (all float64 numpy)."""

    def __init__(self, name: str, robot=None):
        self.name = name
        self.robot = ROBOTS[name]() if robot is None else robot
        rng = np.random.default_rng(sum(map(ord, name)))
        n, j = N_STATES, self.robot.n_joints
        self.q = self.robot.sample_postures(rng, n)  # continuous joints: one turn about rest
        self.qd = QD_SCALE * rng.standard_normal((n, j))
        self.qdd = QDD_SCALE * rng.standard_normal((n, j))
        m = self.robot.mj_model
        d = mujoco.MjData(m)
        adr_q, adr_v = self.robot.qpos_adr, self.robot.dof_adr
        self.tau = np.zeros((n, j))
        self.site_pos, self.site_rot = np.zeros((n, 3)), np.zeros((n, 3, 3))
        self.xpos = np.zeros((n, m.nbody, 3))
        for i in range(n):
            d.qpos[:], d.qvel[:], d.qacc[:] = m.qpos0, 0.0, 0.0
            d.qpos[adr_q], d.qvel[adr_v], d.qacc[adr_v] = self.q[i], self.qd[i], self.qdd[i]
            mujoco.mj_inverse(m, d)  # runs mj_kinematics too
            self.tau[i] = d.qfrc_inverse[adr_v]
            self.site_pos[i] = d.site_xpos[self.robot.site_id]
            self.site_rot[i] = d.site_xmat[self.robot.site_id].reshape(3, 3)
            self.xpos[i] = d.xpos
        self._outputs = {}

    def outputs(self, backend: str, dtype) -> dict:
        """tau, site pose and body positions of all states; one compile per (backend, dtype).

        backend: a `BACKENDS` name, or "rnea-<form>" for a given RNEA layout (`FORMS`).
        """
        key = (backend, np.dtype(dtype).name)
        if key not in self._outputs:
            with jax.enable_x64(dtype == np.float64):
                if backend.startswith("rnea-"):
                    dyn = make_rnea(self.robot, dtype, form=backend.removeprefix("rnea-"))
                else:
                    dyn = make_dynamics(self.robot, backend, dtype)

                def one(q, qd, qdd):
                    pos, rot = dyn.site_pose(q)
                    return dyn.inverse(q, qd, qdd), pos, rot, dyn.body_positions(q)

                args = (jnp.asarray(x, dtype) for x in (self.q, self.qd, self.qdd))
                out = jax.jit(jax.vmap(one))(*args)
                assert all(o.dtype == dtype for o in out)
                self._outputs[key] = dict(
                    zip(("tau", "pos", "rot", "xpos"), map(np.asarray, out), strict=True)
                )
        return self._outputs[key]


@pytest.fixture(scope="module", params=list(ROBOTS))
def case(request) -> Case:
    return Case(request.param)


def rel_err(x, ref) -> float:
    return float(np.abs(x - ref).max() / np.abs(ref).max())


@pytest.fixture(scope="module", params=list(MORE_ROBOTS))
def more_case(request) -> Case:
    path = MORE_ROBOTS[request.param]
    if not path.is_file():
        pytest.skip(f"{path} not found (the published robot models sit beside the repository)")
    return Case(request.param, load_robot(path, end_effector=MORE_SITES.get(request.param)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_more_models_match_mj_inverse(more_case, dtype):
    """Continuous joints (q beyond +-pi included), published arms with meshes, armature and
    damping: the default RNEA form against `mj_inverse` and `mj_kinematics`."""
    out = more_case.outputs(f"rnea-{default_form()}", dtype)
    robot = more_case.robot
    if robot.continuous.any():  # the states reach past a half turn on the continuous joints
        assert np.abs(more_case.q[:, robot.continuous]).max() > np.pi
    tol = TOL_TAU_F32 if dtype == np.float32 else TOL_TAU_F64
    tol_pos = TOL_SITE_POS_F32 if dtype == np.float32 else TOL_KIN_F64
    assert np.abs(more_case.tau).max() > 1.0
    assert rel_err(out["tau"], more_case.tau) <= tol
    assert np.abs(out["pos"] - more_case.site_pos).max() <= tol_pos


# The default RNEA form on CPU is "vector"; the "scalar" one (the default on GPUs) is checked
# too. MJX compiles for tens of seconds on CPU: float32 MJX only on the default robot.
BACKEND_DTYPES = [
    ("rnea-vector", np.float32),
    ("rnea-vector", np.float64),
    ("rnea-scalar", np.float32),
    ("rnea-scalar", np.float64),
    ("mjx", np.float64),
    pytest.param("mjx", np.float32, marks=pytest.mark.slow, id="mjx-float32"),
]


@pytest.mark.parametrize(("backend", "dtype"), BACKEND_DTYPES)
def test_inverse_matches_mj_inverse(case, backend, dtype):
    if backend == "mjx" and dtype == np.float32 and case.name != "mahru_arm":
        pytest.skip("float32 MJX is checked on mahru_arm (compile time)")
    out = case.outputs(backend, dtype)
    tol = TOL_TAU_F32 if dtype == np.float32 else TOL_TAU_F64
    assert np.abs(case.tau).max() > 1.0  # the states exercise the dynamics
    assert rel_err(out["tau"], case.tau) <= tol


@pytest.mark.parametrize(("backend", "dtype"), BACKEND_DTYPES)
def test_site_pose_matches_mj_kinematics(case, backend, dtype):
    if backend == "mjx" and dtype == np.float32 and case.name != "mahru_arm":
        pytest.skip("float32 MJX is checked on mahru_arm (compile time)")
    out = case.outputs(backend, dtype)
    tol_pos, tol_rot = (
        (TOL_SITE_POS_F32, TOL_SITE_ROT_F32) if dtype == np.float32 else (TOL_KIN_F64,) * 2
    )
    assert np.abs(out["pos"] - case.site_pos).max() <= tol_pos
    assert np.abs(out["rot"] - case.site_rot).max() <= tol_rot
    if dtype == np.float64:
        assert np.abs(out["xpos"] - case.xpos).max() <= TOL_KIN_F64


def test_rnea_agrees_with_mjx_float64(case):
    rnea, mjx = case.outputs("rnea-vector", np.float64), case.outputs("mjx", np.float64)
    assert rel_err(rnea["tau"], mjx["tau"]) <= TOL_TAU_F64
    assert np.abs(rnea["pos"] - mjx["pos"]).max() <= TOL_KIN_F64
    assert np.abs(rnea["rot"] - mjx["rot"]).max() <= TOL_KIN_F64


def _torque_energy(dyn: Dynamics):
    """(q, qd, qdd): (B, J) each -> sum of tau^2 over the batch."""

    def energy(q, qd, qdd):
        return jnp.sum(jax.vmap(dyn.inverse)(q, qd, qdd) ** 2)

    return energy


def _central_differences(f, args, step):
    grads = []
    for k, x in enumerate(args):
        g = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            plus, minus = [a.copy() for a in args], [a.copy() for a in args]
            plus[k][idx] += step
            minus[k][idx] -= step
            g[idx] = (float(f(*plus)) - float(f(*minus))) / (2 * step)
        grads.append(g)
    return grads


def test_rnea_gradients_match_finite_differences(case, x64):
    dyn = make_rnea(case.robot, np.float64, form="vector")
    energy = _torque_energy(dyn)
    args = [case.q[:3], case.qd[:3], case.qdd[:3]]
    grads = jax.jit(jax.grad(energy, argnums=(0, 1, 2)))(*args)
    fds = _central_differences(jax.jit(energy), args, FD_STEP)
    for g, fd in zip(grads, fds, strict=True):
        assert np.linalg.norm(g - fd) <= TOL_GRAD_FD * np.linalg.norm(fd)


SMALL_ARM = """
<mujoco model="small_arm">
  <option gravity="0.3 0 -9.81"/>
  <worldbody>
    <body name="a" pos="0.1 0 0.5" quat="0.9 0.1 0.2 0">
      <joint name="h1" type="hinge" axis="0.2 0.1 1" pos="0.01 0.02 0" range="-2 2"/>
      <inertial pos="0.02 0 -0.1" quat="0.8 0.3 0.1 0.2" mass="2" diaginertia="0.03 0.02 0.01"/>
      <body name="b" pos="0 0.05 -0.2" quat="0.95 0 0.3 0">
        <joint name="s1" type="slide" axis="0 0.3 1" range="-0.1 0.1"/>
        <joint name="h2" type="hinge" axis="1 0 0.1" pos="0 0 0.03" range="-2 2"/>
        <inertial pos="0 0.01 -0.08" mass="1" fullinertia="0.01 0.009 0.005 0.0005 0 -0.0003"/>
        <site name="tip" pos="0 0 -0.2"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_scalar_torques_match_mj_inverse(case):
    """The scalar layout's unstacked torques (`Dynamics.torques`, sequences of scalars in, a tuple
    out: the CPU optimiser's fused search gradient reads them) are `mj_inverse`'s, armature,
    damping and stiffness included (`tree_arm`); float64."""
    with jax.enable_x64(True):
        dyn = make_dynamics(case.robot, "rnea", np.float64, form="scalar")
        assert dyn.torques is not None
        assert make_dynamics(case.robot, "rnea", np.float64, form="vector").torques is None

        def one(q, qd, qdd):
            j = case.robot.n_joints
            return jnp.stack(dyn.torques(*([x[k] for k in range(j)] for x in (q, qd, qdd))))

        tau = np.asarray(jax.jit(jax.vmap(one))(case.q, case.qd, case.qdd))
    assert rel_err(tau, case.tau) <= TOL_TAU_F64


@pytest.mark.parametrize("form", FORMS)
def test_rnea_form_gradients_match_finite_differences_small_arm(form, x64):
    """Both layouts' gradients on a 3-joint arm (the scalar form's gradient compiles slowly on
    CPU for larger models; the vector form is also checked on every model above)."""
    robot = robot_from_mjcf_text("small_arm", SMALL_ARM, site="tip")
    energy = _torque_energy(make_rnea(robot, np.float64, form=form))
    rng = np.random.default_rng(3)
    args = [
        rng.uniform(robot.lower, robot.upper, (2, 3)),
        QD_SCALE * rng.standard_normal((2, 3)),
        QDD_SCALE * rng.standard_normal((2, 3)),
    ]
    grads = jax.jit(jax.grad(energy, argnums=(0, 1, 2)))(*args)
    fds = _central_differences(jax.jit(energy), args, FD_STEP)
    for g, fd in zip(grads, fds, strict=True):
        assert np.linalg.norm(g - fd) <= TOL_GRAD_FD * np.linalg.norm(fd)


@pytest.mark.slow
def test_mjx_gradients_match_rnea(x64):
    """Gradients through mjx.inverse (30-40 s to compile on CPU) on one tiny batch."""
    case_robot = ROBOTS["tree_arm"]()
    rng = np.random.default_rng(7)
    j = case_robot.n_joints
    args = [
        rng.uniform(case_robot.lower, case_robot.upper, (2, j)),
        QD_SCALE * rng.standard_normal((2, j)),
        QDD_SCALE * rng.standard_normal((2, j)),
    ]
    ref = jax.grad(_torque_energy(make_dynamics(case_robot, "rnea", np.float64)), (0, 1, 2))
    got = jax.grad(_torque_energy(make_dynamics(case_robot, "mjx", np.float64)), (0, 1, 2))
    for g, r in zip(jax.jit(got)(*args), jax.jit(ref)(*args), strict=True):
        assert np.linalg.norm(g - r) <= TOL_TAU_F64 * np.linalg.norm(r)


def test_dynamics_is_a_static_argument_that_compiles_once():
    robot = ROBOTS["mahru_arm"]()
    dyn = make_dynamics(robot)
    traces = []

    @functools.partial(jax.jit, static_argnums=0)
    def tau(d: Dynamics, q):
        traces.append(1)
        return d.inverse(q, jnp.zeros_like(q), jnp.zeros_like(q))

    q = jnp.asarray(robot.rest, jnp.float32)
    g1, g2 = tau(dyn, q), tau(dyn, q + 0.1)
    assert len(traces) == 1
    assert g1.dtype == jnp.float32
    assert np.abs(np.asarray(g1) - np.asarray(g2)).max() > 0.0


def test_unfused_program_only_where_the_compiler_takes_its_options(monkeypatch):
    """`unfused_cpu_program` asks the compiler (`compiler_accepts`): an option it lacks is refused,
    and a jaxlib without the fusion-emitter switch (jax 0.11 and later) gets the default layout
    with default options instead of a compile error."""
    from evojax_motion.compile_options import compiler_accepts
    from evojax_motion.model import dynamics as dynamics_module
    from evojax_motion.model.dynamics import unfused_cpu_program
    from evojax_motion.model.rnea import UNFUSED_CPU_OPTIONS

    dyn = make_dynamics(ROBOTS["mahru_arm"]())
    fast, options = unfused_cpu_program(dyn)
    if jax.default_backend() == "cpu" and compiler_accepts(**UNFUSED_CPU_OPTIONS):
        assert fast.form == "scalar" and options == UNFUSED_CPU_OPTIONS
    monkeypatch.setattr(dynamics_module, "compiler_accepts", lambda **options: False)
    assert unfused_cpu_program(dyn) == (dyn, None)


def test_a_run_is_told_when_the_cpu_cannot_have_the_fast_layout(monkeypatch):
    """`slow_cpu_layout_note`: a line (naming the jax version and the README section) exactly
    where the CPU compiler refuses the fusion-emitter switch with the RNEA backend; none for
    MJX, where the layouts do not apply."""
    from evojax_motion.compile_options import compiler_accepts
    from evojax_motion.model import dynamics as dynamics_module
    from evojax_motion.model.dynamics import slow_cpu_layout_note
    from evojax_motion.model.rnea import UNFUSED_CPU_OPTIONS

    robot = ROBOTS["mahru_arm"]()
    dyn = make_dynamics(robot)
    cpu = jax.default_backend() == "cpu"
    assert (slow_cpu_layout_note(dyn) is None) == (
        not cpu or compiler_accepts(**UNFUSED_CPU_OPTIONS)
    )
    monkeypatch.setattr(dynamics_module, "compiler_accepts", lambda **options: False)
    note = slow_cpu_layout_note(dyn)
    if cpu:
        assert note is not None and jax.__version__ in note and "CPU and jax versions" in note
    assert slow_cpu_layout_note(make_dynamics(robot, "mjx")) is None


def test_one_shot_layout_is_the_vector_one_on_accelerators_only(monkeypatch):
    """`one_shot_layout`: on accelerators an RNEA `Dynamics` of another layout becomes the
    vector one (same robot and dtype; the layouts' torques are checked against `mj_inverse`
    above); on CPU, for MJX, and for the vector layout itself, the same object. A training run
    takes it up to `SHORT_RUN_WORK` generations x conditions and `SHORT_RUN_CONDITIONS` conditions
    (`training_layout`)."""
    from evojax_motion.model import dynamics as dynamics_module
    from evojax_motion.model.dynamics import (
        SHORT_RUN_CONDITIONS,
        SHORT_RUN_WORK,
        one_shot_layout,
        training_layout,
    )
    from evojax_motion.run.workflow import cache_parts
    from evojax_motion.settings import load_config

    robot = ROBOTS["mahru_arm"]()
    scalar = make_dynamics(robot, "rnea", np.float32, "scalar")
    mjx = make_dynamics(robot, "mjx")
    assert jax.default_backend() != "cpu" or one_shot_layout(scalar) is scalar
    monkeypatch.setattr(dynamics_module.jax, "default_backend", lambda: "gpu")
    vector = one_shot_layout(scalar)
    assert (vector.form, vector.robot, vector.dtype) == ("vector", robot, scalar.dtype)
    assert one_shot_layout(vector) is vector and one_shot_layout(mjx) is mjx
    few = SHORT_RUN_CONDITIONS
    assert training_layout(scalar, SHORT_RUN_WORK // few, few).form == "vector"
    assert training_layout(scalar, SHORT_RUN_WORK // few + 1, few) is scalar
    assert training_layout(scalar, 1, few + 1) is scalar
    # a run's traced programs are kept under a key that tells the layouts apart
    tiny = Path(__file__).resolve().parents[2] / "configs" / "tiny.yaml"
    cfg, longer = (load_config(tiny, s) for s in ([], [f"evolution.generations={SHORT_RUN_WORK}"]))
    layouts = (training_layout(scalar, c.evolution.generations, c.evolution.conditions)
               for c in (cfg, longer))  # fmt: skip
    short_key, long_key = (cache_parts(c, robot, d) for c, d in zip((cfg, longer), layouts))
    assert short_key != long_key


def test_user_errors():
    robot = ROBOTS["mahru_arm"]()
    with pytest.raises(UserError, match="dynamics: expected one of"):
        make_dynamics(robot, "pinocchio")
    assert "pinocchio" not in BACKENDS
    with jax.enable_x64(False), pytest.raises(UserError, match="x64"):
        make_dynamics(robot, "rnea", np.float64)
    with pytest.raises(UserError, match="dtype"):
        make_dynamics(robot, "rnea", np.int32)
    with pytest.raises(UserError, match="form"):
        make_rnea(robot, np.float32, form="matrix")


BALL_BELOW_HINGE = """
<mujoco model="ball_below">
  <worldbody>
    <body name="upper">
      <joint name="hinge" type="hinge" axis="0 1 0" range="-1 1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.04"/>
      <body name="lower" pos="0 0 -0.3">
        <joint name="ball" type="ball"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.04"/>
        <site name="tip" pos="0 0 -0.3"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_rnea_refuses_ball_joint_in_moving_tree():
    robot = robot_from_mjcf_text("ball_below", BALL_BELOW_HINGE, joints=["hinge"], site="tip")
    with pytest.raises(UserError, match="ball"):
        make_dynamics(robot, "rnea")
