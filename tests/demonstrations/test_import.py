"""``evojax-motion import`` end to end (evojax_motion.cli.importing,
evojax_motion.demonstrations.mocap.importer).

Real data: the shipped UE ADL sample (Vicon CSV), imported for mahru_arm and arm6, and converted
to C3D; with the published Kinova Gen3 model (continuous joints) from ``shared/robots`` beside
the repository, and the whole UE ADL subset from ``shared/data`` (slow), when they are there.
Synthetic but exactly known motions: BVH and ASF/AMC reaches whose elbow angle the robot must
reproduce (the ASF/AMC one also while the actor walks and turns), and a joint-angle CSV. Bad
input: truncated file, missing marker, long gap, unknown format; the others are imported, the
exit status says so, nothing is half-written.

Every import uses ``chunk=8`` and trials of <= 320 frames, so the IK compiles once per robot.
"""

import argparse
import json
import re
import shutil
from pathlib import Path

import mujoco
import numpy as np
import pytest

from evojax_motion.cli.importing import (
    EXIT_OK,
    EXIT_SKIPPED,
    EXIT_USER_ERROR,
    add_import_parser,
)
from evojax_motion.demonstrations.mocap.c3d_file import write_c3d
from evojax_motion.demonstrations.mocap.import_params import ImportParams
from evojax_motion.demonstrations.mocap.import_report import format_report
from evojax_motion.demonstrations.mocap.importer import import_trials
from evojax_motion.demonstrations.mocap.vicon_csv import read_vicon_csv
from evojax_motion.errors import UserError
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.database import load_database

SAMPLE = Path(__file__).resolve().parents[2] / "evojax_motion" / "data" / "ue_adl_sample"
SHARED = Path(__file__).resolve().parents[3] / "shared"  # beside the repository, if there
GEN3 = SHARED / "robots" / "kinova_gen3" / "gen3.xml"
UE_ADL = SHARED / "data" / "ue_adl"
TOL_RMS_SAMPLE = 0.02  # [m] key-point RMS after scaling, mahru_arm, every real trial
TOL_RMS_ARM6 = 0.05  # [m] arm6 follows wrist and hand only, within its (non-human) workspace
TOL_DURATION = 0.1  # [s] our onset/offset (5 % hand speed) vs the database's (3 % finger speed)
TOL_ANGLE_DEG = 1.5  # the elbow angle survives direction-preserving scaling
TOL_CALIBRATION_DEG = 3.0  # joint angles when the shoulder centre is fitted to other trials
TOL_FK = 1e-5  # [m]
TOL_SAME_RMS = 1e-4  # [m] the same reach imported walking and standing
TOL_SAME_Q = 1e-3  # [rad]
TOL_RMS_DONE = 0.015  # [m] key-point RMS p95, UE ADL onto the Gen3
MIN_IMPORTED_DONE = 0.9  # fraction of the UE ADL trials imported onto the Gen3
CHUNK = 8


def _needs(path: Path, what: str) -> Path:
    if not path.exists():
        pytest.skip(
            f"{what} ({path.relative_to(SHARED.parent)}, beside the repository) is not here"
        )
    return path


def _run(argv):
    """What ``evojax-motion import ...`` does: parse, run, UserError -> exit 2."""
    parser = argparse.ArgumentParser(prog="evojax-motion")
    add_import_parser(parser.add_subparsers(dest="command", required=True))
    try:
        args = parser.parse_args(["import", *argv])
        return args.func(args)
    except UserError as e:
        print(f"error: {e}")
        return EXIT_USER_ERROR
    except SystemExit as e:  # argparse's own errors (exit 2); the CLI's parser raises UserError
        return e.code


def _params(**kw):
    kw.setdefault("format", "vicon-csv")
    kw.setdefault("quiet", True)
    kw.setdefault("chunk", CHUNK)
    return ImportParams(**kw)


