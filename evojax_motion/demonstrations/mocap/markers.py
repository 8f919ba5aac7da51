"""Human key points (shoulder, elbow, wrist, hand) from labelled 3-D points of a recording.

Park et al. (2008, sec. 2 and 4.1) turn motion-capture markers into joint trajectories with an IK
solver; this module prepares that solver's targets. Every position reader (Vicon CSV, C3D, BVH,
ASF/AMC) returns a `MarkerData`: named points ``(F, M, 3)`` [m], NaN where a marker was not seen.
From it:

1. `fill_gaps`: interior gaps of a marker up to ``max_gap`` frames are filled by a cubic spline
   through the frames that were seen; longer gaps make the trial fail (`TrialError`); frames at the
   start or end where a needed marker is missing are trimmed away.
2. `lowpass`: zero-lag Butterworth filter (the usual 6-10 Hz for arm movements), before any
   derivative is taken.
3. A `MarkerModel` says how each key point is made: the mean of some markers (``markers``), a
   landmark seen only in the static calibration trial and carried by a rigid marker cluster
   (``markers`` + ``cluster``: the cluster's least-squares rigid motion, Soderkvist & Wedin 1993,
   moves the landmark), or a functional joint centre between two clusters (``between``: the point
   that moves rigidly with both, SCoRE, Ehrig et al. 2006).
4. `body_frames`: the trial's points in a frame that moves with the person, x forward, y left,
   z up (the robot's world convention): its origin is the shoulder (or another reference point) in
   every frame, its heading that of the trunk (`heading_direction`: two trunk markers, else the
   right-left shoulder line), turned about the vertical. A person who steps, walks or turns keeps
   the same arm motion in it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from evojax_motion.errors import UserError

KEYPOINT_CHAIN = ("shoulder", "elbow", "wrist", "hand")  # proximal to distal: the scaled segments
LEFT_SHOULDER = "left_shoulder"  # used only for the body frame's lateral axis
MIN_HEADING = 1e-3  # [m] a horizontal heading vector shorter than this tells no direction
MIN_CLUSTER_MARKERS = 3  # a rigid motion needs three non-collinear points
SCORE_RCOND = 1e-3  # singular values below this fraction of the largest: direction undetermined


class TrialError(Exception):
    """A problem with one trial's data (unreadable, a marker missing, gaps too long...).

    The importer skips that trial, reports this message as the reason, and imports the others.
    """


class MarkerData(NamedTuple):
    """Labelled points of one recording: ``positions (F, M, 3)`` [m], NaN where unseen.

    names: (M,) labels (subject prefixes such as ``ADL001:`` removed). rate: frames per second.
    source: the file it came from (names the trial in reports). up: the recording's vertical axis,
    a unit (3,) vector in its own coordinates (+z for Vicon/C3D, +y for BVH and ASF/AMC).
    """

    names: tuple[str, ...]
    positions: np.ndarray
    rate: float
    source: str
    up: np.ndarray

    def column(self, name: str) -> int:
        """Column of marker ``name`` in ``positions`` (axis 1)."""
        return self.names.index(name)

    def has(self, name: str) -> bool:
        """The marker is in the file and was seen in at least one frame."""
        return name in self.names and bool(np.isfinite(self.positions[:, self.column(name)]).any())

    def get(self, name: str) -> np.ndarray:
        """(F, 3) positions of one marker."""
        return self.positions[:, self.column(name)]


class AngleData(NamedTuple):
    """Joint angles of one recording: ``angles (F, K)`` [rad] for the columns ``names (K,)``."""

    names: tuple[str, ...]
    angles: np.ndarray
    rate: float
    source: str


def axis_vector(text: str, where: str) -> np.ndarray:
    """``"+z"``, ``"-y"``... -> unit (3,) vector. Raises ``UserError`` naming ``where``."""
    t = str(text).strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    t = t.lstrip("+-")
    if t not in ("x", "y", "z"):
        raise UserError(f"{where}: expected an axis such as +z, -y or x, got {text!r}")
    v = np.zeros(3)
    v["xyz".index(t)] = sign
    return v


# ------------------------------------------------------------------------------------ gaps, filter


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs of True in a 1-D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


class GapReport(NamedTuple):
    frames_filled: int  # frames in which at least one needed marker was interpolated
    trimmed_start: int  # frames dropped at the start (a needed marker not yet seen)
    trimmed_end: int
    longest_gap: int  # longest interior gap filled [frames]


def fill_gaps(
    data: MarkerData, needed: Sequence[str], max_gap: int
) -> tuple[MarkerData, GapReport]:
    """Fill interior gaps of the ``needed`` markers, trim frames where one is missing at the ends.

    Each interior gap of at most ``max_gap`` frames is filled by a cubic spline through all seen
    frames of that marker (smooth, exact at the seen frames). A longer gap inside the kept window
    raises `TrialError`; so does a needed marker that is never seen. Other markers are untouched.
    """
    from scipy.interpolate import CubicSpline

    pos = data.positions.copy()
    n = pos.shape[0]
    idx = [data.column(m) for m in needed]
    seen = np.isfinite(pos[:, idx]).all(axis=-1)  # (F, k)
    for j, name in enumerate(needed):
        if not seen[:, j].any():
            raise TrialError(f"marker {name} is never seen")
    # keep the frames from where every needed marker has appeared to where the first one vanishes
    start = max(int(np.argmax(seen[:, j])) for j in range(len(needed)))
    stop = min(n - int(np.argmax(seen[::-1, j])) for j in range(len(needed)))
    if stop - start < 2:
        raise TrialError("the needed markers are never seen together")
    filled = np.zeros(n, bool)
    longest = 0
    t = np.arange(n)
    for j, name in enumerate(needed):
        s = seen[:, j]
        gaps = [(a, b) for a, b in _runs(~s) if a > 0 and b < n and a < stop and b > start]
        if not gaps:
            continue
        a, b = max(gaps, key=lambda g: g[1] - g[0])
        if b - a > max_gap:
            raise TrialError(
                f"marker {name}: gap of {b - a} frames at {a / data.rate:.2f} s is longer than "
                f"max_gap={max_gap} frames"
            )
        longest = max(longest, b - a)
        spline = CubicSpline(t[s], pos[s, idx[j]], axis=0)
        for a, b in gaps:
            pos[a:b, idx[j]] = spline(t[a:b])
            filled[a:b] = True
    out = data._replace(positions=pos[start:stop])
    return out, GapReport(int(filled[start:stop].sum()), start, n - stop, longest)


def lowpass(x: np.ndarray, rate: float, cutoff_hz: float | None, order: int = 4) -> np.ndarray:
    """Zero-lag Butterworth low-pass along axis 0 (``filtfilt``: the order doubles, no delay).

    ``cutoff_hz`` None or >= Nyquist: returned unchanged. Short signals use a shorter pad.
    """
    from scipy.signal import butter, filtfilt

    if cutoff_hz is None or cutoff_hz <= 0 or cutoff_hz >= 0.5 * rate or x.shape[0] < 4:
        return x
    b, a = butter(order // 2 if order > 2 else order, cutoff_hz / (0.5 * rate))
    padlen = min(3 * max(len(a), len(b)), x.shape[0] - 1)
    return filtfilt(b, a, x, axis=0, padlen=padlen)


# ---------------------------------------------------------------------------------- rigid clusters


def rigid_motion(ref: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion ``cur ~ R @ ref + d`` of a marker cluster (Kabsch / SVD).

    ref: (k, 3) reference positions; cur: (F, k, 3). Returns ``R (F, 3, 3)``, ``d (F, 3)``.
    """
    cr = ref.mean(axis=0)
    cc = cur.mean(axis=1)
    h = np.einsum("ki,fkj->fij", ref - cr, cur - cc[:, None, :])  # (F, 3, 3) cross-covariance
    u, _, vt = np.linalg.svd(h)
    v = np.swapaxes(vt, -1, -2)
    ut = np.swapaxes(u, -1, -2)
    sign = np.sign(np.linalg.det(v @ ut))  # exclude reflections
    diag = np.ones((cur.shape[0], 3))
    diag[:, 2] = sign
    rot = v @ (diag[:, :, None] * ut)
    d = cc - np.einsum("fij,j->fi", rot, cr)
    return rot, d


