"""Importing real human demonstrations: recordings -> a movement primitive database.

Park et al. (2008, sec. 4.1) build their initial database from captured human motions turned
into joint trajectories by IK. `import_trials` does that for recordings in common formats and any
robot model; the ``evojax-motion import`` command (`cli.importing`) runs it and writes the
database:

    evojax-motion import --format vicon-csv --robot mahru_arm --out demos.npz DATA_DIR

Per trial: read (`vicon_csv`, `c3d_file`, `bvh`, `asf_amc`, `angles_csv`), fill marker gaps up to
``--max-gap`` frames, low-pass filter, build the human key points (`markers`), express them
relative to the person's shoulder (``--reference``) in a frame that turns with the trunk, scale
them to the robot's reach and solve the key-point IK for every frame (`retarget`, one jit for all
trials), keep continuous joints on the rest posture's 2 pi branch (`motion.angles.on_rest_branch`),
cut the movement at hand-speed onset/offset, resample to ``--samples`` T, and take the final hand
position as the condition. Joint-angle CSV files skip the IK (columns map to joints).

A trial that cannot be imported (unreadable or truncated file, a required marker missing, a gap
longer than ``--max-gap``, no movement, IK error above ``--max-rms``) is skipped with its reason and
its figure (e.g. ``IK error: key-point RMS 61 mm > --max-rms 50 mm; largest 89 mm at frame 312
(3.12 s, wrist)``), and the others are imported (`import_report.ImportResult`). The options are an
`import_params.ImportParams`.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evojax_motion.demonstrations.mocap import calibration as cal
from evojax_motion.demonstrations.mocap import frames as fr
from evojax_motion.demonstrations.mocap import markers as mk
from evojax_motion.demonstrations.mocap.import_params import (
    DEFAULT_MARKER_MODEL,
    EXTENSIONS,
    REFERENCES,
    ImportParams,
)
from evojax_motion.demonstrations.mocap.import_report import ImportResult, TrialReport
from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError
from evojax_motion.errors import UserError
from evojax_motion.motion.angles import on_rest_branch
from evojax_motion.settings.demonstrations import IKSettings

PAD_FRAMES = 64  # frame counts are padded to a multiple of this: few distinct jit shapes


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
    calibs: dict[int, cal.Calibration | TrialError | None] = {}
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
        c: cal.Calibration | TrialError | None = None
        try:
            if needs_calibration:
                c = cal.calibrate(model, static_data, [data[i] for i in members])
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
            needed = cal.needed_markers(d, model, calib)
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
            points = cal.keypoints(d, model, calib)
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
        origin, heading = None, fr.Heading(None, None, "fixed (--reference lab)")
    else:
        heading = fr.heading_direction(d, points, model)
        if reference == "shoulder":
            origin = points[next(k for k in mk.KEYPOINT_CHAIN if k in points)]
        elif reference in points:
            origin = points[reference]
        else:
            origin = d.get(reference)
    report.heading = heading.source
    origin, rot = fr.body_frames(points, up, forward, origin, heading.direction)
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
            hits = np.asarray(lim.any(axis=0), bool)  # (J,)
            r.limit_joints = [j for j, hit in zip(robot.joint_names, hits, strict=True) if hit]
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
