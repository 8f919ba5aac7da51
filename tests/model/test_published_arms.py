"""Published arms as a user brings them: MuJoCo Menagerie's Kinova Gen3 (continuous joints 1, 3,
5 and 7) and UFACTORY xArm7, unedited, with a config that names the model file and nothing else.

Every ``demos`` setting takes its default (derived from the model:
`demonstrations.workspace.derive_defaults`);
``demos`` and a 3-generation ``train`` of 40 conditions run at tiny sizes (`configs/tiny.yaml`).
The models live in the folder ``shared/robots`` beside the repository; without it these tests
are skipped.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from evojax_motion.cli.entry import main
from evojax_motion.demonstrations.workspace import derive_defaults
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.database import human_mask, load_database

ROBOTS = Path(__file__).resolve().parents[3] / "shared" / "robots"
TINY = Path(__file__).resolve().parents[2] / "configs" / "tiny.yaml"
CONDITIONS, GENERATIONS = 40, 3
MIN_VALID_FRACTION = 0.9  # of the conditions, with a motion in every generation
LIMIT_TOL = 1e-5  # [rad] float32 rounding at a limit
HUMAN_ONLY_COST_RATIO = 10.0  # the human-only interpolations cost at most this x the database
ARMS = {  # name: (model file, robot section besides mjcf)
    "gen3": ("kinova_gen3/gen3.xml", {}),
    "xarm7_nohand": ("ufactory_xarm7/xarm7_nohand.xml", {}),
}

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not ROBOTS.is_dir(), reason=f"published robot models not found: {ROBOTS} is absent"
    ),
]


def _config(tmp_path: Path, name: str) -> Path:
    """tiny.yaml with the robot section replaced by the published model's file."""
    file, extra = ARMS[name]
    cfg = yaml.safe_load(TINY.read_text())
    cfg["robot"] = {"mjcf": str(ROBOTS / file), **extra}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _inside_limits(robot, q) -> None:
    """Limited joints of ``q (..., J)`` within their range; continuous joints on the rest
    branch (each trajectory's mean within pi of rest)."""
    q = np.asarray(q)
    limited = ~robot.continuous
    assert np.all(q[..., limited] >= robot.lower[limited] - LIMIT_TOL)
    assert np.all(q[..., limited] <= robot.upper[limited] + LIMIT_TOL)
    mean = q[..., robot.continuous].mean(axis=-2)
    assert np.all(np.abs(mean - robot.rest[robot.continuous]) <= np.pi)


@pytest.mark.parametrize("name", ["gen3", "xarm7_nohand"])
def test_demos_and_train_with_only_the_model_file(tmp_path, name, capsys):
    config = _config(tmp_path, name)
    robot = load_robot(ROBOTS / ARMS[name][0])
    demos = tmp_path / "demos.npz"
    status = main(["demos", "--config", str(config), "--out", str(demos)])
    assert status == 0, capsys.readouterr().err
    db, _ = load_database(demos)
    count = yaml.safe_load(config.read_text())["demos"]["count"]
    assert int(human_mask(db).sum()) == count
    _inside_limits(robot, db.q)

    run = tmp_path / "run"
    # BFGS as the paper configs (tiny.yaml's 20 Adam steps converge on none of the problems)
    sets = [f"evolution.conditions={CONDITIONS}", f"evolution.generations={GENERATIONS}"]
    sets += ["compiler.method=bfgs", "compiler.max_iters=null"]
    args = ["train", str(config), "--out", str(run), "--quiet"]
    status = main([*args, *(a for s in sets for a in ("--set", s))])
    err = capsys.readouterr().err
    assert status == 0, err
    assert "over a limit of the robot" in err  # the human rows' count against the limits
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [m["generation"] for m in metrics] == list(range(1, GENERATIONS + 1))
    for m in metrics:
        assert m["n_valid"] >= MIN_VALID_FRACTION * CONDITIONS
    # No joint-limit violation kept: offspring outside the limits are rejected (metrics'
    # n_rejected_limits), every stored motion is inside them.
    final, _ = load_database(run / "db_final.npz")
    _inside_limits(robot, np.asarray(final.q)[np.asarray(final.valid)])
    summary = json.loads((run / "summary.json").read_text())
    assert summary["human_only_cost_mean"] <= HUMAN_ONLY_COST_RATIO * summary["db_cost_gen1"]
    # its report, drawn from the model's meshes (stick figures: no OpenGL needed)
    report = ["report", str(run), "--renderer", "stick", "--snapshots", "2", "--gif-frames", "2"]
    assert main(report) == 0, capsys.readouterr().err
    assert (run / "report" / "report.html").is_file()


def test_the_xarm7_with_its_gripper_gets_a_region_in_front_of_it():
    """xarm7.xml has several sites: the end effector is named (the tool centre point). The
    derived region is centred on the shoulder (link2, on joint 1's axis), in front (+x, where
    the hand rests), and lies farther out than without the gripper."""
    with_hand = derive_defaults(
        load_robot(ROBOTS / "ufactory_xarm7" / "xarm7.xml", end_effector="link_tcp")
    )
    bare = derive_defaults(load_robot(ROBOTS / "ufactory_xarm7" / "xarm7_nohand.xml"))
    for d in (with_hand, bare):
        assert d.region.frame == "link2"
        assert d.region.azimuth_deg == (-40.0, 40.0)
    assert with_hand.region.radius[1] > bare.region.radius[1]