# --------------------------------------------------------------------------------- marker models


@dataclass(frozen=True)
class KeyPointDef:
    """How one key point is made from markers (exactly one of ``markers`` / ``between``).

    markers: the key point is their mean. cluster: markers rigidly attached to the same segment,
      which carry the ``markers`` from the static trial when the moving trials lack them
      (anatomical landmarks recorded only during calibration).
    between: two clusters; the key point is their functional joint centre.
    """

    markers: tuple[str, ...] = ()
    cluster: tuple[str, ...] = ()
    between: tuple[tuple[str, ...], tuple[str, ...]] | None = None

    def all_markers(self) -> tuple[str, ...]:
        if self.between is not None:
            return (*self.between[0], *self.between[1])
        return (*self.markers, *self.cluster)


@dataclass(frozen=True)
class MarkerModel:
    """Key-point definitions of one marker set. ``up``/``forward``: axes of the recording
    (``"+z"``...); ``forward`` None: from the right-left shoulder line (needs ``left_shoulder``).

    heading: two groups of markers fixed to the trunk (or pelvis); the horizontal direction from
    the first group's mean to the second's turns with the person and turns the body frame in
    every frame (`heading_direction`). None, or markers missing from a trial: the shoulder line.
    """

    name: str
    keypoints: Mapping[str, KeyPointDef]
    up: str | None = None  # None: the reader's convention (MarkerData.up)
    forward: str | None = None
    heading: tuple[tuple[str, ...], tuple[str, ...]] | None = None

    def required(self) -> tuple[str, ...]:
        return tuple(k for k in KEYPOINT_CHAIN if k in self.keypoints)


