"""Figures of a training run (matplotlib; every file written atomically).

- `plot_costs` (`costs_figure`): cost per generation, the paper's Fig. 5 ("the average of the
  sum of required torque for each movement primitive database"): ``torque_sum_mean`` [N m] and
  the eq. 5 cost; one legend below both panels names every curve.
- `plot_joint_angles` (`joint_angles_figure`): one condition's joint angles in the first and the
  last generation's database, the paper's Fig. 8 (1st generation black dashed, last red solid),
  with the human-only interpolation as a reference.

The ``*_figure`` functions return the matplotlib figure (tests inspect it); the ``plot_*`` ones
write it. Both are plain ``Figure`` objects: a training run that writes them never imports
pyplot.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from evojax_motion.run.atomic import atomic_write_bytes


def save_figure(fig, path: Path, crop: bool = True) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically and close it (where pyplot made it).

    ``crop``: to its contents (``bbox_inches="tight"``: the figure is drawn twice); False for
    a figure laid out already (a layout engine or fixed margins)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight" if crop else None)
    if fig.canvas.manager is not None:  # a pyplot figure: pyplot holds it until closed
        import matplotlib.pyplot as plt

        plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def costs_figure(metrics: list[dict], baseline: dict | None = None):
    """The figure of `plot_costs` (a matplotlib ``Figure``, not yet saved).

    Both panels' curves are named in one legend below them (the database's curve has the same
    colour in both).
    """
    baseline = baseline or {}
    gen = np.array([r["generation"] for r in metrics])

    def col(name):
        return np.array([np.nan if r.get(name) is None else r[name] for r in metrics], float)

    fig = Figure(figsize=(10, 3.9), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    db_label = "database (evolved slots)"
    ax1.plot(gen, col("torque_sum_mean"), "o-", color="tab:red", label=db_label)
    ax1.set_xlabel("generation")
    ax1.set_ylabel("mean torque sum [N m]")
    ax1.set_title("sum of required torque (Fig. 5)")
    ax2.plot(gen, col("db_cost_mean"), "o-", color="tab:red", label=db_label)
    ax2.plot(gen, col("offspring_cost_mean"), "x--", color="gray", label="offspring")
    ax2.set_xlabel("generation")
    ax2.set_ylabel(r"0.5 $\int |\tau|^2 dt$ [N$^2$ m$^2$ s]")
    ax2.set_title("eq. 5 cost")
    for ax, key in ((ax1, "human_only_torque_sum_mean"), (ax2, "human_only_cost_mean")):
        if baseline.get(key) is not None:
            ax.axhline(baseline[key], ls=":", color="tab:blue", label="human-only interpolation")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.xaxis.get_major_locator().set_params(integer=True)
    # one legend for both panels, outside them: inside, it hid curves
    handles: dict = {}
    for ax in (ax1, ax2):
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncols=len(handles))
    return fig


def plot_costs(metrics: list[dict], path: str | Path, baseline: dict | None = None) -> Path:
    """Fig. 5: per generation, mean torque sum [N m] and mean eq. 5 cost of the evolved slots.

    ``baseline``: ``human_only_torque_sum_mean`` / ``human_only_cost_mean`` (the human-only
    interpolation of the same conditions), drawn as horizontal reference lines.
    """
    return save_figure(costs_figure(metrics, baseline), Path(path), crop=False)


def joint_angles_figure(
    q_first: np.ndarray,
    q_last: np.ndarray,
    duration: float,
    joint_names,
    *,
    q_human: np.ndarray | None = None,
    first_label: str = "1st generation",
    last_label: str = "last generation",
    title: str = "",
):
    """The figure of `plot_joint_angles` (a matplotlib ``Figure``, not yet saved); the top
    panel's legend names the curves of every panel (the same in each)."""
    t = np.linspace(0.0, float(duration), q_last.shape[0])
    j = q_last.shape[1]
    fig = Figure(figsize=(6, 1.5 * j + 0.6))
    axes = fig.subplots(j, 1, sharex=True, squeeze=False)
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
    return fig


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
    fig = joint_angles_figure(
        q_first,
        q_last,
        duration,
        joint_names,
        q_human=q_human,
        first_label=first_label,
        last_label=last_label,
        title=title,
    )
    return save_figure(fig, Path(path))  # cropped: joint names of any length fit
