"""Human key points (shoulder, elbow, wrist, hand) from labelled 3-D points of a recording.

Park et al. (2008, sec. 2 and 4.1) turn motion-capture markers into joint trajectories with an IK
solver; this module and the two beside it (`calibration`, `frames`) prepare that solver's targets.
Every position reader (Vicon CSV, C3D, BVH, ASF/AMC) returns a `MarkerData`: named points
``(F, M, 3)`` [m], NaN where a marker was not seen. From it:

1. `fill_gaps`: interior gaps of a marker up to ``max_gap`` frames are filled by a cubic spline
   through the frames that were seen; longer gaps make the trial fail (`TrialError`); frames at the
   start or end where a needed marker is missing are trimmed away.
2. `lowpass`: zero-lag Butterworth filter (the usual 6-10 Hz for arm movements), before any
   derivative is taken.
3. A `MarkerModel` says how each key point is made: the mean of some markers (``markers``), a
   landmark seen only in the static calibration trial and carried by a rigid marker cluster
   (``markers`` + ``cluster``: the cluster's least-squares rigid motion, Soderkvist & Wedin 1993,
   moves the landmark), or a functional joint centre between two clusters (``between``: the point
   that moves rigidly with both, SCoRE, Ehrig et al. 2006); `calibration.calibrate` and
   `calibration.keypoints` build them. The built-in models are `MARKER_MODELS`.
4. `frames.body_frames`: the trial's points in a frame that moves with the person, x forward,
   y left, z up (the robot's world convention): its origin is the shoulder (or another reference
   point) in every frame, its heading that of the trunk (`frames.heading_direction`: two trunk
   markers, else the right-left shoulder line), turned about the vertical. A person who steps,
   walks or turns keeps the same arm motion in it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from evojax_motion.errors import UserError

KEYPOINT_CHAIN = ("shoulder", "elbow", "wrist", "hand")  # proximal to distal: the scaled segments
LEFT_SHOULDER = "left_shoulder"  # used only for the body frame's lateral axis
MIN_CLUSTER_MARKERS = 3  # a rigid motion needs three non-collinear points


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
    every frame (`frames.heading_direction`). None, or markers missing from a trial: the shoulder
    line.
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