def _cluster(prefix: str) -> tuple[str, ...]:
    return tuple(f"{prefix}{i}" for i in range(1, 5))


# UE ADL database (Freitas & Scholz 2009 marker set, right arm): epicondyles and styloids are
# recorded in the static trial only, so the upper-arm and forearm clusters carry them; the
# glenohumeral centre is the functional centre of the acromion and upper-arm clusters. The hand
# point is the finger-base marker (RFB, on the knuckles): wrist -> RFB follows the hand's long
# axis within ~10 deg, while the hand cluster's plate sits 30-45 deg dorsal of it.
UE_ADL = MarkerModel(
    name="ue_adl",
    keypoints={
        "shoulder": KeyPointDef(between=(_cluster("RSHO"), _cluster("RUAR"))),
        "elbow": KeyPointDef(markers=("RLEP", "RMEP"), cluster=_cluster("RUAR")),
        "wrist": KeyPointDef(markers=("RSPR", "RSPU"), cluster=_cluster("RLAR")),
        "hand": KeyPointDef(markers=("RFB",), cluster=_cluster("RHAN")),
        LEFT_SHOULDER: KeyPointDef(markers=_cluster("LSHO")),
    },
    # the trunk's heading: left acromion to sternum (the right shoulder moves with the scapula)
    heading=(_cluster("LSHO"), ("STRN",)),
)

# Vicon Plug-in Gait upper body (right arm).
PLUG_IN_GAIT = MarkerModel(
    name="plug_in_gait",
    keypoints={
        "shoulder": KeyPointDef(markers=("RSHO",)),
        "elbow": KeyPointDef(markers=("RELB",)),
        "wrist": KeyPointDef(markers=("RWRA", "RWRB")),
        "hand": KeyPointDef(markers=("RFIN",)),
        LEFT_SHOULDER: KeyPointDef(markers=("LSHO",)),
    },
    heading=(("C7",), ("CLAV",)),
)

# BVH as converted from the CMU database (joint origins; the palm is between wrist and knuckles).
CMU_BVH = MarkerModel(
    name="cmu_bvh",
    keypoints={
        "shoulder": KeyPointDef(markers=("RightArm",)),
        "elbow": KeyPointDef(markers=("RightForeArm",)),
        "wrist": KeyPointDef(markers=("RightHand",)),
        "hand": KeyPointDef(markers=("RightHand", "RightFingerBase")),
        LEFT_SHOULDER: KeyPointDef(markers=("LeftArm",)),
    },
    heading=(("LeftUpLeg",), ("RightUpLeg",)),  # the hip joints: the pelvis's heading
)

# ASF/AMC (CMU, HDM05): a bone's point is its distal end (rclavicle ends at the shoulder).
CMU_ASF = MarkerModel(
    name="cmu_asf",
    keypoints={
        "shoulder": KeyPointDef(markers=("rclavicle",)),
        "elbow": KeyPointDef(markers=("rhumerus",)),
        "wrist": KeyPointDef(markers=("rradius",)),
        "hand": KeyPointDef(markers=("rradius", "rhand")),
        LEFT_SHOULDER: KeyPointDef(markers=("lclavicle",)),
    },
    heading=(("lhipjoint",), ("rhipjoint",)),  # the hip joint centres: the pelvis's heading
)

