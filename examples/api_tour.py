"""A tour of the Python API (the README's example): database -> bases -> both compilers -> cost.

Run: ``python examples/api_tour.py`` (about a minute on 2 CPU cores, mostly XLA compilation).
"""

import jax
import numpy as np

from evojax_motion.compiler.basis import pca_basis, select_neighbours
from evojax_motion.compiler.interpolation import Boundary, compile_interpolation
from evojax_motion.compiler.optimisation import make_optimisation_compiler
from evojax_motion.demonstrations.synthetic import generate_demonstrations
from evojax_motion.model.dynamics import make_dynamics
from evojax_motion.model.ik import solve_ik
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.objective import torque_cost
from evojax_motion.motion.timegrid import make_time_grid
from evojax_motion.settings.compiler import OptimSettings
from evojax_motion.settings.demonstrations import DemoSettings

# 1. A robot and its dynamics (RNEA compiled from the MJCF; backend="mjx" for MuJoCo MJX).
robot = load_robot("mahru_arm")
dyn = make_dynamics(robot, backend="rnea")

# 2. A database: synthetic human-like catches here; `load_database("demos.npz")` reads a file.
db, _report = generate_demonstrations(
    robot, dyn, DemoSettings(count=60, samples=32), jax.random.key(0)
)
grid = make_time_grid(db.q.shape[1])

# 3. Bases for a batch of conditions (catch points): neighbours within 15 cm, per-joint PCA.
targets = np.asarray(db.condition[:4]) + np.array([0.02, -0.02, 0.01])
nb = select_neighbours(db.condition, db.valid, targets, k=10, radius=0.15)
basis = pca_basis(db.q, db.duration, nb, n_components=4)

# 4. Boundary conditions: start at rest, end at a human-like IK posture of the target, at rest.
c, j = targets.shape[0], robot.n_joints
rest = np.tile(robot.rest, (c, 1)).astype(np.float32)
qf = solve_ik(dyn, targets, rest, robot.lower, robot.upper).q
zeros = np.zeros((c, j), np.float32)
boundary = Boundary(q0=rest, qf=qf, qd0=zeros, qdf=zeros, duration=basis.duration)

# 5. Compile by interpolation (eq. 1-2) and by optimisation (eq. 3-5), all conditions in one jit.
interp = compile_interpolation(basis, boundary, grid, n_components=3)
optimise = make_optimisation_compiler(dyn, grid, robot.lower, robot.upper, OptimSettings())
opt = optimise(basis, boundary)

# 6. The torque cost 0.5 * int |tau|^2 dt of any trajectory.
cost = jax.vmap(lambda q, d: torque_cost(dyn, grid, q, d))
print("interpolation cost:", np.round(cost(interp.q, boundary.duration), 2))
print("optimisation cost: ", np.round(opt.cost, 2), "within limits:", opt.within_limits)
