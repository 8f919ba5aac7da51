"""The ``evojax-motion`` command line: one subcommand per stage of the pipeline.

User mistakes (``UserError``, bad arguments) print one line ``error: ...`` on stderr and exit 2;
nothing is written in that case. So do the file system's refusals (``OSError``: read-only file
system, no space left, permission denied, a file where a folder should be): one line ``error:
PATH: REASON``. A command checks that its output folder can be written before it starts its
work (`run.atomic.check_writable`; `train` takes its run folder's lock, `run_lock`); every file is
written atomically (`atomic`), so a refusal later on leaves no partial file either.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from evojax_motion.errors import UserError

EXIT_USER_ERROR = 2


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``error: ...``) and exit status 2."""

    def error(self, message):
        raise UserError(f"{self.prog}: {message}")


def _cmd_demos(args) -> int:
    from evojax_motion.run.workflow import build_demonstrations, print_demo_summary
    from evojax_motion.settings import load_config

    cfg = load_config(args.config, args.set)
    out = Path(args.out)
    if out.exists() and not args.force:
        raise UserError(f"{out}: already exists (pass --force to overwrite)")
    if out.suffix != ".npz":
        raise UserError(f"{out}: expected an output path ending in .npz")
    db, meta, report = build_demonstrations(cfg)
    from evojax_motion.motion.database import save_database

    save_database(out, db, meta)
    print_demo_summary(report, out)
    return 0


def _cmd_train(args) -> int:
    if args.distributed:  # before anything else touches JAX
        from evojax_motion.evolution.sharding import initialize_distributed

        initialize_distributed()
    from evojax_motion.run.cache import enable_compile_cache
    from evojax_motion.run.memory import gpu_memory_on_demand
    from evojax_motion.run.training import run_training
    from evojax_motion.settings import load_config

    cfg = load_config(args.config, args.set)
    gpu_memory_on_demand(cfg)  # before anything starts a JAX backend
    enable_compile_cache()  # a second run of the same config skips tracing and compiling
    run_training(cfg, Path(args.out), resume=args.resume, progress=not args.quiet)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="evojax-motion",
        description="Human-like, low-torque robot motions from an evolving primitive database.",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("demos", help="generate the (synthetic) human demonstration database")
    p.add_argument("--config", required=True, help="YAML config, e.g. configs/catch_ball.yaml")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_demos)

    p = sub.add_parser("train", help="evolve the database (the paper's offline process)")
    p.add_argument("config", help="YAML config, e.g. configs/catch_ball.yaml")
    p.add_argument("--out", required=True, help="run directory")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument(
        "--distributed",
        action="store_true",
        help="one of several processes of one run (jax.distributed; SLURM and Open MPI are "
        "detected, else set JAX_COORDINATOR_ADDRESS, EVOJAX_NUM_PROCESSES, EVOJAX_PROCESS_ID; "
        "docs/scaling.md)",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_train)

    from evojax_motion.cli.importing import add_import_parser

    add_import_parser(sub)

    from evojax_motion.cli.online import add_online_parsers
    from evojax_motion.cli.report import add_report_parser

    add_online_parsers(sub)

    add_report_parser(sub)
    __import__("evojax_motion.cli.robot", fromlist=["_"]).add_robot_parser(sub)
    __import__("evojax_motion.cli.simulate", fromlist=["_"]).add_simulate_parser(sub)
    return parser


# Commands whose --out is a folder; every other --out is a file. A run folder is checked by
# `train` itself, as it takes the folder's lock (`run_lock`).
_FOLDER_OUTPUT, _OWN_CHECK = {"report", "simulate"}, {"train"}


def output_folder(args: argparse.Namespace) -> Path | None:
    """The folder a command's output goes into (made if missing), or None: no output, or
    checked by the command itself."""
    out = getattr(args, "out", None)
    if args.command in _OWN_CHECK:
        return None
    if args.command == "report" and out is None:
        from evojax_motion.report.build import REPORT_DIR

        return Path(args.run_dir) / REPORT_DIR
    if out is None:
        return None
    return Path(out) if args.command in _FOLDER_OUTPUT else Path(out).parent


def os_error_line(e: OSError) -> str:
    """``PATH: REASON`` of a file-system error (``REASON`` where it names no path)."""
    reason = e.strerror or str(e) or type(e).__name__
    name = e.filename
    if isinstance(name, (str, bytes, os.PathLike)):
        return f"{os.fsdecode(name)}: {reason}"
    return reason


# Non-finite negative numbers: argparse takes "-inf" for an option (its negative-number test
# knows digits only) and refused "--start 0 ... -inf" as an unknown argument instead of letting
# the option's own check name it. A leading space keeps them values; float() ignores it.
_NEGATIVE_NON_FINITE = {"-inf", "-infinity", "-nan"}


def _keep_values(argv: list[str]) -> list[str]:
    return [f" {a}" if a.lower() in _NEGATIVE_NON_FINITE else a for a in argv]


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script. Returns the exit status."""
    try:
        argv = _keep_values(sys.argv[1:] if argv is None else list(argv))
        args = build_parser().parse_args(argv)
        folder = output_folder(args)
        if folder is not None:
            from evojax_motion.run.atomic import check_writable

            check_writable(folder)  # before minutes of work, not after
        import jax

        # float32 matmuls on GPUs default to TF32; finite differences and the BC solves need full
        # float32 (see timegrid), so every command runs at the highest matmul precision.
        with jax.default_matmul_precision("highest"):
            return int(args.func(args) or 0)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as e:  # the file system's refusal is the user's to fix, not a crash
        print(f"error: {os_error_line(e)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
