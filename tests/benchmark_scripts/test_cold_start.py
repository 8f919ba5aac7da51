"""benchmarks/cold_start.py: the phases it reads from a command's summary (text made up here in
the layout `train` prints)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.cold_start import TRAIN_PHASES, summary_values

SUMMARY = """\
human rows: 0 of 40 over a limit of the robot (joint range 0, velocity 0, torque 0); kept as data
generations                 10
seconds_per_generation      0.35
demos_seconds               11.9
conditions_seconds          9.5
compile_seconds             4.3
total_seconds               32.3
run_dir                     runs/demo
plots                       a.png, b.png
"""


def test_summary_values_reads_the_numeric_rows_only():
    got = summary_values(SUMMARY)
    assert got == {
        "generations": 10.0,
        "seconds_per_generation": 0.35,
        "demos_seconds": 11.9,
        "conditions_seconds": 9.5,
        "compile_seconds": 4.3,
        "total_seconds": 32.3,
    }
    assert set(TRAIN_PHASES) <= set(got)