# a subset of the sample (two subjects, both tasks): the IK batch is one chunk of 8
SUBSET = tuple(
    str(SAMPLE / f)
    for f in (
        "ADL004/ADL004AR1.csv",
        "ADL004/ADL004AR4.csv",
        "ADL004/ADL004FR1.csv",
        "ADL004/ADL004FR3.csv",
        "ADL009/ADL009FR2.csv",
    )
)


@pytest.fixture(scope="module")
def sample_mahru():
    return import_trials(_params(paths=SUBSET))


def _final_site(robot, q):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[robot.qpos_adr] = q
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[robot.site_id].copy()


def test_sample_imports_for_mahru(sample_mahru):
    res = sample_mahru
    robot = load_robot("mahru_arm")
    assert [r.status for r in res.reports] == ["imported"] * 5, format_report(res)
    assert {Path(r.path).relative_to(SAMPLE).as_posix() for r in res.reports} == {
        "ADL004/ADL004AR1.csv",
        "ADL004/ADL004AR4.csv",
        "ADL004/ADL004FR1.csv",
        "ADL004/ADL004FR3.csv",
        "ADL009/ADL009FR2.csv",
    }
    for r in res.reports:
        assert r.rms_error_m <= TOL_RMS_SAMPLE, (r.name, r.rms_error_m)
        assert set(r.keypoint_rms_m) == {"shoulder", "elbow", "wrist", "hand"}
    db = res.db
    assert db.q.shape == (5, 100, 7)
    assert (db.q >= robot.lower - 1e-6).all() and (db.q <= robot.upper + 1e-6).all()
    for i in range(5):
        np.testing.assert_allclose(db.condition[i], _final_site(robot, db.q[i, -1]), atol=TOL_FK)
    assert np.isfinite(db.cost).all() and (db.cost > 0).all()
    assert res.meta.synthetic is False and res.meta.joint_names == robot.joint_names
    # durations agree with the database's own trimmed angle files (100 Hz)
    for r in res.reports:
        angles = Path(r.path).with_name(Path(r.path).stem + "angles.csv")
        if angles.exists():
            n = len(angles.read_text().strip().splitlines()) - 1
            assert abs(r.duration_s - (n - 1) / 100.0) <= TOL_DURATION, r.name
    # forward reaches end in front of the right shoulder, reaches across end to its left
    fr = [db.condition[i] for i, r in enumerate(res.reports) if "FR" in r.name]
    ar = [db.condition[i] for i, r in enumerate(res.reports) if "AR" in r.name]
    assert min(c[0] for c in fr) > 0.3 and max(c[1] for c in fr) < -0.1
    assert min(c[1] for c in ar) > max(c[1] for c in fr) + 0.1


def test_sample_imports_for_arm6():
    res = import_trials(_params(paths=SUBSET, robot="arm6"))
    robot = load_robot("arm6")
    assert len(res.imported) == 5, format_report(res)
    assert res.meta.joint_names == robot.joint_names and res.db.q.shape[-1] == 6
    q = res.db.q
    assert (q >= robot.lower - 1e-6).all() and (q <= robot.upper + 1e-6).all()
    assert max(r.rms_error_m for r in res.imported) <= TOL_RMS_ARM6
    # arm6's upper arm cannot hang: it matches the hand only, whose targets are lifted above its
    # base (the turret at 0.6 m) and lie in front of it
    assert all(r.keypoint_rms_m["hand"] <= TOL_RMS_ARM6 for r in res.imported)
    for r in res.imported:
        assert r.lift_m > 0 and r.hand_target_box[0][2] >= 0.6 and r.hand_target_box[0][0] > 0