MARKER_MODELS: dict[str, MarkerModel] = {
    m.name: m for m in (UE_ADL, PLUG_IN_GAIT, CMU_BVH, CMU_ASF)
}


def _str_tuple(x, where: str) -> tuple[str, ...]:
    if isinstance(x, str) or not isinstance(x, (list, tuple)) or not x:
        raise UserError(f"{where}: expected a non-empty list of marker names, got {x!r}")
    return tuple(str(v) for v in x)


def marker_model_from_dict(data: Mapping, where: str) -> MarkerModel:
    """A `MarkerModel` from a mapping (YAML), e.g.::

    up: +z                      # optional
    forward: +y                 # optional; else the right-left shoulder line is used
    heading: [[C7], [CLAV]]     # optional: two trunk marker groups (the trunk's heading)
    keypoints:
      shoulder: {between: [[RSHO1, RSHO2, RSHO3], [RUAR1, RUAR2, RUAR3]]}
      elbow: {markers: [RLEP, RMEP], cluster: [RUAR1, RUAR2, RUAR3]}
      wrist: {markers: [RWRA, RWRB]}
      hand: {markers: [RFIN]}
      left_shoulder: {markers: [LSHO]}
    """
    if not isinstance(data, Mapping):
        raise UserError(f"{where}: expected a mapping with a 'keypoints' section")
    unknown = set(data) - {"name", "up", "forward", "heading", "keypoints"}
    if unknown:
        raise UserError(
            f"{where}: unknown keys {sorted(unknown)}; expected up, forward, heading, keypoints"
        )
    kps = data.get("keypoints")
    if not isinstance(kps, Mapping) or not kps:
        raise UserError(f"{where}: keypoints: expected a mapping of key point definitions")
    allowed = {*KEYPOINT_CHAIN, LEFT_SHOULDER}
    defs = {}
    for name, spec in kps.items():
        w = f"{where}: keypoints.{name}"
        if name not in allowed:
            raise UserError(f"{w}: unknown key point; expected some of {sorted(allowed)}")
        if isinstance(spec, (list, tuple)):
            spec = {"markers": spec}
        if not isinstance(spec, Mapping) or not set(spec) <= {"markers", "cluster", "between"}:
            raise UserError(f"{w}: expected a list of markers or {{markers, cluster, between}}")
        if ("markers" in spec) == ("between" in spec):
            raise UserError(f"{w}: give exactly one of 'markers' and 'between'")
        if "between" in spec:
            b = spec["between"]
            if not isinstance(b, (list, tuple)) or len(b) != 2:
                raise UserError(f"{w}.between: expected two marker clusters")
            a, c = (_str_tuple(x, f"{w}.between") for x in b)
            if min(len(a), len(c)) < MIN_CLUSTER_MARKERS:
                raise UserError(f"{w}.between: each cluster needs >= {MIN_CLUSTER_MARKERS} markers")
            defs[name] = KeyPointDef(between=(a, c))
        else:
            cluster = _str_tuple(spec["cluster"], f"{w}.cluster") if "cluster" in spec else ()
            if cluster and len(cluster) < MIN_CLUSTER_MARKERS:
                raise UserError(f"{w}.cluster: needs >= {MIN_CLUSTER_MARKERS} markers")
            defs[name] = KeyPointDef(
                markers=_str_tuple(spec["markers"], f"{w}.markers"), cluster=cluster
            )
    present = [k for k in KEYPOINT_CHAIN if k in defs]
    if "hand" not in defs or len(present) < 2:
        raise UserError(
            f"{where}: keypoints: needs 'hand' and at least one more of {KEYPOINT_CHAIN}"
        )
    up = data.get("up")
    forward = data.get("forward")
    for key, val in (("up", up), ("forward", forward)):
        if val is not None:
            axis_vector(val, f"{where}: {key}")
    if forward is None and LEFT_SHOULDER not in defs:
        raise UserError(f"{where}: give 'forward' or a 'left_shoulder' key point (body frame)")
    heading = None
    if data.get("heading") is not None:
        h = data["heading"]
        if not isinstance(h, (list, tuple)) or len(h) != 2:
            raise UserError(
                f"{where}: heading: expected two lists of trunk markers, e.g. [[C7], [CLAV]], "
                f"got {h!r}"
            )
        heading = (_str_tuple(h[0], f"{where}: heading"), _str_tuple(h[1], f"{where}: heading"))
    return MarkerModel(
        name=str(data.get("name", Path(where).stem)),
        keypoints=defs,
        up=up,
        forward=forward,
        heading=heading,
    )


