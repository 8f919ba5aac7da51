"""``evojax-motion import``: real human demonstrations -> a movement primitive database.

Park et al. (2008, sec. 4.1) build their initial database from captured human motions turned
into joint trajectories by IK. This command does that for recordings in common formats and any
robot model:

    evojax-motion import --format vicon-csv --robot mahru_arm --out demos.npz DATA_DIR

Per trial: read (`vicon_csv`, `c3d_file`, `bvh`, `asf_amc`, `angles_csv`), fill marker gaps up to
``--max-gap`` frames, low-pass filter, build the human key points (`markers`), express them
relative to the person's shoulder (``--reference``) in a frame that turns with the trunk, scale
them to the robot's reach and solve the key-point IK for every frame (`retarget`, one jit for all
trials), keep continuous joints on the rest posture's 2 pi branch (`motion.angles.on_rest_branch`),
cut
the movement at hand-speed onset/offset, resample to ``--samples`` T, and take the final hand
position as the condition. Joint-angle CSV files skip the IK (columns map to joints).

A trial that cannot be imported (unreadable or truncated file, a required marker missing, a gap
longer than ``--max-gap``, no movement, IK error above ``--max-rms``) is skipped with its reason and
its figure (e.g. ``IK error: key-point RMS 61 mm > --max-rms 50 mm; largest 89 mm at frame 312
(3.12 s, wrist)``), and the others are imported. Exit status: 0 every trial imported; 1 some
trials skipped (the others are saved); 2 a user error (bad option, no input, no trial
importable): nothing is written. The database is written atomically
(`motion.database.save_database`).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evojax_motion.demonstrations.mocap import markers as mk
from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError
from evojax_motion.errors import UserError
from evojax_motion.motion.angles import on_rest_branch
from evojax_motion.settings.demonstrations import IKSettings

FORMATS = ("vicon-csv", "c3d", "bvh", "asf-amc", "angles-csv")
REFERENCES = ("shoulder", "lab")  # --reference, besides a marker or key point name
DEFAULT_MARKER_MODEL = {
    "vicon-csv": "ue_adl",
    "c3d": "ue_adl",
    "bvh": "cmu_bvh",
    "asf-amc": "cmu_asf",
}
EXTENSIONS = {
    "vicon-csv": ".csv",
    "c3d": ".c3d",
    "bvh": ".bvh",
    "asf-amc": ".amc",
    "angles-csv": ".csv",
}
EXIT_OK, EXIT_SKIPPED, EXIT_USER_ERROR = 0, 1, 2
PAD_FRAMES = 64  # frame counts are padded to a multiple of this: few distinct jit shapes


@dataclass(frozen=True)
class ImportParams:
    """Options of the import (the CLI's flags; see `add_import_parser` for their help)."""

    format: str
    paths: tuple[str, ...]
    out: str | None = None
    robot: str = "mahru_arm"
    joints: tuple[str, ...] | None = None
    site: str | None = None
    keypoints: str | Mapping[str, str] | None = None  # "body:x=shoulder,..." or a mapping
    reference: str = "shoulder"  # shoulder | lab | a marker or key point name
    marker_model: str | None = None
    static: str | None = None
    skeleton: str | None = None
    samples: int = 100
    max_gap: int = 20
    cutoff_hz: float | None = 6.0
    onset_threshold: float = 0.05
    min_peak_speed: float = 0.05
    min_duration: float = 0.2
    max_rms: float = 0.05
    limit_margin_deg: float = 1.0
    rate: float | None = None
    angle_unit: str = "deg"
    angle_map: str | None = None
    unit_scale: float | None = None
    smooth: float = 1e-3
    weights: str | Mapping[str, float] | None = None  # "shoulder=0,..." or a mapping
    ik_iters: int = 4
    chunk: int = 32
    capacity: int | None = None
    description: str | None = None
    report: str | None = None
    force: bool = False
    quiet: bool = False

    def __post_init__(self):
        def need(ok, msg):
            if not ok:
                raise UserError(msg)

        need(self.format in FORMATS, f"--format: expected one of {FORMATS}, got {self.format!r}")
        need(len(self.paths) > 0, "import: expected at least one input PATH")
        need(self.samples >= 8, f"--samples: expected an integer >= 8, got {self.samples}")
        need(self.max_gap >= 0, f"--max-gap: expected frames >= 0, got {self.max_gap}")
        need(0 < self.onset_threshold < 1, "--onset-threshold: expected a fraction in (0, 1)")
        need(self.max_rms > 0, "--max-rms: expected metres > 0")
        need(self.min_duration >= 0, "--min-duration: expected seconds >= 0")
        need(self.limit_margin_deg >= 0, "--limit-margin-deg: expected degrees >= 0")
        need(self.rate is None or self.rate > 0, "--rate: expected Hz > 0")
        need(self.cutoff_hz is None or self.cutoff_hz >= 0, "--cutoff-hz: expected Hz >= 0")
        need(self.angle_unit in ("deg", "rad"), "--angle-unit: expected deg or rad")
        need(self.chunk >= 1 and self.ik_iters >= 1, "--chunk and --ik-iters: expected >= 1")
        need(self.unit_scale is None or self.unit_scale > 0, "--unit-scale: expected > 0")
        need(
            isinstance(self.reference, str) and self.reference.strip() != "",
            f"--reference: expected {' or '.join(REFERENCES)} or a marker name, "
            f"got {self.reference!r}",
        )
        need(
            self.capacity is None or self.capacity >= 1,
            f"--capacity: expected an integer >= 1, got {self.capacity}",
        )
        if self.out is not None:
            need(str(self.out).endswith(".npz"), f"--out {self.out}: expected a path ending .npz")


@dataclass
class TrialReport:
    """What happened to one trial (one row of the report)."""

    name: str
    path: str
    status: str = "skipped"  # imported | skipped
    reason: str = ""
    frames: int = 0  # frames read
    rate: float = 0.0  # [Hz]
    frames_filled: int = 0  # frames with an interpolated marker
    frames_trimmed: int = 0  # frames cut at the ends (a needed marker not seen)
    onset_s: float = math.nan
    duration_s: float = math.nan
    peak_hand_speed: float = math.nan  # [m/s] human hand (robot hand for angle files)
    heading: str = ""  # what turns the body frame with the person (markers, shoulder line...)
    lift_m: float = 0.0  # [m] targets raised to keep the hand above the robot's base
    hand_target_box: list = field(default_factory=list)  # [[x, y, z] min, max] over the movement
    rms_error_m: float = math.nan  # key-point RMS over the movement, after scaling
    max_error_m: float = math.nan
    keypoint_rms_m: dict = field(default_factory=dict)
    limit_frames: int = 0  # movement frames with a joint on a limit (clipped by the IK)
    limit_joints: list = field(default_factory=list)
    segment_scale: list = field(default_factory=list)  # robot / human segment lengths
    condition: list = field(default_factory=list)  # final hand position [m]


_SKIP_CATEGORIES = (  # (words in the reason, category), first match wins
    (("unreadable", "truncated", "cannot read", "not a "), "unreadable file"),
    (("static trial", "calibration"), "calibration"),
    (("missing", "never seen"), "marker missing"),
    (("gap of",), "gap too long"),
    (("no movement",), "no movement"),
    (("too short",), "movement too short"),
    (("key-point RMS", "IK "), "IK error too large"),
)


def skip_category(reason: str) -> str:
    """A skipped trial's reason grouped for the summary (``"gap too long"``, ...)."""
    for words, category in _SKIP_CATEGORIES:
        if any(w in reason for w in words):
            return category
    return "other"


class ImportResult:
    """Outcome of `import_trials`: the database (None if no trial survived) and the reports."""

    def __init__(self, db, meta, reports: list[TrialReport], timing: dict):
        self.db, self.meta, self.reports, self.timing = db, meta, reports, timing

    @property
    def imported(self) -> list[TrialReport]:
        return [r for r in self.reports if r.status == "imported"]

    @property
    def skipped(self) -> list[TrialReport]:
        return [r for r in self.reports if r.status != "imported"]

    def summary(self) -> dict:
        rms = np.array([r.rms_error_m for r in self.imported if np.isfinite(r.rms_error_m)])
        reasons: dict[str, int] = {}
        for r in self.skipped:
            key = skip_category(r.reason)
            reasons[key] = reasons.get(key, 0) + 1
        return {
            "trials": len(self.reports),
            "imported": len(self.imported),
            "skipped": len(self.skipped),
            "skipped_reasons": reasons,
            "rms_error_median_m": float(np.median(rms)) if rms.size else None,
            "rms_error_p95_m": float(np.percentile(rms, 95)) if rms.size else None,
            "rms_error_max_m": float(rms.max()) if rms.size else None,
            "frames_filled": int(sum(r.frames_filled for r in self.reports)),
            "trials_touching_limits": int(sum(r.limit_frames > 0 for r in self.imported)),
            "timing_s": self.timing,
        }


# ------------------------------------------------------------------------------ input discovery


def _is_static(path: Path) -> bool:
    return "static" in path.stem.lower()


def _is_vicon_export(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = [f.readline().strip().split(",")[0] for _ in range(40)]
    except OSError:
        return False
    return "Trajectories" in head or "Devices" in head


def find_trials(params: ImportParams) -> list[Path]:
    """Trial files named by ``params.paths``: files as given, folders searched recursively.

    In folders, only files of the format's extension count; calibration trials (``*static*``)
    and, for ``vicon-csv``, CSV files that are not Nexus exports (e.g. ``*angles.csv``) are left
    out. Raises `UserError` for a path that does not exist or when nothing is found.
    """
    ext = EXTENSIONS[params.format]
    out: list[Path] = []
    for p in map(Path, params.paths):
        if p.is_dir():
            found = sorted(x for x in p.rglob(f"*{ext}") if x.is_file() and not _is_static(x))
            if params.format == "vicon-csv":
                found = [x for x in found if _is_vicon_export(x)]
            out.extend(found)
        elif p.is_file():
            if not _is_static(p):
                out.append(p)
        else:
            raise UserError(f"{p}: no such file or folder")
    seen, unique = set(), []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            unique.append(p)
    if not unique:
        raise UserError(
            f"import: no {params.format} trial files ({ext}) found in {list(params.paths)}"
        )
    return unique


def find_static(trial: Path, explicit: str | None) -> Path | None:
    """The calibration trial of ``trial``: ``--static`` if given, else a ``*static*`` file of the
    same format in its folder (the one whose name before "static" prefixes the trial's name)."""
    if explicit is not None:
        return Path(explicit)
    cands = [
        p
        for p in trial.parent.iterdir()
        if p.is_file() and _is_static(p) and p.suffix.lower() == trial.suffix.lower()
    ]
    if len(cands) == 1:
        return cands[0]

    def prefix(p: Path) -> str:
        stem = p.stem
        return stem[: stem.lower().index("static")].rstrip("_- ")

    matches = [c for c in cands if prefix(c) and trial.stem.startswith(prefix(c))]
    return max(matches, key=lambda c: len(prefix(c))) if matches else None


def find_skeleton(amc: Path, explicit: str | None) -> Path:
    """The ASF of an AMC file: ``--skeleton`` or the folder's only ``.asf`` (or the one whose
    stem prefixes the AMC's, CMU style ``01.asf`` for ``01_02.amc``)."""
    if explicit is not None:
        return Path(explicit)
    cands = sorted(amc.parent.glob("*.asf"))
    if len(cands) == 1:
        return cands[0]
    matches = [c for c in cands if amc.stem.startswith(c.stem)]
    if matches:
        return max(matches, key=lambda c: len(c.stem))
    raise TrialError(f"no skeleton (.asf) found beside {amc.name} (give --skeleton)")


def _read_markers(path: Path, params: ImportParams, cache: dict) -> MarkerData:
    from evojax_motion.demonstrations.mocap.asf_amc import read_amc, read_asf
    from evojax_motion.demonstrations.mocap.bvh import read_bvh
    from evojax_motion.demonstrations.mocap.c3d_file import read_c3d
    from evojax_motion.demonstrations.mocap.vicon_csv import read_vicon_csv

    if params.format == "vicon-csv":
        return read_vicon_csv(path)
    if params.format == "c3d":
        return read_c3d(path)
    if params.format == "bvh":
        return read_bvh(path, 0.01 if params.unit_scale is None else params.unit_scale)
    asf = find_skeleton(path, params.skeleton)
    if asf not in cache:
        try:
            cache[asf] = read_asf(asf, params.unit_scale)
        except TrialError as e:
            cache[asf] = e
    sk = cache[asf]
    if isinstance(sk, TrialError):
        raise TrialError(f"skeleton {asf.name}: {sk}")
    return read_amc(path, sk, params.rate or 120.0)


# ------------------------------------------------------------------------------------- pipeline


class _Prepared(NamedTuple):
    """A trial ready for the IK: robot targets ``(F, K, 3)`` [m] and its movement segment."""

    report: TrialReport
    targets: np.ndarray
    rate: float
    segment: Any
    first_frame: int  # the file's frame of targets[0] (frames trimmed at the start before it)


def _progress(iterable, total, desc, quiet):
    if quiet:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="trial", file=sys.stderr, leave=False)


def _trial_name(path: Path, roots: Sequence[str]) -> str:
    for r in roots:
        rp = Path(r)
        if rp.is_dir():
            try:
                return str(path.relative_to(rp))
            except ValueError:
                continue
    return path.name


@functools.lru_cache(maxsize=4)
def _cached_dynamics(name, mjcf, joints, site):
    from evojax_motion.model.dynamics import make_dynamics
    from evojax_motion.model.robot import robot_from_mjcf_text

    robot = robot_from_mjcf_text(name, mjcf, joints, site)
    return robot, make_dynamics(robot, backend="rnea")


def _robot_and_dynamics(robot):
    """The same (robot, `Dynamics`) objects for the same model: the jitted IK, keyed on the
    `Dynamics` object, then compiles once per process, not once per import."""
    return _cached_dynamics(robot.name, robot.mjcf, tuple(robot.joint_names), robot.site_name)


def import_trials(params: ImportParams) -> ImportResult:
    """Run the whole import in memory (no file written). Raises `UserError` for bad options."""
    from evojax_motion.demonstrations.mocap import retarget as rt
    from evojax_motion.model.robot import load_robot

    t_start = time.perf_counter()
    robot, dyn = _robot_and_dynamics(
        load_robot(params.robot, joints=params.joints, site=params.site)
    )
    files = find_trials(params)
    if params.capacity is not None and params.capacity < len(files):  # before the IK's work
        raise UserError(
            f"--capacity: expected >= the {len(files)} trials found, got {params.capacity}"
        )
    margin = np.deg2rad(params.limit_margin_deg)
    lower = np.asarray(robot.lower) + margin
    upper = np.asarray(robot.upper) - margin
    if not (lower < upper).all():
        raise UserError("--limit-margin-deg: larger than half of a joint's range")
    reports = [TrialReport(_trial_name(p, params.paths), str(p)) for p in files]

    if params.format == "angles-csv":
        prepared_q = _prepare_angles(params, robot, dyn, files, reports, lower, upper)
        t_ik = time.perf_counter()
        ik_s = 0.0
    else:
        kmap, weights = params.keypoints, params.weights
        kp = rt.robot_keypoints(
            robot,
            rt.parse_pairs(kmap, "--keypoints") if isinstance(kmap, str) else kmap,
            rt.parse_weights(weights) if isinstance(weights, str) else weights,
        )
        model = mk.load_marker_model(params.marker_model or DEFAULT_MARKER_MODEL[params.format])
        undefined = [h for h in kp.human if h not in model.keypoints]
        if undefined:
            raise UserError(
                f"marker model {model.name!r} does not define the key points {undefined} that "
                f"robot {robot.name!r} uses ({dict(zip(kp.robot, kp.human))})"
            )
        rest_clipped = np.clip(np.asarray(robot.rest), lower, upper)
        rest_points = rt.rest_keypoints(dyn, kp, rest_clipped)
        # a shoulder that is a reference only: the hand's targets stay above the robot's base
        base_z = rt.base_height(robot) if kp.weights[0] == 0 else None
        prepared = _prepare_markers(params, model, kp, rest_points, base_z, files, reports)
        t_ik = time.perf_counter()
        settings = IKSettings(smooth=params.smooth, iters=params.ik_iters)
        prepared_q = _solve(params, robot, dyn, kp, settings, prepared, lower, upper, rest_clipped)
        ik_s = time.perf_counter() - t_ik

    # prepared_q: (report, q of the movement (F', J), rate) per trial that got this far
    qs, durations, rows = [], [], []
    for r, q, rate in prepared_q:
        q = on_rest_branch(q, np.asarray(robot.rest), robot.continuous)
        duration = (q.shape[0] - 1) / rate
        r.duration_s = duration
        if duration < params.min_duration:
            r.reason = (
                f"too short: movement of {duration:.2f} s < --min-duration {params.min_duration} s"
            )
            continue
        qs.append(np.clip(rt.resample(q, params.samples), lower, upper))
        durations.append(duration)
        rows.append(r)
    db = meta = None
    if rows:
        from evojax_motion.motion.database import DatabaseMeta, make_database

        q_all = np.stack(qs)
        dur = np.asarray(durations)
        cond, cost = rt.conditions_and_costs(dyn, q_all, dur)
        for r, c in zip(rows, cond):
            r.status, r.condition = "imported", np.round(c, 5).tolist()
        db = make_database(q_all, dur, cond, cost=cost, capacity=params.capacity)
        desc = params.description or (
            f"motion capture ({params.format}) of {len(rows)} trials retargeted to "
            f"{robot.name}: " + ", ".join(sorted({Path(r.path).parent.name for r in rows}))
        )
        meta = DatabaseMeta.of_robot(robot, synthetic=False, description=desc[:2000])
    for r in reports:
        if r.status != "imported":
            r.status = "skipped"
    total = time.perf_counter() - t_start
    timing = {
        "total": round(total, 3),
        "read_prepare": round(t_ik - t_start, 3),
        "ik": round(ik_s, 3),
    }
    return ImportResult(db, meta, reports, timing)


def _prepare_markers(params, model, kp, rest_points, base_z, files, reports) -> list[_Prepared]:
    """Read, calibrate, gap-fill, filter, build key points, scale and segment every trial.

    base_z: None, or the robot's base height [m] above which the hand targets are lifted.
    """
    from evojax_motion.demonstrations.mocap import retarget as rt

    cache: dict = {}
    data: dict[int, MarkerData] = {}
    for i, path in enumerate(_progress(files, len(files), "reading", params.quiet)):
        try:
            data[i] = _read_markers(path, params, cache)
            reports[i].frames, reports[i].rate = data[i].positions.shape[0], data[i].rate
        except TrialError as e:
            reports[i].reason = f"unreadable: {e}"
    # calibration per subject: trials that share a static trial (or a folder, without one)
    groups: dict[Any, list[int]] = {}
    statics: dict[Any, Path | None] = {}
    for i in data:
        static = (
            find_static(files[i], params.static) if params.format in ("vicon-csv", "c3d") else None
        )
        key = str(static) if static is not None else ("folder", str(files[i].parent))
        groups.setdefault(key, []).append(i)
        statics[key] = static
    calibs: dict[int, mk.Calibration | TrialError | None] = {}
    needs_calibration = any(kd.between is not None or kd.cluster for kd in model.keypoints.values())
    for key, members in groups.items():
        static_data = None
        static = statics[key]
        if static is not None:
            try:
                static_data = _read_markers(static, params, cache)
            except TrialError as e:
                for i in members:
                    calibs[i] = TrialError(f"static trial {static.name}: {e}")
                continue
        c: mk.Calibration | TrialError | None = None
        try:
            if needs_calibration:
                c = mk.calibrate(model, static_data, [data[i] for i in members])
        except TrialError as e:
            c = TrialError(f"calibration: {e}")
        for i in members:
            calibs[i] = c
    up_override = mk.axis_vector(model.up, "marker model up") if model.up else None
    forward = mk.axis_vector(model.forward, "marker model forward") if model.forward else None
    out = []
    for i in sorted(data):
        r, d = reports[i], data[i]
        try:
            calib = calibs[i]
            if isinstance(calib, TrialError):
                raise calib
            needed = mk.needed_markers(d, model, calib)
            ref_marker = _reference_marker(params.reference, model, d)
            if ref_marker is not None and ref_marker not in needed:
                needed.append(ref_marker)
            d, gaps = mk.fill_gaps(d, needed, params.max_gap)
            r.frames_filled, r.frames_trimmed = (
                gaps.frames_filled,
                gaps.trimmed_start + gaps.trimmed_end,
            )
            needed += _filled_heading_markers(d, model, params.max_gap)
            d = d._replace(positions=_filter_needed(d, needed, params.cutoff_hz))
            points = mk.keypoints(d, model, calib)
            up = up_override if up_override is not None else d.up
            human, moving = _body_coordinates(
                params.reference, model, d, points, kp.human, up, forward, r
            )
            scaled = rt.scale_to_robot(human, rest_points)
            targets = scaled.targets
            if base_z is not None:
                targets, r.lift_m = rt.lift_above_base(targets, base_z)
            seg = rt.segment_movement(moving, d.rate, params.onset_threshold, params.min_peak_speed)
            hand = targets[seg.onset : seg.offset + 1, -1]
            r.hand_target_box = np.round([hand.min(axis=0), hand.max(axis=0)], 4).tolist()
            r.segment_scale = np.round(scaled.robot_lengths / scaled.human_lengths, 4).tolist()
            r.onset_s = (gaps.trimmed_start + seg.onset) / d.rate
            r.peak_hand_speed = seg.peak_speed
            out.append(_Prepared(r, targets, d.rate, seg, gaps.trimmed_start))
        except TrialError as e:
            r.reason = str(e)
    return out


def _reference_marker(reference: str, model, d: MarkerData) -> str | None:
    """The marker ``--reference`` names (None: a key point or a built-in reference)."""
    if reference in REFERENCES or reference in model.keypoints:
        return None
    if not d.has(reference):
        raise TrialError(
            f"--reference {reference}: no such marker in the trial (expected shoulder, lab, a "
            f"key point of {sorted(model.keypoints)} or one of its {len(d.names)} markers)"
        )
    return reference


def _filled_heading_markers(d: MarkerData, model, max_gap: int) -> list[str]:
    """The model's heading markers, gap-filled in place in ``d``, when every frame of the kept
    window has them after filling; else none (the body frame then turns with the shoulder line).
    """
    if model.heading is None:
        return []
    names = [*model.heading[0], *model.heading[1]]
    if not all(d.has(n) for n in names):
        return []
    try:
        filled, gaps = mk.fill_gaps(d, names, max_gap)
    except TrialError:
        return []
    if gaps.trimmed_start or gaps.trimmed_end:
        return []
    idx = [d.column(n) for n in names]
    d.positions[:, idx] = filled.positions[:, idx]
    return names


def _body_coordinates(
    reference, model, d, points, humans, up, forward, report
) -> tuple[np.ndarray, np.ndarray]:
    """``(human (F, K, 3), hand (F, 3))``: the key points ``humans`` in the body frames of
    ``--reference`` (origin at the shoulder, or the marker / key point named, in every frame,
    turned with the trunk's heading; ``lab``: frame 0's body frame in every frame), and the hand
    relative to the trunk (the heading markers' centre, else the origin) along frame 0's axes,
    whose speed segments the movement: walking does not move it, and a seated person's trunk
    barely does, so it keeps the lab's speed profile.
    """
    hand = points[humans[-1]]
    if reference == "lab":
        origin, heading = None, mk.Heading(None, None, "fixed (--reference lab)")
    else:
        heading = mk.heading_direction(d, points, model)
        if reference == "shoulder":
            origin = points[next(k for k in mk.KEYPOINT_CHAIN if k in points)]
        elif reference in points:
            origin = points[reference]
        else:
            origin = d.get(reference)
    report.heading = heading.source
    origin, rot = mk.body_frames(points, up, forward, origin, heading.direction)
    human = np.stack([np.einsum("fij,fj->fi", rot, points[h] - origin) for h in humans], axis=1)
    bad = ~np.isfinite(human).all(axis=-1)
    if bad.any():
        f, k = np.argwhere(bad)[0]
        raise TrialError(f"key point {humans[k]} is not finite at frame {f} after gap filling")
    centre = origin if heading.centre is None else heading.centre
    return human, (hand - centre) @ rot[0].T


def _filter_needed(d: MarkerData, needed, cutoff) -> np.ndarray:
    pos = d.positions.copy()
    idx = [d.column(m) for m in needed]
    pos[:, idx] = mk.lowpass(pos[:, idx], d.rate, cutoff)
    return pos


def _solve(params, robot, dyn, kp, settings, prepared, lower, upper, rest):
    """Batched key-point IK of every prepared trial; returns (report, q movement, rate) rows."""
    from evojax_motion.demonstrations.mocap import retarget as rt

    if not prepared:
        return []
    n_max = max(p.targets.shape[0] for p in prepared)
    frames = int(math.ceil(n_max / PAD_FRAMES) * PAD_FRAMES)
    # batches of 8, 16, ... up to --chunk trials: few distinct shapes, few compilations
    chunk = min(params.chunk, max(8, 1 << (len(prepared) - 1).bit_length()))
    rows = []
    batches = range(0, len(prepared), chunk)
    for start in _progress(batches, len(batches), "retargeting", params.quiet):
        part = prepared[start : start + chunk]
        targets = np.stack(
            [
                np.pad(p.targets, ((0, frames - p.targets.shape[0]), (0, 0), (0, 0)), mode="edge")
                for p in part
            ]
        )
        if len(part) < chunk:  # same shape every call: one compilation
            targets = np.concatenate([targets, np.repeat(targets[-1:], chunk - len(part), 0)])
        res = rt.solve_keypoint_ik(dyn, kp, settings, targets, rest, lower, upper, rest)
        q_all, err_all = np.asarray(res.q, np.float64), np.asarray(res.error, np.float64)
        for b, p in enumerate(part):
            r = p.report
            on, off = p.segment.onset, p.segment.offset
            q, err = q_all[b, on : off + 1], err_all[b, on : off + 1]
            if not np.isfinite(q).all():
                f = p.first_frame + on + int(np.argmax(~np.isfinite(q).all(axis=1)))
                r.reason = f"IK did not converge (NaN) at frame {f} ({f / p.rate:.2f} s)"
                continue
            used = np.flatnonzero(np.asarray(kp.weights) > 0)  # weight 0: scaling only
            matched = err[:, used]
            r.rms_error_m = float(np.sqrt(np.mean(matched**2)))
            r.max_error_m = float(matched.max())
            r.keypoint_rms_m = {
                h: round(float(np.sqrt(np.mean(err[:, k] ** 2))), 5) for k, h in enumerate(kp.human)
            }
            lim = rt.at_limit(q, lower, upper)
            r.limit_frames = int(lim.any(axis=1).sum())
            r.limit_joints = [j for j, hit in zip(robot.joint_names, lim.any(axis=0)) if hit]
            if r.rms_error_m > params.max_rms:
                f, k = np.unravel_index(int(np.argmax(matched)), matched.shape)
                frame = p.first_frame + on + int(f)
                r.reason = (
                    f"IK error: key-point RMS {1e3 * r.rms_error_m:.0f} mm > --max-rms "
                    f"{1e3 * params.max_rms:.0f} mm; largest {1e3 * matched[f, k]:.0f} mm at "
                    f"frame {frame} ({frame / p.rate:.2f} s, {kp.human[used[k]]})"
                )
                continue
            rows.append((r, q, p.rate))
    return rows


def _prepare_angles(params, robot, dyn, files, reports, lower, upper):
    """Joint-angle files: map columns to joints, clip to the limits, segment on the robot hand."""
    from evojax_motion.demonstrations.mocap import retarget as rt
    from evojax_motion.demonstrations.mocap.angles_csv import (
        angles_to_robot,
        load_angle_map,
        read_angles_csv,
    )

    amap = load_angle_map(params.angle_map) if params.angle_map else None
    rows = []
    for i, path in enumerate(_progress(files, len(files), "reading", params.quiet)):
        r = reports[i]
        try:
            data = read_angles_csv(path, params.rate, degrees=params.angle_unit == "deg")
            r.frames, r.rate = data.angles.shape[0], data.rate
            q, _ = angles_to_robot(data, tuple(robot.joint_names), np.asarray(robot.rest), amap)
            q = mk.lowpass(q, data.rate, params.cutoff_hz)
            lim = (q < lower) | (q > upper)
            q = np.clip(q, lower, upper)
            hand = rt.site_path(dyn, q)
            seg = rt.segment_movement(
                hand, data.rate, params.onset_threshold, params.min_peak_speed
            )
            r.onset_s, r.peak_hand_speed = seg.onset / data.rate, seg.peak_speed
            mv = slice(seg.onset, seg.offset + 1)
            r.limit_frames = int(lim[mv].any(axis=1).sum())
            r.limit_joints = [j for j, hit in zip(robot.joint_names, lim[mv].any(axis=0)) if hit]
            rows.append((r, q[mv], data.rate))
        except TrialError as e:
            r.reason = str(e)
    return rows


# ------------------------------------------------------------------------------------ reporting


def format_report(result: ImportResult) -> str:
    """The per-trial table and the summary, as printed by the command."""
    lines = [
        f"{'trial':<28} {'status':<8} {'frames':>6} {'filled':>6} {'dur s':>6} "
        f"{'rms mm':>7} {'max mm':>7} {'limit%':>6}  reason"
    ]
    for r in result.reports:
        dur = f"{r.duration_s:.2f}" if np.isfinite(r.duration_s) else "-"
        rms = f"{1e3 * r.rms_error_m:.1f}" if np.isfinite(r.rms_error_m) else "-"
        mx = f"{1e3 * r.max_error_m:.1f}" if np.isfinite(r.max_error_m) else "-"
        n_mv = round(r.duration_s * r.rate) + 1 if np.isfinite(r.duration_s) else 0
        lim = f"{100 * r.limit_frames / n_mv:.0f}" if n_mv else "-"
        lines.append(
            f"{r.name[:28]:<28} {r.status:<8} {r.frames:>6} {r.frames_filled:>6} "
            f"{dur:>6} {rms:>7} {mx:>7} {lim:>6}  {r.reason}"
        )
    s = result.summary()
    lines.append("")
    lines.append(
        f"imported {s['imported']} of {s['trials']} trials"
        + (f"; skipped {s['skipped']}: {s['skipped_reasons']}" if s["skipped"] else "")
    )
    if s["rms_error_median_m"] is not None:
        lines.append(
            f"key-point RMS error after scaling: median {1e3 * s['rms_error_median_m']:.1f} mm, "
            f"p95 {1e3 * s['rms_error_p95_m']:.1f} mm, max {1e3 * s['rms_error_max_m']:.1f} mm"
        )
    lines.append(
        f"trials with a joint on a limit: {s['trials_touching_limits']}; "
        f"frames with filled markers: {s['frames_filled']}; time {s['timing_s']}"
    )
    return "\n".join(lines)


def report_dict(result: ImportResult, params: ImportParams) -> dict:
    """JSON-ready report: options, summary and one entry per trial."""

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return clean(
        {
            "params": {
                k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(params).items()
            },
            "summary": result.summary(),
            "trials": [asdict(r) for r in result.reports],
        }
    )


# -------------------------------------------------------------------------------------------- CLI


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
        f"built-in {sorted(mk.MARKER_MODELS)} or a YAML file (default: per format)",
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