def test_sample_imports_for_the_published_gen3():
    """Kinova Gen3 as published (continuous joints 1, 3, 5, 7; joints named joint_N) imports the
    sample with its defaults: hand targets in front of it and above its base, every primitive's
    continuous joints on the rest posture's branch."""
    from evojax_motion.demonstrations.mocap import retarget as rt

    robot = load_robot(_needs(GEN3, "the published Kinova Gen3 model"))
    res = import_trials(_params(paths=SUBSET, robot=str(GEN3)))
    assert len(res.imported) == 5, format_report(res)
    assert max(r.rms_error_m for r in res.imported) <= TOL_RMS_DONE
    base = rt.base_height(robot)
    for r in res.imported:
        (x0, _, z0), (_, _, z1) = r.hand_target_box
        assert x0 > 0 and z0 >= base + rt.BASE_CLEARANCE - 1e-9, (r.name, r.hand_target_box)
        assert z1 < base + 0.5  # a table-top reach stays low, not lifted far
    cont = robot.continuous
    q = np.asarray(res.db.q)
    mean = q.mean(axis=1)
    assert (np.abs(mean - robot.rest)[:, cont] <= np.pi).all()
    assert (np.abs(np.diff(q, axis=1))[..., cont] < 0.5).all()  # no 2 pi jumps
    for i in range(5):
        np.testing.assert_allclose(
            db_cond := res.db.condition[i], _final_site(robot, q[i, -1]), atol=TOL_FK
        )
        assert db_cond[0] > 0


@pytest.mark.slow
def test_ue_adl_onto_the_published_gen3():
    """The whole UE ADL subset (10 subjects x 2 tasks x 5 trials) onto the unedited Gen3 with
    the defaults (no --weights): >= 90 % imported, key-point RMS p95 <= 15 mm, every hand target
    in front of the robot and above its base."""
    from evojax_motion.demonstrations.mocap import retarget as rt

    robot = load_robot(_needs(GEN3, "the published Kinova Gen3 model"))
    data = _needs(UE_ADL, "the UE ADL data")
    res = import_trials(_params(paths=(str(data),), robot=str(GEN3), chunk=32))
    s = res.summary()
    assert s["imported"] >= MIN_IMPORTED_DONE * s["trials"], format_report(res)
    assert s["rms_error_p95_m"] <= TOL_RMS_DONE
    base = rt.base_height(robot)
    assert all(r.hand_target_box[0][0] > 0 for r in res.imported)
    assert all(r.hand_target_box[0][2] >= base for r in res.imported)
    q0 = np.asarray(res.db.q)[:, 0]
    assert np.ptp(q0[:, robot.continuous], axis=0).max() < np.pi  # one branch


def test_cli_writes_a_loadable_database_and_report(tmp_path, sample_mahru):
    out, rep = tmp_path / "demos.npz", tmp_path / "report.json"
    trial = SAMPLE / "ADL004" / "ADL004FR1.csv"
    argv = [
        "--format",
        "vicon-csv",
        "--robot",
        "mahru_arm",
        "--out",
        str(out),
        "--quiet",
        "--report",
        str(rep),
        str(trial),
    ]
    assert _run(argv) == EXIT_OK
    db, meta = load_database(out)
    assert meta.robot_name == "mahru_arm" and not meta.synthetic
    alone = import_trials(_params(paths=(str(trial),)))
    np.testing.assert_allclose(db.q[0], alone.db.q[0], atol=1e-6)
    np.testing.assert_allclose(db.condition[0], alone.db.condition[0], atol=1e-6)
    # the shoulder centre is calibrated from fewer trials than in the whole sample
    i = [r.name for r in sample_mahru.reports].index("ADL004FR1.csv")
    assert np.abs(db.q[0] - sample_mahru.db.q[i]).max() < np.deg2rad(TOL_CALIBRATION_DEG)
    report = json.loads(rep.read_text())
    assert report["summary"]["imported"] == 1 and report["trials"][0]["status"] == "imported"
    # an existing output needs --force; a user error writes nothing
    assert _run(argv) == EXIT_USER_ERROR
    assert _run(["--format", "xyz", "--out", str(tmp_path / "x.npz"), str(trial)]) == 2
    assert (
        _run(["--format", "vicon-csv", "--out", str(tmp_path / "x.npz"), str(tmp_path / "missing")])
        == EXIT_USER_ERROR
    )
    assert not (tmp_path / "x.npz").exists()


