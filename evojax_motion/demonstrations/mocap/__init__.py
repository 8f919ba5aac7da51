"""Real human demonstrations: motion-capture readers, retargeting to any robot, the importer.

See docs/importing.md. Readers return `MarkerData` (named points) or `AngleData` (joint angles);
`retarget` scales the human to the robot and solves the key-point IK; `importer.import_trials`
imports whole trials (`import_params.ImportParams` in, `import_report.ImportResult` out). The
``evojax-motion import`` command is `cli.importing`.
"""

from evojax_motion.demonstrations.mocap.angles_csv import read_angles_csv
from evojax_motion.demonstrations.mocap.asf_amc import read_amc, read_asf, read_asf_amc
from evojax_motion.demonstrations.mocap.bvh import read_bvh
from evojax_motion.demonstrations.mocap.c3d_file import read_c3d, write_c3d
from evojax_motion.demonstrations.mocap.import_params import FORMATS, ImportParams
from evojax_motion.demonstrations.mocap.import_report import ImportResult
from evojax_motion.demonstrations.mocap.importer import import_trials
from evojax_motion.demonstrations.mocap.markers import (
    MARKER_MODELS,
    AngleData,
    MarkerData,
    MarkerModel,
    TrialError,
    load_marker_model,
)
from evojax_motion.demonstrations.mocap.vicon_csv import read_vicon_csv

__all__ = [
    "FORMATS",
    "MARKER_MODELS",
    "AngleData",
    "ImportParams",
    "ImportResult",
    "MarkerData",
    "MarkerModel",
    "TrialError",
    "import_trials",
    "load_marker_model",
    "read_amc",
    "read_angles_csv",
    "read_asf",
    "read_asf_amc",
    "read_bvh",
    "read_c3d",
    "read_vicon_csv",
    "write_c3d",
]
