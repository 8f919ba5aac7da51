"""Reader of C3D motion-capture files (the biomechanics standard binary format), via ``c3d``.

The `c3d` package (pure Python, MIT; PyPI ``c3d``) parses the header, the parameter section
(``POINT:LABELS``, ``POINT:RATE``, ``POINT:UNITS``) and the frames. A sample whose residual is
negative was not seen by the cameras (C3D's convention) and becomes NaN. Positions are returned in
metres in the lab frame (z up, as Vicon and most C3D writers use; a marker model may say otherwise).
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError

_UNIT_SCALE = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


def read_c3d(path: str | os.PathLike) -> MarkerData:
    """Read the 3-D points of a C3D file. Raises `TrialError` on an unreadable or truncated file."""
    try:
        import c3d
    except ImportError:  # pragma: no cover - a dependency of the package
        raise TrialError("reading C3D needs the 'c3d' package (pip install c3d)") from None
    path = os.fspath(path)
    try:
        with open(path, "rb") as f, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "no analog data" and the like
            reader = c3d.Reader(f)
            labels = [str(s).strip() for s in reader.point_labels]
            rate = float(reader.point_rate)
            expected = int(reader.last_frame) - int(reader.first_frame) + 1
            try:
                units = reader.get("POINT:UNITS").string_value.strip().lower()
            except AttributeError:
                units = "mm"
            frames = [p[:, :4].copy() for _, p, _ in reader.read_frames(copy=True)]
    except TrialError:
        raise
    except Exception as e:  # the library raises struct/Value/Index errors on damaged files
        raise TrialError(f"not a readable C3D file ({type(e).__name__}: {e})") from None
    if not frames:
        raise TrialError("no frames in the C3D file")
    if len(frames) < expected:
        raise TrialError(f"truncated: {len(frames)} of {expected} frames")
    if units not in _UNIT_SCALE:
        raise TrialError(f"POINT:UNITS: expected mm, cm or m, got {units!r}")
    if not rate > 0:
        raise TrialError(f"POINT:RATE must be > 0, got {rate}")
    arr = np.stack(frames).astype(np.float64)  # (F, M, 4): x, y, z, residual
    pos = arr[..., :3] * _UNIT_SCALE[units]
    pos[arr[..., 3] < 0] = np.nan
    labels = [s.split(":")[-1] for s in labels]
    if len(labels) != pos.shape[1]:
        raise TrialError(f"POINT:LABELS has {len(labels)} names for {pos.shape[1]} points")
    return MarkerData(tuple(labels), pos, rate, path, np.array([0.0, 0.0, 1.0]))


def write_c3d(path: str | os.PathLike, data: MarkerData) -> None:
    """Write ``data`` as a C3D file in millimetres (NaN samples marked unseen). For tests and for
    converting other formats; uses the library's writer."""
    import c3d

    writer = c3d.Writer(point_rate=float(data.rate), point_units="mm  ")
    writer.set_point_labels(list(data.names))
    frames = []
    for p in data.positions:
        pts = np.zeros((p.shape[0], 5), np.float32)
        seen = np.isfinite(p).all(axis=1)
        pts[seen, :3] = p[seen] * 1e3
        pts[~seen, 3] = -1.0
        frames.append((pts, np.zeros((0, 0), np.float32)))
    writer.add_frames(frames)
    with open(path, "wb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        writer.write(f)
