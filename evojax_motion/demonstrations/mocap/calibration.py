"""Key points from markers: per-subject calibration (`calibrate`) and key point trajectories of a
trial (`keypoints`), as its `markers.MarkerModel` defines them.

A landmark seen only in the static calibration trial is carried by a rigid marker cluster (the
cluster's least-squares rigid motion, `rigid_motion`, Soderkvist & Wedin 1993); a functional joint
centre is the point that moves rigidly with two clusters (SCoRE, Ehrig et al. 2006).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from evojax_motion.demonstrations.mocap.markers import MarkerData, MarkerModel, TrialError

SCORE_RCOND = 1e-3  # singular values below this fraction of the largest: direction undetermined


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
