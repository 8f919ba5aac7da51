"""Figures of a training run (matplotlib; every file written atomically).

- `plot_costs`: cost per generation, the paper's Fig. 5 ("the average of the sum of required torque
  for each movement primitive database"): ``torque_sum_mean`` [N m] and the eq. 5 cost.
- `plot_joint_angles`: one condition's joint angles in the first and the last generation's
  database, the paper's Fig. 8 (1st generation black dashed, last red solid), with the human-only
  interpolation as a reference.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from evojax_motion.checkpoint import atomic_write_bytes


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def plot_costs(metrics: list[dict], path: str | Path, baseline: dict | None = None) -> Path:
    """Fig. 5: per generation, mean torque sum [N m] and mean eq. 5 cost of the evolved slots.

    ``baseline``: ``human_only_torque_sum_mean`` / ``human_only_cost_mean`` (the human-only
    interpolation of the same conditions), drawn as horizontal reference lines.
    """
    baseline = baseline or {}
    gen = np.array([r["generation"] for r in metrics])

    def col(name):
        return np.array([np.nan if r.get(name) is None else r[name] for r in metrics], float)

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    ax1.plot(gen, col("torque_sum_mean"), "o-", color="tab:red")
    ax1.set_xlabel("generation")
    ax1.set_ylabel("mean torque sum [N m]")
    ax1.set_title("sum of required torque (Fig. 5)")
    ax2.plot(gen, col("db_cost_mean"), "o-", label="database (survivors)")
    ax2.plot(gen, col("offspring_cost_mean"), "x--", color="gray", label="offspring")
    ax2.set_xlabel("generation")
    ax2.set_ylabel(r"0.5 $\int |\tau|^2 dt$ [N$^2$ m$^2$ s]")
    ax2.set_title("eq. 5 cost")
    for ax, key in ((ax1, "human_only_torque_sum_mean"), (ax2, "human_only_cost_mean")):
        if baseline.get(key) is not None:
            ax.axhline(baseline[key], ls=":", color="tab:blue", label="human-only interpolation")
    ax1.legend()
    ax2.legend()
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)
    return save_figure(fig, Path(path))


def plot_joint_angles(
    q_first: np.ndarray,
    q_last: np.ndarray,
    duration: float,
    joint_names,
    path: str | Path,
    *,
    q_human: np.ndarray | None = None,
    first_label: str = "1st generation",
    last_label: str = "last generation",
    title: str = "",
) -> Path:
    """Fig. 8: joint angles [deg] over time [s] of one condition. ``q_*: (T, J)`` [rad]."""
    t = np.linspace(0.0, float(duration), q_last.shape[0])
    j = q_last.shape[1]
    fig, axes = plt.subplots(j, 1, figsize=(6, 1.5 * j + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        if q_human is not None:
            ax.plot(t, np.degrees(q_human[:, k]), ":", color="tab:blue", lw=1, label="human only")
        ax.plot(t, np.degrees(q_first[:, k]), "--", color="black", lw=1.2, label=first_label)
        ax.plot(t, np.degrees(q_last[:, k]), "-", color="tab:red", lw=1.5, label=last_label)
        ax.set_ylabel(f"{joint_names[k]}\n[deg]", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time [s]")
    if title:
        axes[0, 0].set_title(title)
    return save_figure(fig, Path(path))
