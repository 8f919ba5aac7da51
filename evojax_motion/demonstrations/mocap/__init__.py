"""Real human demonstrations: motion-capture readers, retargeting to any robot, the importer.

See docs/importing.md. Readers return `MarkerData` (named points) or `AngleData` (joint angles);
`retarget` scales the human to the robot and solves the key-point IK; `importer.run_import` is the
``evojax-motion import`` command.
"""

from evojax_motion.demonstrations.mocap.angles_csv import read_angles_csv
from evojax_motion.demonstrations.mocap.asf_amc import read_amc, read_asf, read_asf_amc
from evojax_motion.demonstrations.mocap.bvh import read_bvh
from evojax_motion.demonstrations.mocap.c3d_file import read_c3d, write_c3d
from evojax_motion.demonstrations.mocap.importer import (
    FORMATS,
    ImportParams,
    ImportResult,
    add_import_parser,
    import_trials,
    run_import,
)
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
    "add_import_parser",
    "import_trials",
    "load_marker_model",
    "read_amc",
    "read_angles_csv",
    "read_asf",
    "read_asf_amc",
    "read_bvh",
    "read_c3d",
    "read_vicon_csv",
    "run_import",
    "write_c3d",
]
