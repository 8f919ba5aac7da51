"""Which rows of a primitive database a robot can execute: joint, velocity and torque limits.

The evolution rejects offspring over any of them (`evolution.step.generation_stages`); human rows
(demonstrations, imported motion) are data and stay in the database whatever they need, but a
run reports how many are over a limit (`count_over_limits`, `over_limits_line`), and the
conditions take their neighbours' durations slowed to the velocity limits
(`slowed_to_velocity_limits`, ``evolution.fit_speed``). A row is over a
limit where some sample leaves ``[lower, upper]`` (+`compiler.optimisation.LIMIT_TOL`), or its peak
``|qd|`` (``|tau|``, inverse dynamics on the time grid, as eq. 5's torques) over the T samples
exceeds `model.robot.Robot.velocity_limit` (``torque_limit``). Infinite limits are never exceeded.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from evojax_motion.compile_options import one_shot_jit
from evojax_motion.compiler.optimisation import LIMIT_TOL
from evojax_motion.model.dynamics import Dynamics
from evojax_motion.motion.database import Database
from evojax_motion.motion.objective import trajectory_measures
from evojax_motion.motion.timegrid import make_time_grid

# Rows per call of the torque program (one compilation for any database size).
CHUNK_ROWS = 256


class OverLimits(NamedTuple):
    """Counts among the valid rows: ``rows`` checked; rows over a ``joint`` range, a
    ``velocity`` or a ``torque`` limit (a row may count in several); ``any``: over at least
    one."""

    rows: int
    joint: int
    velocity: int
    torque: int
    any: int


def _peaks(dyn: Dynamics, q, duration):
    """Peak ``|qd|`` and ``|tau|`` per row: ``q (n, T, J)``, ``duration (n,)`` -> ``(n, J)`` x 2."""
    grid = make_time_grid(q.shape[1], q.dtype)
    return jax.vmap(lambda q1, d: trajectory_measures(dyn, grid, q1, d)[2:])(q, duration)


_peaks_program = one_shot_jit(_peaks, static_argnums=0)


def row_peaks(db: Database, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """``(peak |qd| [rad/s], peak |tau| [N m])``, each ``(N, J)`` float64 for every row of
    ``db`` (invalid rows too), computed in chunks of `CHUNK_ROWS` rows."""
    q = np.asarray(db.q, np.float32)
    dur = np.asarray(db.duration, np.float32)
    n = q.shape[0]
    out_qd, out_tau = [], []
    for s in range(0, n, CHUNK_ROWS):
        qc, dc = q[s : s + CHUNK_ROWS], dur[s : s + CHUNK_ROWS]
        pad = CHUNK_ROWS - qc.shape[0] if n > CHUNK_ROWS else 0
        if pad:  # resting rows: the last row repeated, dropped below
            qc = np.concatenate([qc, np.repeat(qc[-1:], pad, axis=0)])
            dc = np.concatenate([dc, np.repeat(dc[-1:], pad, axis=0)])
        pqd, ptau = _peaks_program()(dyn, qc, dc)
        keep = qc.shape[0] - pad
        out_qd.append(np.asarray(pqd, np.float64)[:keep])
        out_tau.append(np.asarray(ptau, np.float64)[:keep])
    if not out_qd:
        j = q.shape[-1]
        return np.zeros((0, j)), np.zeros((0, j))
    return np.concatenate(out_qd), np.concatenate(out_tau)


def outside_joint_range(q, lower, upper) -> np.ndarray:
    """``(N,)`` bool: the motions of ``q (N, T, J)`` with a sample outside ``[lower, upper]``
    (``(J,)`` [rad], +`compiler.optimisation.LIMIT_TOL`), compared in float64."""
    q = np.asarray(q, np.float64)
    return np.any((q < lower - LIMIT_TOL) | (q > upper + LIMIT_TOL), axis=(1, 2))


def count_over_limits(db: Database, robot, dyn: Dynamics, rows=None, peaks=None) -> OverLimits:
    """How many valid rows of ``db`` (or of the boolean mask ``rows (N,)`` among them, e.g.
    `motion.database.human_mask`) are over a joint, velocity or torque limit of ``robot``
    (`model.robot.Robot`), with torques from ``dyn``. ``peaks``: ``(peak |qd|, peak |tau|)``,
    each ``(N, J)``, of every row of ``db`` where already computed (`row_peaks`;
    `motion.objective.CostProgram`), else None."""
    sel = np.asarray(db.valid, bool)
    if rows is not None:
        sel = sel & np.asarray(rows, bool)
    sub = Database(*(np.asarray(a)[sel] for a in db))
    q = np.asarray(sub.q, np.float64)
    joint = outside_joint_range(q, np.asarray(robot.lower), np.asarray(robot.upper))
    qd_max, tau_max = np.asarray(robot.velocity_limit), np.asarray(robot.torque_limit)
    if peaks is not None:
        pqd, ptau = (np.asarray(p, np.float64)[sel] for p in peaks)
    elif q.shape[0] and (np.isfinite(qd_max).any() or np.isfinite(tau_max).any()):
        pqd, ptau = row_peaks(sub, dyn)
    else:
        pqd = ptau = np.zeros_like(q[:, 0])
    velocity = np.any(~(pqd <= qd_max), axis=1)  # NaN counts as over
    torque = np.any(~(ptau <= tau_max), axis=1)
    return OverLimits(
        rows=int(q.shape[0]),
        joint=int(joint.sum()),
        velocity=int(velocity.sum()),
        torque=int(torque.sum()),
        any=int((joint | velocity | torque).sum()),
    )


def over_limits_line(counts: OverLimits, what: str = "human rows") -> str:
    """One line for a log: ``what``, and how many are over each limit."""
    return (
        f"{what}: {counts.any} of {counts.rows} over a limit of the robot (joint range "
        f"{counts.joint}, velocity {counts.velocity}, torque {counts.torque}); kept as data"
    )


def slowed_to_velocity_limits(duration, peak_velocity, velocity_limit, headroom: float):
    """Durations at which rows keep within the velocity limits: ``duration (n,)`` [s] times
    ``max(1, max_j peak_velocity_j / ((1 - headroom) velocity_limit_j))``, i.e. each row slowed
    uniformly in time (its speeds scale with ``1 / duration``) until its fastest joint is at the
    usable limit; rows already within keep their duration exactly. ``peak_velocity (n, J)``
    [rad/s], ``velocity_limit (J,)`` (inf: none). Returns ``(durations (n,), factors (n,))``."""
    usable = (1.0 - headroom) * np.asarray(velocity_limit, np.float64)
    ratio = np.asarray(peak_velocity, np.float64) / usable
    factor = np.maximum(1.0, np.max(ratio, axis=1, initial=0.0))
    return np.asarray(duration, np.float64) * factor, factor


def slowed_line(factor, headroom: float) -> str | None:
    """One line for a log on `slowed_to_velocity_limits`'s ``factors (n,)``: how many rows
    were slowed and by how much; None when none was."""
    slow = np.asarray(factor)[np.asarray(factor) > 1.0]
    if slow.size == 0:
        return None
    return (
        f"demonstrations: {slow.size} of {np.size(factor)} faster than the robot's velocity "
        f"limits less {headroom:.0%}; the conditions count them slowed x{slow.min():.2f}"
        f"-{slow.max():.2f} (median x{np.median(slow):.2f}; evolution.fit_speed)"
    )
