"""Options of ``evojax-motion import`` (`ImportParams`) and the input formats it reads.

The command's flags (`cli.importing.add_import_parser`) and the Python API
(`importer.import_trials`) take the same `ImportParams`; its defaults are the flags' defaults.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from evojax_motion.errors import UserError

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


@dataclass(frozen=True)
class ImportParams:
    """Options of the import (the CLI's flags; see `cli.importing.add_import_parser` for their
    help)."""

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
