"""Motion-capture readers and marker processing (evojax_motion.demonstrations.mocap: readers,
markers).

Real files: the shipped UE ADL sample (Vicon Nexus CSV, processed angle CSV). Other formats: tiny
valid files written here (BVH, ASF/AMC, angle CSV; C3D through the ``c3d`` library's writer) whose
forward kinematics is worked out by hand in the comments.
"""

import csv
from pathlib import Path

import numpy as np
import pytest

from evojax_motion.demonstrations.mocap import calibration as cal
from evojax_motion.demonstrations.mocap import frames as fr
from evojax_motion.demonstrations.mocap import markers as mk
from evojax_motion.demonstrations.mocap.angles_csv import (
    AngleSource,
    angles_to_robot,
    load_angle_map,
    read_angles_csv,
)
from evojax_motion.demonstrations.mocap.asf_amc import read_amc, read_asf, read_asf_amc
from evojax_motion.demonstrations.mocap.bvh import read_bvh
from evojax_motion.demonstrations.mocap.c3d_file import read_c3d, write_c3d
from evojax_motion.demonstrations.mocap.markers import MarkerData, TrialError
from evojax_motion.demonstrations.mocap.vicon_csv import read_vicon_csv
from evojax_motion.errors import UserError

SAMPLE = Path(__file__).resolve().parents[2] / "evojax_motion" / "data" / "ue_adl_sample"
TRIAL = SAMPLE / "ADL004" / "ADL004FR1.csv"
STATIC = SAMPLE / "ADL004" / "ADL004_static.csv"
TOL_POS = 1e-9  # [m] float64 parsing / exact kinematics
TOL_C3D = 1e-6  # [m] C3D stores float32 millimetres
TOL_FILL = 1e-4  # [m] cubic-spline fill of a smooth 5-frame gap
TOL_SCORE = 1e-8  # [m] functional joint centre from noise-free rigid motion


# ------------------------------------------------------------------------------- Vicon Nexus CSV


def _raw_rows(path):
    with open(path, encoding="utf-8-sig", newline="") as f:
        return list(csv.reader(f))


def test_vicon_csv_reads_the_real_sample():
    d = read_vicon_csv(TRIAL)
    rows = _raw_rows(TRIAL)
    assert d.rate == 100.0
    assert len(d.names) == 29 and d.names[:2] == ("RSHO1", "RSHO2")
    assert d.positions.shape == (len([r for r in rows[5:] if r]), 29, 3)
    # mm -> m, column by column, against the raw text
    first = rows[5]
    i = d.column("RFB")
    expect = np.array([float(x) for x in first[2 + 3 * i : 5 + 3 * i]]) / 1000.0
    np.testing.assert_allclose(d.positions[0, i], expect, atol=TOL_POS)
    # landmarks recorded only in the static trial are empty here, present there
    assert not d.has("RLEP") and d.has("RSHO1")
    assert read_vicon_csv(STATIC).has("RLEP")
    np.testing.assert_array_equal(d.up, [0.0, 0.0, 1.0])


def test_vicon_csv_truncated_and_foreign_files_are_trial_errors(tmp_path):
    text = TRIAL.read_text(encoding="utf-8-sig")
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: len(text) // 2])  # ends in the middle of a row
    with pytest.raises(TrialError, match="truncated"):
        read_vicon_csv(cut)
    header_only = tmp_path / "header.csv"
    header_only.write_text("\n".join(text.splitlines()[:3]))
    with pytest.raises(TrialError, match="truncated"):
        read_vicon_csv(header_only)
    other = tmp_path / "angles.csv"
    other.write_text("a,b\n1,2\n")
    with pytest.raises(TrialError, match="Trajectories"):
        read_vicon_csv(other)
    bad = tmp_path / "bad.csv"
    lines = text.splitlines()
    lines[7] = lines[7].replace(",", ",x", 1)
    bad.write_text("\n".join(lines))
    with pytest.raises(TrialError, match="expected numbers"):
        read_vicon_csv(bad)


# ------------------------------------------------------------------------------------------ C3D