def load_marker_model(spec: str | MarkerModel) -> MarkerModel:
    """A built-in model by name (`MARKER_MODELS`) or a YAML file (`marker_model_from_dict`)."""
    if isinstance(spec, MarkerModel):
        return spec
    if spec in MARKER_MODELS:
        return MARKER_MODELS[spec]
    path = Path(spec)
    if not path.is_file():
        raise UserError(
            f"--marker-model: {spec!r} is neither a built-in model {sorted(MARKER_MODELS)} nor a "
            "YAML file"
        )
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise UserError(f"{path}: cannot read the marker model: {e}") from None
    return marker_model_from_dict(data, str(path))


# ------------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class Calibration:
    """Per-subject calibration: reference cluster shapes and points carried by them.

    clusters: cluster (marker names) -> (k, 3) reference positions [m].
    landmarks: key point name -> (cluster, (3,) position in the reference frame of the cluster).
    joint_centres: key point name -> (3,) centre in the reference frame of its first cluster.
    source: the static trial (or first moving trial) the references come from.
    """

    clusters: Mapping[tuple[str, ...], np.ndarray]
    landmarks: Mapping[str, tuple[tuple[str, ...], np.ndarray]]
    joint_centres: Mapping[str, np.ndarray]
    residual: Mapping[str, float]  # RMS mismatch of a joint centre between its clusters [m]
    source: str


def _mean_seen(data: MarkerData, names: Sequence[str]) -> np.ndarray | None:
    """(k, 3) mean positions over the frames where all ``names`` are seen; None if never."""
    if not all(n in data.names for n in names):
        return None
    p = data.positions[:, [data.column(n) for n in names]]
    ok = np.isfinite(p).all(axis=(1, 2))
    return p[ok].mean(axis=0) if ok.any() else None


def calibrate(
    model: MarkerModel, static: MarkerData | None, moving: Sequence[MarkerData]
) -> Calibration:
    """Reference clusters, landmarks and functional joint centres of one subject.

    References come from the static trial (mean over its frames) or, without one, from the first
    moving trial's first complete frame. Landmarks need the static trial. A functional centre
    solves, over every frame ``t`` of the moving trials (and the static trial),
    ``R_a(t) c_a + d_a(t) = R_b(t) c_b + d_b(t)`` for ``c_a``, ``c_b`` in the least-squares sense
    (SCoRE); directions the motion leaves undetermined fall back to the midpoint of the clusters.
    Raises `TrialError` when a cluster is never seen.
    """
    clusters: dict[tuple[str, ...], np.ndarray] = {}
    ref_source = static.source if static is not None else (moving[0].source if moving else "")

    def reference(names: tuple[str, ...]) -> np.ndarray:
        if names not in clusters:
            r = _mean_seen(static, names) if static is not None else None
            for m in moving:
                if r is not None:
                    break
                if all(n in m.names for n in names):
                    p = m.positions[:, [m.column(n) for n in names]]
                    ok = np.flatnonzero(np.isfinite(p).all(axis=(1, 2)))
                    r = p[ok[0]] if ok.size else None
            if r is None:
                raise TrialError(f"cluster {list(names)} is never seen")
            clusters[names] = r
        return clusters[names]

    landmarks, centres, residual = {}, {}, {}
    for name, kp in model.keypoints.items():
        if kp.between is not None:
            a, b = kp.between
            ra, rb = reference(a), reference(b)
            centres[name], residual[name] = _functional_centre(
                ra, rb, a, b, [*([static] if static is not None else []), *moving]
            )
        elif kp.cluster:
            lm = _mean_seen(static, kp.markers) if static is not None else None
            if lm is not None:
                reference(kp.cluster)
                landmarks[name] = (kp.cluster, lm.mean(axis=0))
    return Calibration(clusters, landmarks, centres, residual, ref_source)


def _cluster_frames(data: MarkerData, names: Sequence[str]) -> np.ndarray:
    p = data.positions[:, [data.column(n) for n in names]]
    return p


