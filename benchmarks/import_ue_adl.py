"""Full import of the UE ADL motion-capture subset (``../shared/data/ue_adl``) for several robots.

Runs `evojax_motion.demonstrations.mocap.import_trials` with its defaults (no ``--weights``, no
``--keypoints``) on all 10 subjects x 2 tasks x 5 trials of the right-arm reaching data, once per
robot: the shipped mahru_arm and arm6, and the published Kinova Gen3 and UFactory xArm7 models
from ``../shared/robots`` (unedited; continuous joints) when that folder is there. Writes the
statistics (trials imported, key-point RMS error after scaling per trial, median / p95, joint
limit contacts, where the hand targets lie, the spread of each continuous joint's start angle,
timing) to ``benchmarks/results/import_ue_adl.json``, and the imported databases to
``runs/import_ue_adl_<robot>.npz`` (not committed) unless ``--no-save``.

    python benchmarks/import_ue_adl.py [--data ../shared/data/ue_adl] [--robots mahru_arm ...]

Skips (exit 0, a message) when the data folder is absent.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SHARED = ROOT.parent / "shared"
DEFAULT_DATA = SHARED / "data" / "ue_adl"
PUBLISHED = (
    SHARED / "robots" / "kinova_gen3" / "gen3.xml",
    SHARED / "robots" / "ufactory_xarm7" / "xarm7_nohand.xml",
)
OUT = HERE / "results" / "import_ue_adl.json"
TOL_LIMIT = 1e-6  # [rad] imported joint values inside the limits


def _relative(path: str | Path) -> str:
    """A path as seen from the repository (results name no machine-local folder)."""
    return os.path.relpath(Path(path).resolve(), ROOT) if Path(path).exists() else str(path)


def hand_placement(trials: list[dict], base_z: float) -> dict:
    """Where the hand targets of the imported ``trials`` (report rows) lie in the robot's frame:
    how many stay in front of its base (x > 0 over the whole movement) and above it (z >=
    ``base_z``), and the extremes [m]."""
    boxes = np.array([t["hand_target_box"] for t in trials if t["hand_target_box"]])
    if boxes.size == 0:
        return {"trials": 0}
    lo, hi = boxes[:, 0], boxes[:, 1]
    return {
        "trials": len(boxes),
        "in_front": int((lo[:, 0] > 0).sum()),
        "above_base": int((lo[:, 2] >= base_z - 1e-9).sum()),
        "base_z_m": round(base_z, 4),
        "x_range_m": [round(float(lo[:, 0].min()), 4), round(float(hi[:, 0].max()), 4)],
        "y_range_m": [round(float(lo[:, 1].min()), 4), round(float(hi[:, 1].max()), 4)],
        "z_range_m": [round(float(lo[:, 2].min()), 4), round(float(hi[:, 2].max()), 4)],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument(
        "--robots",
        nargs="+",
        default=["mahru_arm", "arm6", *(str(p) for p in PUBLISHED if p.is_file())],
        help="shipped robot names or MJCF paths",
    )
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--no-save", action="store_true", help="do not write the databases")
    args = parser.parse_args(argv)
    data = Path(args.data)
    if not data.is_dir():
        print(f"{data}: not found; nothing to benchmark")
        return 0

    sys.path.insert(0, str(HERE))
    from dynamics_throughput import machine_info

    from evojax_motion.demonstrations.mocap import retarget as rt
    from evojax_motion.demonstrations.mocap.import_params import ImportParams
    from evojax_motion.demonstrations.mocap.import_report import report_dict
    from evojax_motion.demonstrations.mocap.importer import import_trials
    from evojax_motion.model.robot import load_robot
    from evojax_motion.motion.database import save_database

    machine = machine_info()
    machine["command"] = " ".join(
        ["python", "benchmarks/import_ue_adl.py", *(_relative(a) for a in (argv or sys.argv[1:]))]
    )
    results: dict = {"data": _relative(data), "machine": machine, "robots": {}}
    for spec in args.robots:
        robot = load_robot(spec)
        params = ImportParams(format="vicon-csv", paths=(str(data),), robot=spec, quiet=True)
        t0 = time.perf_counter()
        res = import_trials(params)
        wall = time.perf_counter() - t0
        rep = report_dict(res, params)
        summary = rep["summary"]
        summary["wall_s"] = round(wall, 2)
        rms = np.array([r.rms_error_m for r in res.imported])
        summary["imported_fraction"] = len(res.imported) / max(len(res.reports), 1)
        summary["rms_error_mean_m"] = float(rms.mean()) if rms.size else None
        kp = rt.robot_keypoints(robot)
        summary["keypoints"] = dict(zip(kp.human, kp.robot))
        summary["weights"] = dict(zip(kp.human, kp.weights))
        imported = [t for t in rep["trials"] if t["status"] == "imported"]
        summary["hand_targets"] = hand_placement(imported, rt.base_height(robot))
        summary["lift_m_range"] = (
            [min(t["lift_m"] for t in imported), max(t["lift_m"] for t in imported)]
            if imported
            else None
        )
        if res.db is not None:
            q = np.asarray(res.db.q)
            summary["within_joint_limits"] = bool(
                ((q >= robot.lower - TOL_LIMIT) & (q <= robot.upper + TOL_LIMIT)).all()
            )
            summary["duration_s_range"] = [
                float(res.db.duration.min()),
                float(res.db.duration.max()),
            ]
            # continuous joints: the start angles of all primitives lie on one 2 pi branch
            summary["continuous_start_rad"] = {
                name: [round(float(q[:, 0, j].min()), 3), round(float(q[:, 0, j].max()), 3)]
                for j, name in enumerate(robot.joint_names)
                if robot.continuous[j]
            }
            if not args.no_save:
                save_database(ROOT / "runs" / f"import_ue_adl_{robot.name}.npz", res.db, res.meta)
        results["robots"][robot.name] = {
            "model": spec if spec == robot.name else _relative(spec),
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
                        "lift_m",
                        "hand_target_box",
                        "condition",
                    )
                }
                for t in rep["trials"]
            ],
        }
        med = summary["rms_error_median_m"]
        p95 = summary["rms_error_p95_m"]
        hands = summary["hand_targets"]
        print(
            f"{robot.name}: imported {summary['imported']}/{summary['trials']}, key-point RMS "
            f"median {1e3 * med:.1f} mm, p95 {1e3 * p95:.1f} mm, hand targets in front "
            f"{hands['in_front']}/{hands['trials']}, above the base {hands['above_base']}, "
            f"{wall:.1f} s (ik {summary['timing_s']['ik']} s)"
            if med is not None
            else f"{robot.name}: none imported"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"written to {_relative(out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
