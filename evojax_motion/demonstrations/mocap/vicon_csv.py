"""Reader of Vicon Nexus marker exports (CSV, "Trajectories" section).

Layout (Nexus 2.x; the UE ADL database's files):

    Trajectories
    100                                   <- frame rate [Hz]
    ,,Subj:RSHO1,,,Subj:RSHO2,,,...       <- marker names, one per X/Y/Z triple
    Frame,Sub Frame,X,Y,Z,X,Y,Z,...
    ,,mm,mm,mm,...                        <- units
    1,0,129.56,-277.53,354.29,...         <- one row per frame; empty cells = marker not seen

A file may hold other sections (``Devices``, ``Model Outputs``) before or after; only
``Trajectories`` is read. Positions are returned in metres, in the lab frame (Vicon: z up).
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np

from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError

_UNIT_SCALE = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "": 1e-3}
_SECTIONS = ("Trajectories", "Devices", "Model Outputs", "Joints", "Segments")


def read_vicon_csv(path: str | os.PathLike) -> MarkerData:
    """Read the ``Trajectories`` section of a Nexus CSV export. Raises `TrialError` on bad input
    (no such section, a truncated or non-numeric row, unknown units)."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            text = f.read()
        rows = list(csv.reader(io.StringIO(text)))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise TrialError(f"cannot read the file: {e}") from None
    # Nexus ends every line with a newline: a last line without one was cut short
    complete = text.endswith(("\n", "\r"))
    starts = [i for i, r in enumerate(rows) if r and r[0].strip() == "Trajectories"]
    if not starts:
        raise TrialError("not a Vicon Nexus export: no 'Trajectories' section")
    i = starts[0]
    if len(rows) < i + 5:
        raise TrialError("truncated: the Trajectories header is incomplete")
    try:
        rate = float(rows[i + 1][0])
    except (IndexError, ValueError):
        raise TrialError(f"line {i + 2}: expected the frame rate, got {rows[i + 1]!r}") from None
    if not rate > 0:
        raise TrialError(f"line {i + 2}: frame rate must be > 0, got {rate}")
    header, comps, units = rows[i + 2], rows[i + 3], rows[i + 4]
    names = [h.split(":")[-1].strip() for h in header[2::3]]
    while names and names[-1] == "":  # a trailing comma in the header
        names.pop()
    m = len(names)
    ncol = 2 + 3 * m
    if m == 0 or any(not n for n in names):
        raise TrialError(f"line {i + 3}: expected a marker name over every X/Y/Z triple")
    if [c.strip().upper() for c in comps[2:ncol]] != ["X", "Y", "Z"] * m:
        raise TrialError(f"line {i + 4}: expected X,Y,Z columns for each of the {m} markers")
    unit = {u.strip() for u in units[2:ncol]}
    if len(unit) != 1 or next(iter(unit)) not in _UNIT_SCALE:
        raise TrialError(f"line {i + 5}: expected one length unit (mm, cm or m), got {unit}")
    scale = _UNIT_SCALE[next(iter(unit))]

    data = []
    for k in range(i + 5, len(rows)):
        r = rows[k]
        if not r or not any(c.strip() for c in r):
            break  # a blank line ends the section
        if r[0].strip() in _SECTIONS:
            break
        if len(r) < ncol:
            raise TrialError(f"truncated: line {k + 1} has {len(r)} of {ncol} fields")
        if k == len(rows) - 1 and not complete:
            raise TrialError(f"truncated: line {k + 1} does not end with a newline")
        try:
            data.append([float(c) if c.strip() else np.nan for c in r[:ncol]])
        except ValueError:
            raise TrialError(f"line {k + 1}: expected numbers, got {r[:4]!r}...") from None
    if len(data) < 2:
        raise TrialError("no frames in the Trajectories section")
    arr = np.asarray(data, np.float64)
    frames = arr[:, 0]
    if np.isnan(frames).any() or not (np.diff(frames) > 0).all():
        raise TrialError("frame numbers are missing or not increasing")
    # Nexus leaves rows out for frames it did not export: put them back as unseen
    idx = np.round(frames - frames[0]).astype(int)
    pos = np.full((idx[-1] + 1, m, 3), np.nan)
    pos[idx] = arr[:, 2:].reshape(len(arr), m, 3) * scale
    return MarkerData(tuple(names), pos, rate, path, np.array([0.0, 0.0, 1.0]))