def _functional_centre(ra, rb, a, b, trials: Sequence[MarkerData]) -> tuple[np.ndarray, float]:
    """SCoRE centre of clusters ``a``/``b`` (reference shapes ``ra``/``rb``) over ``trials``."""
    rows, rhs = [], []
    for t in trials:
        if not all(n in t.names for n in (*a, *b)):
            continue
        pa, pb = _cluster_frames(t, a), _cluster_frames(t, b)
        ok = np.isfinite(pa).all(axis=(1, 2)) & np.isfinite(pb).all(axis=(1, 2))
        if ok.sum() < 2:
            continue
        rot_a, da = rigid_motion(ra, pa[ok])
        rot_b, db = rigid_motion(rb, pb[ok])
        rows.append(np.concatenate([rot_a, -rot_b], axis=2).reshape(-1, 6))
        rhs.append((db - da).reshape(-1))
    if not rows:
        raise TrialError(f"clusters {list(a)} and {list(b)} are never seen together")
    m, y = np.concatenate(rows), np.concatenate(rhs)
    prior = 0.5 * (ra.mean(axis=0) + rb.mean(axis=0))
    x0 = np.concatenate([prior, prior])
    delta, *_ = np.linalg.lstsq(m, y - m @ x0, rcond=SCORE_RCOND)
    x = x0 + delta
    res = (m @ x - y).reshape(-1, 3)
    return x[:3], float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


def keypoints(
    data: MarkerData, model: MarkerModel, calib: Calibration | None
) -> dict[str, np.ndarray]:
    """Key point trajectories ``name -> (F, 3)`` [m] of a gap-filled trial.

    Raises `TrialError` naming the first marker that is missing and cannot be reconstructed.
    """
    out = {}
    for name, kp in model.keypoints.items():
        if kp.between is not None:
            if calib is None or name not in calib.joint_centres:
                raise TrialError(f"{name}: no calibration for the functional joint centre")
            a = kp.between[0]
            missing = [m for m in a if not data.has(m)]
            if missing:
                raise TrialError(f"required marker {missing[0]} missing ({name})")
            rot, d = rigid_motion(calib.clusters[a], _cluster_frames(data, a))
            out[name] = np.einsum("fij,j->fi", rot, calib.joint_centres[name]) + d
            continue
        missing = [m for m in kp.markers if not data.has(m)]
        if not missing:
            out[name] = np.mean([data.get(m) for m in kp.markers], axis=0)
            continue
        if not kp.cluster:
            raise TrialError(f"required marker {missing[0]} missing ({name})")
        if calib is None or name not in calib.landmarks:
            raise TrialError(
                f"required marker {missing[0]} missing ({name}) and no static trial holds it"
            )
        lost = [m for m in kp.cluster if not data.has(m)]
        if lost:
            raise TrialError(f"required marker {lost[0]} missing ({name} cluster)")
        cluster, point = calib.landmarks[name]
        rot, d = rigid_motion(calib.clusters[cluster], _cluster_frames(data, cluster))
        out[name] = np.einsum("fij,j->fi", rot, point) + d
    return out


def needed_markers(data: MarkerData, model: MarkerModel, calib: Calibration | None) -> list[str]:
    """The markers of ``data`` that the key points will read (gap filling applies to these)."""
    names: list[str] = []
    for name, kp in model.keypoints.items():
        if kp.between is not None:
            use = kp.between[0]
        elif all(data.has(m) for m in kp.markers) or not kp.cluster:
            use = kp.markers
        elif calib is not None and name in calib.landmarks:
            use = kp.cluster
        else:
            use = kp.markers
        names.extend(m for m in use if m not in names)
    missing = [m for m in names if m not in data.names or not data.has(m)]
    if missing:
        raise TrialError(f"required marker {missing[0]} missing")
    return names


