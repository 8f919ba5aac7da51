"""Settings of the training run's bookkeeping (config section ``train``; `run.training`)."""

from __future__ import annotations

from dataclasses import dataclass

from evojax_motion.errors import check_setting


@dataclass(frozen=True)
class TrainSettings:
    """Run bookkeeping.

    - ``max_to_keep``: checkpoints kept (>= 2, so a damaged latest one has a predecessor).
    - ``checkpoint_every``: a checkpoint after every this many generations and after the last
      (>= 1); a resumed run restarts from the newest one and computes the generations after it
      again (to the same results). With a checkpoint after every generation, a generation's
      files took 44 ms on 2 CPU cores and 145 ms on one H100 machine, more than a paper-scale
      generation on a GPU (~8 ms): there a run checkpointing every generation made 6.6
      generations/s, every 10th 84 (`benchmarks/train_loop.py`).
    - ``plot_condition``: index of the condition drawn in ``plots/joint_angles.png`` (Fig. 8);
      ``null``: the one whose cost fell most from generation 1 to the last.
    - ``plots``: write the figures.
    """

    max_to_keep: int = 3
    checkpoint_every: int = 10
    plot_condition: int | None = None
    plots: bool = True

    def __post_init__(self):
        keep = self.max_to_keep
        check_setting(isinstance(keep, int) and keep >= 2, "max_to_keep", "an integer >= 2", keep)
        n = self.checkpoint_every
        check_setting(
            isinstance(n, int) and not isinstance(n, bool) and n >= 1,
            "checkpoint_every",
            "an integer >= 1",
            n,
        )
        c = self.plot_condition
        check_setting(
            c is None or (isinstance(c, int) and c >= 0),
            "plot_condition",
            "null or an integer >= 0",
            c,
        )