def test_c3d_round_trip_through_the_library_writer(tmp_path):
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1.0, 1.0, (120, 3, 3))
    pos[40:45, 1] = np.nan  # unseen samples
    data = MarkerData(("RSHO", "RELB", "RFIN"), pos, 120.0, "x", np.array([0.0, 0.0, 1.0]))
    path = tmp_path / "t.c3d"
    write_c3d(path, data)
    back = read_c3d(path)
    assert back.names == data.names and back.rate == 120.0
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(pos))
    np.testing.assert_allclose(back.positions, pos, atol=TOL_C3D)


def test_c3d_truncated_is_a_trial_error(tmp_path):
    pos = np.zeros((300, 4, 3))
    path = tmp_path / "t.c3d"
    write_c3d(path, MarkerData(tuple("abcd"), pos, 100.0, "", np.zeros(3)))
    raw = path.read_bytes()
    for n in (len(raw) // 2, 700):
        (tmp_path / "cut.c3d").write_bytes(raw[:n])
        with pytest.raises(TrialError):
            read_c3d(tmp_path / "cut.c3d")


# ------------------------------------------------------------------------------------------ BVH

BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT RightArm
  {
    OFFSET -20 40 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT RightForeArm
    {
      OFFSET -30 0 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET -25 0 0
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.01
0 0 0 0 0 0 0 0 0 0 0 0
10 0 0 90 0 0 0 0 0 0 0 90
0 0 0 0 0 0 0 0 0 90 90 0
"""


def test_bvh_forward_kinematics_by_hand(tmp_path):
    path = tmp_path / "t.bvh"
    path.write_text(BVH)
    d = read_bvh(path)  # centimetres -> metres
    assert d.names == ("Hips", "RightArm", "RightForeArm", "RightForeArm_end")
    assert d.rate == pytest.approx(100.0)
    np.testing.assert_array_equal(d.up, [0.0, 1.0, 0.0])
    cm = 0.01
    # frame 0: offsets add up
    np.testing.assert_allclose(
        d.positions[0] / cm, [[0, 0, 0], [-20, 40, 0], [-50, 40, 0], [-75, 40, 0]], atol=TOL_POS
    )
    # frame 1: root at x=10 turned 90 deg about z; forearm turned 90 deg about its y:
    # arm = (10,0,0) + Rz90 (-20,40,0) = (-30,-20,0); forearm = arm + Rz90 (-30,0,0) = (-30,-50,0);
    # end = forearm + Rz90 Ry90 (-25,0,0) = forearm + Rz90 (0,0,25) = (-30,-50,25)
    np.testing.assert_allclose(
        d.positions[1] / cm, [[10, 0, 0], [-30, -20, 0], [-30, -50, 0], [-30, -50, 25]], atol=1e-9
    )
    # frame 2: channels compose in their order, Rz then Rx (intrinsic):
    # end = forearm + Rz90 Rx90 (-25,0,0) = forearm + (0,-25,0)   (Rx90 Rz90 would give (0,0,-25))
    np.testing.assert_allclose(d.positions[2, 3] / cm, [-50, 15, 0], atol=1e-9)


def test_bvh_truncated_is_a_trial_error(tmp_path):
    path = tmp_path / "t.bvh"
    path.write_text(BVH[: BVH.index("10 0 0 90")])
    with pytest.raises(TrialError, match="truncated"):
        read_bvh(path)
    path.write_text(BVH[:100])
    with pytest.raises(TrialError):
        read_bvh(path)


# -------------------------------------------------------------------------------------- ASF/AMC

ASF = """# test skeleton
:version 1.10
:name test
:units
  mass 1.0
  length 1.0
  angle deg
:root
  order TX TY TZ RX RY RZ
  axis XYZ
  position 0 0 0
  orientation 0 0 0
:bonedata
  begin
    id 1
    name rclavicle
    direction -1 0 0
    length 10
    axis 0 0 0 XYZ
  end
  begin
    id 2
    name rhumerus
    direction 0 -1 0
    length 12
    axis 0 0 90 XYZ
    dof rx ry rz
    limits (-180 180)
           (-180 180)
           (-180 180)
  end
  begin
    id 3
    name rradius
    direction 0 -1 0
    length 11
    axis 0 0 0 XYZ
    dof rx
    limits (-180 180)
  end
:hierarchy
  begin
    root rclavicle
    rclavicle rhumerus
    rhumerus rradius
  end
"""

AMC = """:FULLY-SPECIFIED
:DEGREES
1
root 0 0 0 0 0 0
rhumerus 0 0 0
rradius 0
2
root 1 2 3 0 90 0
rhumerus 90 0 0
rradius 90
"""


def test_asf_amc_forward_kinematics_by_hand(tmp_path):
    (tmp_path / "s.asf").write_text(ASF)
    (tmp_path / "m.amc").write_text(AMC)
    d = read_asf_amc(tmp_path / "m.amc", tmp_path / "s.asf", rate=120.0)
    inch = 0.0254  # ":units length 1.0": lengths in inches
    assert d.names == ("root", "rclavicle", "rhumerus", "rradius")
    np.testing.assert_allclose(
        d.positions[0] / inch, [[0, 0, 0], [-10, 0, 0], [-10, -12, 0], [-10, -23, 0]], atol=1e-9
    )
    # frame 2: root at (1,2,3) turned Ry90; clavicle end = root + Ry90 (-10,0,0) = (1,2,13).
    # humerus: C = Rz90, M = Rx90 -> R = Ry90 (Rz90 Rx90 Rz90^T) = Ry90 Ry90 = Ry180;
    # end = (1,2,13) + Ry180 (0,-12,0) = (1,-10,13).
    # radius: R = Ry180 Rx90; end = (1,-10,13) + Ry180 Rx90 (0,-11,0)
    #   = (1,-10,13) + Ry180 (0,0,-11) = (1,-10,24)
    np.testing.assert_allclose(
        d.positions[1] / inch, [[1, 2, 3], [1, 2, 13], [1, -10, 13], [1, -10, 24]], atol=1e-9
    )
    assert d.rate == 120.0


def test_asf_amc_bad_input(tmp_path):
    (tmp_path / "s.asf").write_text(ASF)
    sk = read_asf(tmp_path / "s.asf")
    (tmp_path / "cut.amc").write_text(AMC[: AMC.index("rradius 90")])
    with pytest.raises(TrialError, match="truncated"):
        read_amc(tmp_path / "cut.amc", sk)
    (tmp_path / "bad.asf").write_text(ASF.replace("rclavicle rhumerus", "rclavicle"))
    with pytest.raises(TrialError, match="hierarchy"):
        read_asf(tmp_path / "bad.asf")


# ------------------------------------------------------------------------------ joint-angle CSV


def test_angles_csv_reads_the_real_processed_file():
    path = SAMPLE / "ADL004" / "ADL004FR1angles.csv"
    d = read_angles_csv(path, rate=100.0)
    raw = np.genfromtxt(path, delimiter=",", skip_header=1)
    assert d.names[0] == "Finger Velocity" and d.names[7] == "elbow flexion-extension"
    np.testing.assert_allclose(d.angles, np.deg2rad(raw), atol=1e-12)
    with pytest.raises(TrialError, match="rate"):
        read_angles_csv(path)  # no time column, no rate


def test_angles_csv_time_column_mapping_and_errors(tmp_path):
    path = tmp_path / "a.csv"
    t = np.arange(5) / 50.0
    path.write_text("time,elbow,flex\n" + "".join(f"{x},{10 * i},{-i}\n" for i, x in enumerate(t)))
    d = read_angles_csv(path)
    assert d.rate == pytest.approx(50.0) and d.names == ("elbow", "flex")
    joints = ("shoulder", "elbow", "wrist")
    rest = np.array([0.1, 0.2, 0.3])
    q, unmatched = angles_to_robot(d, joints, rest)
    assert unmatched == ("shoulder", "wrist")
    np.testing.assert_allclose(q[:, 1], np.deg2rad(10 * np.arange(5)), atol=1e-12)
    np.testing.assert_allclose(q[:, [0, 2]], np.tile([0.1, 0.3], (5, 1)))
    amap = {"wrist": AngleSource("flex", -2.0, 0.5)}
    q, _ = angles_to_robot(d, joints, rest, amap)
    np.testing.assert_allclose(q[:, 2], -2.0 * np.deg2rad(-np.arange(5)) + 0.5, atol=1e-12)
    (tmp_path / "map.yaml").write_text("wrist: {column: flex, scale: -2, offset_deg: 10}\n")
    assert load_angle_map(tmp_path / "map.yaml")["wrist"] == AngleSource(
        "flex", -2.0, pytest.approx(np.deg2rad(10.0))
    )
    with pytest.raises(TrialError, match="missing"):
        angles_to_robot(d, joints, rest, {"wrist": AngleSource("nope")})
    path.write_text("time,elbow\n0,1\n0.02,2\n0.04")
    with pytest.raises(TrialError, match="truncated"):
        read_angles_csv(path)


# ----------------------------------------------------------------------------- gaps, clusters


def _smooth_markers(n=100, m=2):
    t = np.arange(n)[:, None, None] / 100.0
    pos = np.concatenate([np.sin(2 * t + k) * [1.0, 0.5, 0.2] for k in range(m)], axis=1)
    return MarkerData(tuple(f"M{k}" for k in range(m)), pos, 100.0, "x", np.array([0, 0, 1.0]))


def test_fill_gaps_interpolates_short_gaps_and_rejects_long_ones():
    truth = _smooth_markers()
    pos = truth.positions.copy()
    pos[40:45, 0] = np.nan  # 5 frames
    pos[:3, 1] = np.nan  # not yet seen: trimmed
    filled, rep = mk.fill_gaps(truth._replace(positions=pos), ["M0", "M1"], max_gap=10)
    assert rep == mk.GapReport(frames_filled=5, trimmed_start=3, trimmed_end=0, longest_gap=5)
    np.testing.assert_allclose(filled.positions, truth.positions[3:], atol=TOL_FILL)
    pos[60:75, 0] = np.nan  # 15 frames
    with pytest.raises(TrialError, match="gap of 15 frames"):
        mk.fill_gaps(truth._replace(positions=pos), ["M0", "M1"], max_gap=10)
    # only needed markers count
    mk.fill_gaps(truth._replace(positions=pos), ["M1"], max_gap=10)
    pos[:, 1] = np.nan
    with pytest.raises(TrialError, match="never seen"):
        mk.fill_gaps(truth._replace(positions=pos), ["M1"], max_gap=10)


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_rigid_motion_recovers_a_known_motion():
    rng = np.random.default_rng(1)
    ref = rng.normal(size=(4, 3))
    rots = np.stack([_rotation(rng.normal(size=3), rng.uniform(-3, 3)) for _ in range(6)])
    d = rng.normal(size=(6, 3))
    cur = np.einsum("fij,kj->fki", rots, ref) + d[:, None]
    r, t = cal.rigid_motion(ref, cur)
    np.testing.assert_allclose(r, rots, atol=1e-12)
    np.testing.assert_allclose(t, d, atol=1e-12)


def _two_segment_trial():
    """Clusters A (proximal) and B (distal) articulated at ``centre``; landmark L on B."""
    rng = np.random.default_rng(2)
    centre = np.array([0.1, -0.2, 1.3])
    ref_a = centre + rng.normal(scale=0.05, size=(4, 3)) + [0, 0, 0.1]
    ref_b = centre + rng.normal(scale=0.05, size=(4, 3)) + [0.2, 0, -0.1]
    landmark = centre + np.array([0.25, 0.02, -0.15])
    names = ("A1", "A2", "A3", "A4", "B1", "B2", "B3", "B4", "L")
    static = np.concatenate([ref_a, ref_b, landmark[None]])[None]
    frames = []
    for i in range(60):
        s = i / 59
        r_a = _rotation([0, 0, 1], 0.3 * s)  # the proximal segment turns a little
        d_a = np.array([0.02 * s, 0.0, 0.0])
        r_rel = _rotation([0, 1, 0], 1.2 * s) @ _rotation([1, 0, 0], 0.6 * np.sin(3 * s))
        a = ref_a @ r_a.T + d_a
        b = ((ref_b - centre) @ r_rel.T + centre) @ r_a.T + d_a
        lm = ((landmark - centre) @ r_rel.T + centre) @ r_a.T + d_a
        frames.append(np.concatenate([a, b, lm[None]]))
    up = np.array([0.0, 0.0, 1.0])
    return names, static, np.stack(frames), centre, up


def test_calibration_functional_centre_and_landmarks():
    names, static, moving, centre, up = _two_segment_trial()
    st = MarkerData(names, static.repeat(3, axis=0), 100.0, "static", up)
    mv_pos = moving.copy()
    mv_pos[:, -1] = np.nan  # the landmark is seen in the static trial only
    mv = MarkerData(names, mv_pos, 100.0, "moving", up)
    a, b = ("A1", "A2", "A3", "A4"), ("B1", "B2", "B3", "B4")
    model = mk.MarkerModel(
        "test",
        {
            "shoulder": mk.KeyPointDef(between=(a, b)),
            "hand": mk.KeyPointDef(markers=("L",), cluster=b),
        },
        forward="+x",
    )
    calib = cal.calibrate(model, st, [mv])
    np.testing.assert_allclose(calib.joint_centres["shoulder"], centre, atol=TOL_SCORE)
    assert calib.residual["shoulder"] < TOL_SCORE
    pts = cal.keypoints(mv, model, calib)
    np.testing.assert_allclose(pts["hand"], moving[:, -1], atol=1e-12)
    # the centre moves with the proximal segment
    r_a, d_a = cal.rigid_motion(static[0, :4], moving[:, :4])
    np.testing.assert_allclose(pts["shoulder"], r_a @ centre + d_a, atol=TOL_SCORE)
    # without the static trial the landmark cannot be made
    calib2 = cal.calibrate(model, None, [mv])
    with pytest.raises(TrialError, match="required marker L missing"):
        cal.keypoints(mv, model, calib2)


def test_body_frame_from_the_shoulder_line():
    pts = {"shoulder": np.array([[0.0, -1.0, 2.0]]), "left_shoulder": np.array([[0.3, -0.6, 2.1]])}
    origin, rot = fr.body_frame(pts, np.array([0.0, 0.0, 1.0]), None)
    np.testing.assert_allclose(origin, [0.0, -1.0, 2.0])
    right = np.array([-0.3, -0.4, 0.0]) / 0.5
    np.testing.assert_allclose(rot[1], -right, atol=1e-12)  # y: left
    np.testing.assert_allclose(rot[2], [0, 0, 1], atol=1e-12)  # z: up
    np.testing.assert_allclose(rot[0], np.cross([0, 0, 1], right), atol=1e-12)  # x: forward
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)


def _person(n=120):
    """Key points and two hip markers of a person standing still ``(F, 3)`` each [m], z up."""
    still = {
        "shoulder": [0.0, -0.2, 1.4],
        "left_shoulder": [0.0, 0.2, 1.4],
        "elbow": [0.05, -0.22, 1.12],
        "hand": [0.3, -0.2, 1.0],
        "LHIP": [0.0, 0.1, 0.9],
        "RHIP": [0.0, -0.1, 0.9],
    }
    s = np.linspace(0.0, 1.0, n)[:, None]
    pts = {k: np.repeat(np.asarray(v)[None], n, axis=0) for k, v in still.items()}
    pts["hand"] = pts["hand"] + s * [0.25, 0.0, 0.15]  # the arm reaches forward and up
    return pts


def test_body_frames_follow_a_person_who_walks_and_turns():
    """A person who walks 0.8 m, bobs and turns 1.2 turns while reaching has, in `body_frames`
    with the shoulder as origin and the hips as heading, the key points of the same reach done
    standing still; `heading_turn` is the turn, unwrapped past pi, tilt left out."""
    up = np.array([0.0, 0.0, 1.0])
    still = _person()
    n = len(still["hand"])
    s = np.linspace(0.0, 1.0, n)
    turn = 2.4 * np.pi * s**2
    shift = np.stack([0.8 * s, 0.1 * s, 0.02 * np.sin(12 * s)], axis=1)
    rot = np.stack([_rotation(up, a) for a in turn])
    moved = {k: np.einsum("fij,fj->fi", rot, v) + shift for k, v in still.items()}

    def body(pts):
        heading = pts["RHIP"] - pts["LHIP"]
        origin, r = fr.body_frames(pts, up, None, pts["shoulder"], heading)
        return {k: np.einsum("fij,fj->fi", r, v - origin) for k, v in pts.items()}

    still_body, moved_body = body(still), body(moved)
    for k in still:
        np.testing.assert_allclose(moved_body[k], still_body[k], atol=TOL_POS)
    np.testing.assert_allclose(still_body["shoulder"], 0.0, atol=TOL_POS)
    # frame 0 is body_frame's: x forward, y left
    np.testing.assert_allclose(still_body["left_shoulder"][0], [0.0, 0.4, 0.0], atol=TOL_POS)
    tilted = (moved["RHIP"] - moved["LHIP"]) + np.outer(np.sin(5 * s), up)
    np.testing.assert_allclose(fr.heading_turn(tilted, up), turn, atol=1e-9)
    # without a heading the frame is frame 0's, fixed: the walk stays in the coordinates
    origin, r = fr.body_frames(moved, up, None)
    np.testing.assert_allclose(origin, np.broadcast_to(moved["shoulder"][0], (n, 3)))
    assert np.ptp(np.einsum("fij,fj->fi", r, moved["shoulder"] - origin), axis=0).max() > 0.7
    with pytest.raises(TrialError, match=r"heading at frame 3: its horizontal part is 0\.0 mm"):
        vertical = tilted.copy()
        vertical[3] = up
        fr.heading_turn(vertical, up)


def test_heading_markers_of_the_models():
    """The heading comes from the model's trunk markers when a trial has them, else from the
    shoulder line; UE ADL's are the left acromion cluster and the sternum."""
    d = read_vicon_csv(TRIAL)
    model = mk.MARKER_MODELS["ue_adl"]
    assert model.heading == (("LSHO1", "LSHO2", "LSHO3", "LSHO4"), ("STRN",))
    pts = {"shoulder": d.get("RSHO1"), "left_shoulder": d.get("LSHO1")}
    h = fr.heading_direction(d, pts, model)
    lsho = [d.get(f"LSHO{i}") for i in range(1, 5)]
    np.testing.assert_allclose(h.direction, d.get("STRN") - np.mean(lsho, axis=0))
    np.testing.assert_allclose(h.centre, np.mean([*lsho, d.get("STRN")], axis=0))
    assert h.source == "markers LSHO1+LSHO2+LSHO3+LSHO4 -> STRN"
    without = d._replace(names=tuple("X" if n == "STRN" else n for n in d.names))
    h = fr.heading_direction(without, pts, model)
    np.testing.assert_allclose(h.direction, pts["shoulder"] - pts["left_shoulder"])
    assert h.centre is None and h.source == "shoulder line"


def test_marker_models_builtin_and_yaml(tmp_path):
    assert set(mk.MARKER_MODELS) >= {"ue_adl", "plug_in_gait", "cmu_bvh", "cmu_asf"}
    good = tmp_path / "m.yaml"
    good.write_text(
        "forward: +y\nkeypoints:\n  shoulder: [RSHO]\n  elbow: {markers: [RELB]}\n"
        "  hand: {markers: [RFIN], cluster: [H1, H2, H3]}\n"
    )
    m = mk.load_marker_model(str(good))
    assert m.keypoints["hand"] == mk.KeyPointDef(markers=("RFIN",), cluster=("H1", "H2", "H3"))
    assert m.required() == ("shoulder", "elbow", "hand")
    assert m.heading is None
    good.write_text(good.read_text() + "heading: [[C7], [CLAV, STRN]]\n")
    assert mk.load_marker_model(str(good)).heading == (("C7",), ("CLAV", "STRN"))
    for text, match in [
        ("keypoints: {hand: [A], knee: [B]}\nforward: x", "unknown key point"),
        ("keypoints: {hand: [A]}\nforward: x", "at least one more"),
        ("keypoints: {hand: [A], elbow: [B]}", "left_shoulder"),
        ("keypoints: {hand: [A], elbow: [B]}\nforward: w", "axis"),
        ("keypoints: {hand: [A], elbow: [B]}\nforward: x\nheading: [C7]", "heading"),
        (
            "keypoints: {hand: {markers: [A], between: [[a], [b]]}, elbow: [B]}\nforward: x",
            "exactly one",
        ),
    ]:
        good.write_text(text)
        with pytest.raises(UserError, match=match):
            mk.load_marker_model(str(good))
    with pytest.raises(UserError, match="built-in"):
        mk.load_marker_model("no_such_model")
