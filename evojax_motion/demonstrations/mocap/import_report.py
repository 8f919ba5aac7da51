"""What an import did: one `TrialReport` per trial, the `ImportResult` of `importer.import_trials`,
the table the command prints (`format_report`) and the JSON report (`report_dict`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from evojax_motion.demonstrations.mocap.import_params import ImportParams


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
