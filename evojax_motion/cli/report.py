"""``evojax-motion report RUN_DIR``: the paper's figures and an HTML page from a run folder
(`report.build.make_report`; docs/report.md)."""

from __future__ import annotations

import sys


def add_report_parser(subparsers) -> None:
    """Add ``report`` to the ``evojax-motion`` subcommands (``cli.entry.build_parser``)."""
    from evojax_motion.cli.online import add_device_argument

    p = subparsers.add_parser(
        "report",
        help="the paper's figures and an HTML page from a run directory",
        description="Write the figures of a training run (paper Fig. 4, 5, 7-10, a cost vs "
        "human-likeness plot and a catch animation) and one self-contained report.html. "
        "Exit status: 0 all written; 1 run files missing (the other figures are written); "
        "2 no run in RUN_DIR.",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of `evojax-motion train`")
    p.add_argument("--out", default=None, help="output folder (default: RUN_DIR/report)")
    p.add_argument(
        "--condition",
        type=int,
        default=None,
        help="condition index (default: the config's train.plot_condition)",
    )
    p.add_argument("--joint", default=None, help="joint of Fig. 4 (default: the most varied)")
    p.add_argument(
        "--renderer",
        choices=("auto", "mujoco", "stick"),
        default="auto",
        help="snapshots: MuJoCo if a GL backend works (auto), MuJoCo only, or "
        "matplotlib stick figures",
    )
    p.add_argument("--snapshots", type=int, default=5, help="snapshots per motion (default 5)")
    p.add_argument("--gif-frames", type=int, default=36, help="frames of the catch animation")
    p.add_argument("--no-animation", action="store_true", help="skip catch.gif")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    add_device_argument(p)
    p.set_defaults(func=run_report)


def run_report(args) -> int:
    """The ``report`` subcommand: 0 complete, 1 incomplete run folder (figures still written)."""
    from evojax_motion.cli.online import use_device

    use_device(args.device)  # before anything starts a JAX backend
    from evojax_motion.report.build import make_report
    from evojax_motion.run.cache import enable_compile_cache

    enable_compile_cache()  # a second report of a run skips most of the XLA compile time
    rep = make_report(
        args.run_dir,
        args.out,
        condition=args.condition,
        joint=args.joint,
        renderer=args.renderer,
        snapshots=args.snapshots,
        gif_frames=args.gif_frames,
        animation=not args.no_animation,
        quiet=args.quiet,
    )
    print(rep.html)
    if rep.problems:
        names = ", ".join(rep.problems)
        print(
            f"error: incomplete run folder ({names}); the other figures were written",
            file=sys.stderr,
        )
        return 1
    return 0
