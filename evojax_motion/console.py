"""Lines for the user on stderr: warnings and progress of a run or a report (stdout holds the
results: a run's summary table, a command's output)."""

import sys


def log(msg: str) -> None:
    """``msg`` as one line on stderr, flushed at once (it may precede a long computation)."""
    print(msg, file=sys.stderr, flush=True)