def _copy_with(src: Path, dst: Path, edit):
    lines = src.read_text(encoding="utf-8-sig").splitlines()
    dst.write_text("\n".join(edit(lines)) + "\n")


def _blank(lines, marker, frames):
    names = lines[2].split(",")
    col = next(i for i, n in enumerate(names) if n.endswith(":" + marker))
    out = list(lines)
    for k in frames:
        cells = out[5 + k].split(",")
        cells[col : col + 3] = ["", "", ""]
        out[5 + k] = ",".join(cells)
    return out


def test_bad_trials_are_skipped_with_reasons(tmp_path, sample_mahru):
    src = SAMPLE / "ADL004"
    bad = tmp_path / "ADL004"
    bad.mkdir()
    shutil.copy(src / "ADL004_static.csv", bad)
    # imported after filling a 10-frame gap
    _copy_with(
        src / "ADL004FR1.csv",
        bad / "ADL004FR1.csv",
        lambda ln: _blank(ln, "RUAR2", range(100, 110)),
    )
    # truncated in the middle of a row
    text = (src / "ADL004FR3.csv").read_text(encoding="utf-8-sig")
    (bad / "ADL004FR3.csv").write_text(text[: len(text) * 2 // 3])
    # a required marker missing (renamed)
    _copy_with(
        src / "ADL004AR1.csv",
        bad / "ADL004AR1.csv",
        lambda ln: [ln[0], ln[1], ln[2].replace(":RSHO1,", ":XSHO1,"), *ln[3:]],
    )
    # a gap longer than --max-gap
    _copy_with(
        src / "ADL004AR4.csv", bad / "ADL004AR4.csv", lambda ln: _blank(ln, "RFB", range(100, 140))
    )
    # not a Vicon export, named explicitly
    (tmp_path / "notes.csv").write_text("hello,world\n")
    out = tmp_path / "demos.npz"
    out.write_bytes(b"old")
    argv = [
        "--format",
        "vicon-csv",
        "--out",
        str(out),
        "--force",
        "--quiet",
        "--max-gap",
        "20",
        "--report",
        str(tmp_path / "r.json"),
        str(bad),
        str(tmp_path / "notes.csv"),
    ]
    assert _run(argv) == EXIT_SKIPPED
    full = json.loads((tmp_path / "r.json").read_text())
    assert full["summary"]["skipped_reasons"] == {
        "unreadable file": 2,
        "marker missing": 1,
        "gap too long": 1,
    }
    report = {t["name"]: t for t in full["trials"]}
    assert report["ADL004FR1.csv"]["status"] == "imported"
    assert report["ADL004FR1.csv"]["frames_filled"] == 10
    assert "truncated" in report["ADL004FR3.csv"]["reason"]
    assert "RSHO1 missing" in report["ADL004AR1.csv"]["reason"]
    assert "gap of 40 frames" in report["ADL004AR4.csv"]["reason"]
    assert "Trajectories" in report["notes.csv"]["reason"]
    db, _ = load_database(out)
    assert db.q.shape[0] == 1
    # the filled gap barely changes the trial (the marker moves smoothly); the shoulder centre
    # is calibrated from fewer trials here
    i = [r.name for r in sample_mahru.reports].index("ADL004FR1.csv")
    assert np.abs(db.q[0] - sample_mahru.db.q[i]).max() < np.deg2rad(TOL_CALIBRATION_DEG)
    # nothing importable: exit 2 and the old file stays as it was
    out.write_bytes(b"old")
    argv = [
        "--format",
        "vicon-csv",
        "--out",
        str(out),
        "--force",
        "--quiet",
        str(bad / "ADL004FR3.csv"),
        str(bad / "ADL004AR4.csv"),
    ]
    assert _run(argv) == EXIT_USER_ERROR
    assert out.read_bytes() == b"old"


def test_c3d_import_matches_the_vicon_import(tmp_path):
    folder = tmp_path / "c3d"
    folder.mkdir()
    for name in ("ADL004FR1", "ADL004_static"):
        write_c3d(folder / f"{name}.c3d", read_vicon_csv(SAMPLE / "ADL004" / f"{name}.csv"))
    res = import_trials(_params(format="c3d", paths=(str(folder),)))
    assert len(res.imported) == 1, format_report(res)
    vicon = import_trials(_params(paths=(str(SAMPLE / "ADL004" / "ADL004FR1.csv"),)))
    # same markers up to float32 millimetres in the C3D file
    np.testing.assert_allclose(res.db.q[0], vicon.db.q[0], atol=1e-3)
    assert res.imported[0].rms_error_m == pytest.approx(vicon.imported[0].rms_error_m, abs=1e-5)


# ---------------------------------------------------------------- synthetic skeleton reaches

N_PRE, N_MOVE, N_POST = 100, 100, 100  # frames at 100 Hz


def _reach():
    """Shoulder flexion 10 -> 70 deg, elbow flexion 60 -> 20 deg, minimum jerk over 1 s."""
    n = N_PRE + N_MOVE + N_POST
    s = np.clip((np.arange(n) - N_PRE) / N_MOVE, 0.0, 1.0)
    mj = 10 * s**3 - 15 * s**4 + 6 * s**5
    return 10.0 + 60.0 * mj, 60.0 - 40.0 * mj


def _check_reach(res, theta, phi):
    assert len(res.imported) == 1, format_report(res)
    r = res.imported[0]
    robot = load_robot("mahru_arm")
    off = round((r.onset_s + r.duration_s) * 100)
    q_end = np.rad2deg(res.db.q[0, -1])
    names = robot.joint_names
    assert abs(q_end[names.index("elbow")] - phi[off]) < TOL_ANGLE_DEG
    assert abs(q_end[names.index("shoulder_pitch")] - theta[off]) < 2 * TOL_ANGLE_DEG
    assert abs(q_end[names.index("waist_yaw")]) < TOL_ANGLE_DEG  # the shoulder did not move
    q_start = np.rad2deg(res.db.q[0, 0])
    on = round(r.onset_s * 100)
    assert abs(q_start[names.index("elbow")] - phi[on]) < TOL_ANGLE_DEG
    assert r.rms_error_m < 0.01


def test_bvh_import_reproduces_the_elbow_angle(tmp_path):
    theta, phi = _reach()
    rows = []
    for t, p in zip(theta, phi):
        # root(6) LeftArm(3) RightArm(3: Z X Y) RightForeArm(3) RightHand(3) RightFingerBase(3)
        rows.append(
            " ".join(map(str, [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, -t, 0, 0, -p, 0, 0, 0, 0, 0, 0, 0]))
        )
    rot = "CHANNELS 3 Zrotation Xrotation Yrotation"
    text = (
        f"""HIERARCHY
ROOT Hips
{{
  OFFSET 0 100 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT LeftArm
  {{
    OFFSET 18 45 0
    {rot}
    End Site
    {{
      OFFSET 0 -28 0
    }}
  }}
  JOINT RightArm
  {{
    OFFSET -18 45 0
    {rot}
    JOINT RightForeArm
    {{
      OFFSET 0 -28 0
      {rot}
      JOINT RightHand
      {{
        OFFSET 0 -26 0
        {rot}
        JOINT RightFingerBase
        {{
          OFFSET 0 -9 0
          {rot}
          End Site
          {{
            OFFSET 0 -3 0
          }}
        }}
      }}
    }}
  }}
}}
MOTION
Frames: {len(rows)}
Frame Time: 0.01
"""
        + "\n".join(rows)
        + "\n"
    )
    (tmp_path / "reach.bvh").write_text(text)
    res = import_trials(_params(format="bvh", paths=(str(tmp_path),)))
    _check_reach(res, theta, phi)


def _asf_bone(i, name, direction, length, dof=""):
    d = " ".join(map(str, direction))
    extra = (
        f"\n    dof {dof}\n    limits " + " ".join(["(-180 180)"] * len(dof.split())) if dof else ""
    )
    return (
        f"  begin\n    id {i}\n    name {name}\n    direction {d}\n    length {length}\n"
        f"    axis 0 0 0 XYZ{extra}\n  end\n"
    )


# y up; the clavicles along x (x points to the actor's left), so the actor faces +z
REACH_ASF = (
    ":version 1.10\n:name reach\n:units\n  mass 1.0\n  length 0.45\n  angle deg\n"
    ":root\n  order TX TY TZ RX RY RZ\n  axis XYZ\n  position 0 0 0\n"
    "  orientation 0 0 0\n:bonedata\n"
    + _asf_bone(1, "lclavicle", (1, 0, 0), 7)
    + _asf_bone(2, "rclavicle", (-1, 0, 0), 7)
    + _asf_bone(3, "rhumerus", (0, -1, 0), 11, "rx ry rz")
    + _asf_bone(4, "rradius", (0, -1, 0), 10, "rx")
    + _asf_bone(5, "rwrist", (0, -1, 0), 1)
    + _asf_bone(6, "rhand", (0, -1, 0), 3)
    + _asf_bone(7, "lhipjoint", (1, -4, 0), 4)
    + _asf_bone(8, "rhipjoint", (-1, -4, 0), 4)
    + ":hierarchy\n  begin\n    root lclavicle rclavicle lhipjoint rhipjoint\n"
    "    rclavicle rhumerus\n    rhumerus rradius\n    rradius rwrist\n    rwrist rhand\n  end\n"
)
ASF_UNIT = 0.0254 / 0.45  # [m] per length unit of REACH_ASF


def _reach_amc(theta, phi, root=None) -> str:
    """The reach ``theta``/``phi`` [deg] per frame; root: ``(F, 6)`` TX TY TZ [m] RX RY RZ [deg]
    (None: standing at 40 units height)."""
    if root is None:
        root = np.tile([0.0, 40 * ASF_UNIT, 0.0, 0.0, 0.0, 0.0], (len(theta), 1))
    lines = [":FULLY-SPECIFIED", ":DEGREES"]
    for k, (t, p, r) in enumerate(zip(theta, phi, root), start=1):
        pos = " ".join(f"{v / ASF_UNIT:.6f}" for v in r[:3])
        rot = " ".join(f"{v:.6f}" for v in r[3:])
        lines += [str(k), f"root {pos} {rot}", f"rhumerus {-t} 0 0", f"rradius {-p}"]
    return "\n".join(lines) + "\n"


def test_asf_amc_import_reproduces_the_elbow_angle(tmp_path):
    theta, phi = _reach()
    (tmp_path / "07.asf").write_text(REACH_ASF)
    (tmp_path / "07_01.amc").write_text(_reach_amc(theta, phi))
    res = import_trials(_params(format="asf-amc", paths=(str(tmp_path),), rate=100.0))
    _check_reach(res, theta, phi)


def test_asf_amc_reach_while_walking_imports_as_standing(tmp_path):
    """HDM05-style: the actor, facing 30 deg away from the lab's axes, walks 0.8 m forward and
    bobs 2 cm while the arm reaches. The robot's shoulder is fixed, so its targets are taken
    relative to the person's shoulder and heading (hips): the clip imports with the error, the
    movement and the joint angles of the same reach standing still. Taken in the lab's frame
    (``--reference lab``), the walk moves the shoulder's target 0.8 m and the trial is skipped,
    its reason giving the figures."""
    theta, phi = _reach()
    n = len(theta)
    s = np.arange(n) / (n - 1)
    walk = np.zeros((n, 6))
    facing = np.deg2rad(30.0)  # about the vertical (RY)
    step = 0.8 * (10 * s**3 - 15 * s**4 + 6 * s**5)  # [m] forward, along the facing direction
    walk[:, 0], walk[:, 2] = step * np.sin(facing), step * np.cos(facing)
    walk[:, 1] = 40 * ASF_UNIT + 0.02 * np.sin(2 * np.pi * 3 * s)  # stepping bob [m]
    walk[:, 4] = np.rad2deg(facing)
    (tmp_path / "07.asf").write_text(REACH_ASF)
    (tmp_path / "07_01.amc").write_text(_reach_amc(theta, phi))
    (tmp_path / "07_02.amc").write_text(_reach_amc(theta, phi, walk))
    res = import_trials(_params(format="asf-amc", paths=(str(tmp_path),), rate=100.0))
    assert len(res.imported) == 2, format_report(res)
    stand, walking = res.reports
    assert walking.heading == "markers lhipjoint -> rhipjoint"
    assert abs(walking.rms_error_m - stand.rms_error_m) <= TOL_SAME_RMS
    assert walking.duration_s == pytest.approx(stand.duration_s)
    np.testing.assert_allclose(res.db.q[1], res.db.q[0], atol=TOL_SAME_Q)
    _check_reach(
        import_trials(_params(format="asf-amc", paths=(str(tmp_path / "07_02.amc"),), rate=100.0)),
        theta,
        phi,
    )
    # a root segment as the reference: the pelvis (lhipjoint) carries the shoulder rigidly here,
    # so the targets are the shoulder reference's; a name the recording lacks is the reason
    hip = import_trials(
        _params(format="asf-amc", paths=(str(tmp_path),), rate=100.0, reference="lhipjoint")
    )
    assert len(hip.imported) == 2, format_report(hip)
    np.testing.assert_allclose(hip.db.q, res.db.q, atol=TOL_SAME_Q)
    nope = import_trials(
        _params(format="asf-amc", paths=(str(tmp_path / "07_02.amc"),), rate=100.0, reference="x")
    )
    assert "--reference x: no such marker in the trial" in nope.reports[0].reason
    # the lab frame: the walk is in the shoulder's target
    lab = import_trials(
        _params(format="asf-amc", paths=(str(tmp_path / "07_02.amc"),), rate=100.0, reference="lab")
    )
    r = lab.reports[0]
    assert r.status == "skipped" and r.rms_error_m > 0.05, format_report(lab)
    m = re.fullmatch(
        r"IK error: key-point RMS (\d+) mm > --max-rms 50 mm; largest (\d+) mm at frame (\d+) "
        r"\((\d+\.\d\d) s, (shoulder|elbow|wrist|hand)\)",
        r.reason,
    )
    assert m, r.reason
    assert int(m[1]) == round(1e3 * r.rms_error_m) and int(m[2]) == round(1e3 * r.max_error_m)
    frame = int(m[3])
    assert float(m[4]) == pytest.approx(frame / 100.0, abs=0.006)
    assert round(r.onset_s * 100) <= frame < r.frames  # in the movement
    assert lab.summary()["skipped_reasons"] == {"IK error too large": 1}


def test_angles_csv_import(tmp_path):
    robot = load_robot("mahru_arm")
    rest = np.asarray(robot.rest)
    goal = rest + np.deg2rad([10, 50, 5, 10, -10, 0, 0])
    n = N_PRE + N_MOVE + N_POST
    s = np.clip((np.arange(n) - N_PRE) / N_MOVE, 0.0, 1.0)
    q = rest + np.outer(10 * s**3 - 15 * s**4 + 6 * s**5, goal - rest)
    header = "time," + ",".join(robot.joint_names)
    body = "\n".join(
        f"{k / 100:.2f}," + ",".join(f"{v:.6f}" for v in np.rad2deg(row)) for k, row in enumerate(q)
    )
    (tmp_path / "reach.csv").write_text(header + "\n" + body + "\n")
    res = import_trials(_params(format="angles-csv", paths=(str(tmp_path),), cutoff_hz=None))
    assert len(res.imported) == 1, format_report(res)
    r = res.imported[0]
    assert 0.6 <= r.duration_s <= 0.9  # the 5 %-speed span of a 1 s minimum-jerk reach
    np.testing.assert_allclose(res.db.q[0, -1], goal, atol=0.02 * np.abs(goal - rest).max())
    np.testing.assert_allclose(res.db.condition[0], _final_site(robot, goal), atol=0.01)
    # no matching column: skipped with the reason
    (tmp_path / "other.csv").write_text("time,a,b\n0,1,2\n0.01,1,2\n0.02,1,2\n")
    res = import_trials(_params(format="angles-csv", paths=(str(tmp_path / "other.csv"),)))
    assert res.db is None and "no column is named after a robot joint" in res.reports[0].reason


def test_angles_csv_continuous_joints_land_on_the_rest_branch(tmp_path):
    """Angles of the Gen3's continuous joints recorded whole turns away from its rest posture
    (joint_1 from 2 pi + 0.1, joint_3 from -pi) are imported on the rest posture's branch."""
    robot = load_robot(_needs(GEN3, "the published Kinova Gen3 model"))
    rest = np.asarray(robot.rest)
    n = N_PRE + N_MOVE + N_POST
    s = np.clip((np.arange(n) - N_PRE) / N_MOVE, 0.0, 1.0)
    mj = 10 * s**3 - 15 * s**4 + 6 * s**5
    goal = rest + np.array([0.6, 0.4, 0.3, 0.5, -0.4, 0.3, 0.2])
    q = rest + np.outer(mj, goal - rest)
    turns = np.array([1, 0, -1, 0, 2, 0, -1]) * 2 * np.pi  # continuous joints only
    header = "time," + ",".join(robot.joint_names)
    body = "\n".join(
        f"{k / 100:.2f}," + ",".join(f"{v:.6f}" for v in row) for k, row in enumerate(q + turns)
    )
    (tmp_path / "reach.csv").write_text(header + "\n" + body + "\n")
    res = import_trials(
        _params(
            format="angles-csv",
            paths=(str(tmp_path),),
            robot=str(GEN3),
            cutoff_hz=None,
            angle_unit="rad",
        )
    )
    assert len(res.imported) == 1, format_report(res)
    np.testing.assert_allclose(res.db.q[0, -1], goal, atol=0.02)
    np.testing.assert_allclose(res.db.q[0, 0], rest, atol=0.02)


REACH_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "reach_real.yaml"


def test_reach_real_config_names_the_imported_database():
    from evojax_motion.settings import load_config

    cfg = load_config(REACH_CONFIG)
    assert cfg.demos_file == "runs/reach_real_demos.npz"
    assert cfg.robot.name == "mahru_arm"
    assert cfg.basis.neighbours >= cfg.compiler.n_components + 1  # K components + a constant


@pytest.mark.slow
def test_training_on_the_imported_sample_lowers_the_cost(tmp_path):
    """configs/reach_real.yaml on the shipped sample, shortened: the run completes on real human
    data, a quarter of the conditions or more get a motion within the robot's limits, and
    every slot filled in generation 1 ends at the same or a lower eq. 5 cost, some lower (the
    mean over filled slots may rise as harder conditions fill). T = 32 keeps the compile time
    small."""
    from evojax_motion.run.training import run_training
    from evojax_motion.settings import load_config

    demos = tmp_path / "demos.npz"
    argv = ["--format", "vicon-csv", "--out", str(demos), "--quiet", "--samples", "32"]
    assert _run([*argv, "--chunk", "8", str(SAMPLE)]) == EXIT_OK
    m = 16
    sets = [f"demos_file={demos}", f"evolution.conditions={m}", "evolution.generations=3"]
    cfg = load_config(REACH_CONFIG, [*sets, "train.plots=false"])
    summary = run_training(cfg, tmp_path / "run", progress=False)
    assert summary["n_valid"] >= m // 4  # measured 7 of 16: the rest stay over a limit
    gen1, final = (load_database(tmp_path / "run" / f)[0] for f in ("db_gen1.npz", "db_final.npz"))
    filled = np.asarray(gen1.valid)[-m:]
    before, after = np.asarray(gen1.cost)[-m:][filled], np.asarray(final.cost)[-m:][filled]
    assert filled.any() and np.all(after <= before) and np.any(after < before)
