"""Full import of the UE ADL motion-capture subset (``../shared/data/ue_adl``) for two robots.

Runs `evojax_motion.mocap.import_trials` on all 10 subjects x 2 tasks x 5 trials of the right-arm
reaching data, once for the default robot (mahru_arm) and once for arm6, and writes the statistics
(trials imported, key-point RMS error after scaling per trial, median / p95, joint-limit contacts,
timing) to ``benchmarks/results/import_ue_adl.json``, and the imported databases to
``runs/import_ue_adl_<robot>.npz`` (not committed) unless ``--no-save``.

    python benchmarks/import_ue_adl.py [--data ../shared/data/ue_adl] [--robots mahru_arm arm6]

Skips (exit 0, a message) when the data folder is absent.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "ue_adl"
OUT = HERE / "results" / "import_ue_adl.json"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument("--robots", nargs="+", default=["mahru_arm", "arm6"])
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--no-save", action="store_true", help="do not write the databases")
    args = parser.parse_args(argv)
    data = Path(args.data)
    if not data.is_dir():
        print(f"{data}: not found; nothing to benchmark")
        return 0

    import jax

    from evojax_motion.database import save_database
    from evojax_motion.mocap.importer import ImportParams, import_trials, report_dict

    results = {
        "data": str(data),
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
        },
        "robots": {},
    }
    for robot in args.robots:
        params = ImportParams(format="vicon-csv", paths=(str(data),), robot=robot, quiet=True)
        t0 = time.perf_counter()
        res = import_trials(params)
        wall = time.perf_counter() - t0
        rep = report_dict(res, params)
        summary = rep["summary"]
        summary["wall_s"] = round(wall, 2)
        rms = np.array([r.rms_error_m for r in res.imported])
        summary["imported_fraction"] = len(res.imported) / max(len(res.reports), 1)
        summary["rms_error_mean_m"] = float(rms.mean()) if rms.size else None
        if res.db is not None:
            q = np.asarray(res.db.q)
            from evojax_motion.robot import load_robot

            rb = load_robot(robot)
            summary["within_joint_limits"] = bool(
                ((q >= rb.lower - 1e-6) & (q <= rb.upper + 1e-6)).all()
            )
            summary["duration_s_range"] = [
                float(res.db.duration.min()),
                float(res.db.duration.max()),
            ]
            if not args.no_save:
                save_database(HERE.parent / "runs" / f"import_ue_adl_{robot}.npz", res.db, res.meta)
        results["robots"][robot] = {
            "summary": summary,
            "trials": [
                {
                    k: t[k]
                    for k in (
                        "name",
                        "status",
                        "reason",
                        "frames",
                        "frames_filled",
                        "duration_s",
                        "rms_error_m",
                        "max_error_m",
                        "keypoint_rms_m",
                        "limit_frames",
                        "limit_joints",
                        "condition",
                    )
                }
                for t in rep["trials"]
            ],
        }
        med = summary["rms_error_median_m"]
        p95 = summary["rms_error_p95_m"]
        print(
            f"{robot}: imported {summary['imported']}/{summary['trials']}, key-point RMS median "
            f"{1e3 * med:.1f} mm, p95 {1e3 * p95:.1f} mm, {wall:.1f} s "
            f"(ik {summary['timing_s']['ik']} s)"
            if med is not None
            else f"{robot}: none imported"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