def body_frame(
    points: Mapping[str, np.ndarray], up: np.ndarray, forward: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Trunk frame of a trial's first frame: ``(origin (3,), rot (3, 3))``; ``rot @ (p - origin)``
    gives coordinates x forward, y left, z up. Origin: the shoulder (or first key point)."""
    first = next(k for k in KEYPOINT_CHAIN if k in points)
    origin = points[first][0]
    up = up / np.linalg.norm(up)
    if forward is None:
        right = points[first][0] - points[LEFT_SHOULDER][0]
    else:
        right = np.cross(forward, up)
    right = right - up * (right @ up)
    norm = np.linalg.norm(right)
    if not math.isfinite(norm) or norm < 1e-6:
        raise TrialError(
            f"cannot tell left from right: the shoulder line's horizontal part is "
            f"{1e3 * norm:.2f} mm in the first frame"
        )
    right /= norm
    fwd = np.cross(up, right)
    left = -right
    return origin, np.stack([fwd, left, up])


class Heading(NamedTuple):
    """What turns a trial's body frame (`heading_direction`).

    direction: (F, 3) a vector that turns with the trunk, or None (the frame does not turn).
    centre: (F, 3) the mean of the trunk markers it comes from, or None (from the shoulders).
    source: in words, for the report.
    """

    direction: np.ndarray | None
    centre: np.ndarray | None
    source: str


def heading_direction(
    data: MarkerData, points: Mapping[str, np.ndarray], model: MarkerModel
) -> Heading:
    """The trunk's heading: the model's `MarkerModel.heading` markers when the trial has them in
    every frame (gap-filled as the key points' markers are); else the shoulder line (shoulder -
    left shoulder) when the model has a left shoulder; else none (the recording's ``forward``
    axis, fixed).
    """
    if model.heading is not None:
        names = [*model.heading[0], *model.heading[1]]
        if all(n in data.names for n in names):
            a = np.mean([data.get(n) for n in model.heading[0]], axis=0)
            b = np.mean([data.get(n) for n in model.heading[1]], axis=0)
            if np.isfinite(b - a).all():
                centre = np.mean([data.get(n) for n in names], axis=0)
                source = f"markers {'+'.join(model.heading[0])} -> {'+'.join(model.heading[1])}"
                return Heading(b - a, centre, source)
    if model.forward is None and LEFT_SHOULDER in points:
        first = next(k for k in KEYPOINT_CHAIN if k in points)
        return Heading(points[first] - points[LEFT_SHOULDER], None, "shoulder line")
    return Heading(None, None, "fixed")


def heading_turn(direction: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``(F,)`` [rad] how far ``direction (F, 3)`` has turned about ``up`` since frame 0
    (counter-clockwise seen from above positive), unwrapped. Its tilt out of the horizontal does
    not count. Raises `TrialError` when it points (nearly) straight up in some frame."""
    up = up / np.linalg.norm(up)
    flat = direction - np.outer(direction @ up, up)
    norm = np.linalg.norm(flat, axis=-1)
    if not (norm > MIN_HEADING).all():
        frame = int(np.argmin(np.where(np.isfinite(norm), norm, -1.0)))
        raise TrialError(
            f"cannot tell the trunk's heading at frame {frame}: its horizontal part is "
            f"{1e3 * norm[frame]:.1f} mm < {1e3 * MIN_HEADING:.0f} mm"
        )
    d0 = flat[0]
    sin = np.cross(d0, flat) @ up
    cos = flat @ d0
    return np.unwrap(np.arctan2(sin, cos))


def body_frames(
    points: Mapping[str, np.ndarray],
    up: np.ndarray,
    forward: np.ndarray | None,
    origin: np.ndarray | None = None,
    heading: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Body frames of every frame of a trial: ``(origin (F, 3), rot (F, 3, 3))``; ``rot[t] @
    (p[t] - origin[t])`` gives coordinates x forward, y left, z up that move with the person.

    Frame 0 is `body_frame`; frame ``t`` is it turned about ``up`` by `heading_turn` of
    ``heading (F, 3)`` (None: not turned). origin: ``(F, 3)`` the reference point in every frame
    (None: frame 0's shoulder in every frame, a frame fixed in the lab).
    """
    o0, rot0 = body_frame(points, up, forward)
    first = next(iter(points.values()))
    n = first.shape[0]
    origin = np.broadcast_to(o0, (n, 3)) if origin is None else np.asarray(origin)
    if heading is None:
        return origin, np.broadcast_to(rot0, (n, 3, 3))
    turn = heading_turn(heading, up)
    u = up / np.linalg.norm(up)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    s, c = np.sin(turn)[:, None, None], np.cos(turn)[:, None, None]
    turned = np.eye(3) + s * k + (1.0 - c) * (k @ k)  # (F, 3, 3) Rodrigues: turn about up
    return origin, rot0 @ np.swapaxes(turned, -1, -2)
