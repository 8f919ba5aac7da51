"""``evojax-motion import``: the argument parser and the command (`run_import`).

The import itself is `demonstrations.mocap.importer.import_trials` (docs/importing.md). Exit
status: 0 every trial imported; 1 some trials skipped (the others are saved); 2 a user error (bad
option, no input, no trial importable): nothing is written. The database is written atomically
(`motion.database.save_database`).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

from evojax_motion.demonstrations.mocap.import_params import FORMATS, ImportParams
from evojax_motion.demonstrations.mocap.import_report import format_report, report_dict
from evojax_motion.demonstrations.mocap.importer import import_trials
from evojax_motion.demonstrations.mocap.markers import MARKER_MODELS
from evojax_motion.errors import UserError

EXIT_OK, EXIT_SKIPPED, EXIT_USER_ERROR = 0, 1, 2


def add_import_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``import`` subcommand to an ``argparse`` subparsers object; sets ``func``.

    Option defaults are those of `ImportParams` (one source of truth for the CLI and the API).
    """
    p = subparsers.add_parser(
        "import",
        help="import real human demonstrations (motion capture) retargeted to a robot",
        description=(
            "Import motion-capture trials, retarget them to a robot by batched key-point IK and "
            "write a primitive database (docs/importing.md). Exit status: 0 all trials imported, "
            "1 some trials skipped (the others are written), 2 user error (nothing written)."
        ),
    )
    defaults = {f.name: f.default for f in fields(ImportParams)}

    def opt(flag, help, **kw):
        name = flag.lstrip("-").replace("-", "_")
        if defaults.get(name) is not None and not isinstance(defaults[name], bool):
            help += f" (default: {defaults[name]})"
        p.add_argument(flag, help=help, default=None, **kw)

    p.add_argument("paths", nargs="+", metavar="PATH", help="trial files or folders")
    p.add_argument("--format", required=True, choices=FORMATS, help="input format")
    p.add_argument("--out", required=True, help="output database .npz")
    opt("--robot", "shipped robot name or MJCF path")
    opt("--joints", "controlled joints of an MJCF, comma-separated")
    opt("--site", "end-effector site (or body) of an MJCF (default: its only site)")
    opt(
        "--keypoints",
        "robot point=human key point, e.g. body:upper_arm=shoulder,"
        "body:forearm=elbow,body:hand=wrist,site:hand=hand (default: per robot)",
    )
    opt(
        "--weights",
        "IK weight per key point, e.g. shoulder=0,elbow=0.5 (default: 1 where the robot's upper "
        "arm can hang as a person's, else hand=1 and 0 for the others)",
    )
    opt(
        "--reference",
        "origin of the human key points in every frame: shoulder, lab (frame 0's shoulder, "
        "fixed in the room), or a marker or key point name (e.g. STRN, thorax)",
    )
    opt(
        "--marker-model",
        f"built-in {sorted(MARKER_MODELS)} or a YAML file (default: per format)",
    )
    opt("--static", "static calibration trial for every trial (default: *static* beside it)")
    opt("--skeleton", "ASF skeleton of the AMC files (default: the .asf beside them)")
    opt("--samples", "samples T per primitive", type=int)
    opt("--max-gap", "longest marker gap filled by interpolation [frames]", type=int)
    opt("--cutoff-hz", "low-pass cut-off [Hz], 0: none", type=float)
    opt(
        "--onset-threshold", "movement onset/offset at this fraction of peak hand speed", type=float
    )
    opt("--min-peak-speed", "skip trials whose hand never moves faster [m/s]", type=float)
    opt("--min-duration", "skip movements shorter than this [s]", type=float)
    opt("--max-rms", "skip trials whose key-point RMS error exceeds this [m]", type=float)
    opt("--limit-margin-deg", "keep joints this far inside their limits [deg]", type=float)
    opt(
        "--rate",
        "frame rate [Hz] of angle files without a time column and of AMC files",
        type=float,
    )
    opt("--angle-unit", "unit of angle files", choices=("deg", "rad"))
    opt("--angle-map", "YAML robot_joint -> column for angles-csv")
    opt("--unit-scale", "metres per file unit (BVH default 0.01, ASF from :units)", type=float)
    opt("--ik-iters", "Levenberg-Marquardt iterations per frame", type=int)
    opt("--chunk", "trials per IK batch (memory vs. compile time)", type=int)
    opt("--capacity", "database capacity (>= trials; empty slots for evolution)", type=int)
    opt("--description", "description stored in the database")
    opt("--report", "also write the per-trial report as JSON here")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_import)
    return p


def _params_from(args) -> ImportParams:
    if isinstance(args, ImportParams):
        return args
    src = vars(args) if isinstance(args, argparse.Namespace) else dict(args)
    names = {f.name for f in fields(ImportParams)}
    kw = {k: v for k, v in src.items() if k in names and v is not None}
    for key in ("joints",):
        if isinstance(kw.get(key), str):
            kw[key] = tuple(s.strip() for s in kw[key].split(",") if s.strip())
    if "paths" in kw:
        kw["paths"] = tuple(map(str, kw["paths"]))
    if kw.get("cutoff_hz") == 0:
        kw["cutoff_hz"] = None
    try:
        return ImportParams(**kw)
    except TypeError as e:
        raise UserError(f"import: {e}") from None


def run_import(args) -> int:
    """The ``import`` command: an ``argparse.Namespace``, a mapping or `ImportParams` in, exit
    status out (0 all imported, 1 some skipped, 2 user error, raised as `UserError`)."""
    params = _params_from(args)
    if params.out is None:
        raise UserError("import: --out is required")
    out = Path(params.out)
    if out.exists() and not params.force:
        raise UserError(f"{out}: already exists (pass --force to overwrite)")
    result = import_trials(params)
    print(format_report(result))
    if result.db is None:
        reasons = "; ".join(f"{r.name}: {r.reason}" for r in result.reports[:5])
        raise UserError(f"import: no trial could be imported ({reasons})")
    from evojax_motion.motion.database import save_database
    from evojax_motion.run.atomic import atomic_write_text

    save_database(out, result.db, result.meta)
    if params.report:
        atomic_write_text(Path(params.report), json.dumps(report_dict(result, params), indent=1))
    print(f"written to {out}")
    return EXIT_SKIPPED if result.skipped else EXIT_OK
