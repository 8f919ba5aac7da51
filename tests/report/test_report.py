"""The report (report.py) and the renderer (render.py).

A synthetic run folder is built in numpy + C MuJoCo (no training, no IK): human-like rest-to-posture
motions of mahru_arm, conditions from forward kinematics, two "generations" and their metrics, in
exactly the layout ``run.training.run_training`` writes. The report must write every figure as a
readable,
non-blank image, name the files a damaged folder lacks (exit 1) and refuse a folder without a run
(exit 2). The renderer's camera and its stick-figure fallback are checked against MuJoCo itself.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from evojax_motion.cli.report import add_report_parser, run_report
from evojax_motion.model.robot import load_robot
from evojax_motion.motion.database import DatabaseMeta, make_database, save_database
from evojax_motion.report import build as report
from evojax_motion.report import kinematics as kin
from evojax_motion.report import render as rnd
from evojax_motion.report.condition import catch_camera, throw
from evojax_motion.report.figures import FIGURES, tradeoff_figure
from evojax_motion.report.html import HTML_FILE
from evojax_motion.report.sticks import render_sticks
from evojax_motion.settings import config_to_yaml, load_config
from evojax_motion.settings.online import BALL_RADIUS

T, N_HUMAN, M = 24, 40, 6
TINY = Path(__file__).resolve().parents[2] / "configs" / "tiny.yaml"
PIXEL_STD_MIN = 8.0  # a blank or single-colour image has std ~0; our figures are > 20
SILHOUETTE_IOU_MIN = (
    0.8  # stick figure vs MuJoCo, same frame: measured 0.90; a 40 deg wrong azimuth 0.45
)
GEN_FIELDS = (
    "offspring_cost_mean",
    "db_cost_mean",
    "torque_sum_mean",
    "human_deviation_deg",
    "n_replaced",
    "n_rejected_nonfinite",
    "n_rejected_limits",
    "bc_residual_max",
)
ALL_FIGURES = tuple(FIGURES)


def _motions(rng, robot, qf, bump):
    """Rest-to-``qf (n, J)`` minimum-jerk motions plus a rest-to-rest bump: ``(n, T, J)``."""
    s = np.linspace(0.0, 1.0, T)[None, :, None]
    shape = s**3 * (10 - 15 * s + 6 * s**2)
    rest = np.asarray(robot.rest)[None, None]
    wiggle = (16 * s**2 * (1 - s) ** 2) * bump[:, None, :]
    q = rest + (qf[:, None] - rest) * shape + wiggle
    return np.clip(q, robot.lower, robot.upper).astype(np.float32)


def make_fake_run(path: Path, generations: int = 2) -> Path:
    """A complete run folder (the files `run.training.run_training` writes) without training."""
    robot = load_robot("mahru_arm")
    rng = np.random.default_rng(0)
    j = robot.n_joints
    names = robot.joint_names
    nominal = np.zeros(j)
    nominal[names.index("shoulder_pitch")] = 1.1
    nominal[names.index("shoulder_roll")] = 0.3
    nominal[names.index("elbow")] = 0.9
    lo, hi = robot.lower + 0.05, robot.upper - 0.05
    qf_h = np.clip(nominal + rng.normal(0, 0.15, (N_HUMAN, j)), lo, hi)
    q_h = _motions(rng, robot, qf_h, rng.normal(0, 0.08, (N_HUMAN, j)))
    dur_h = rng.uniform(0.6, 0.9, N_HUMAN).astype(np.float32)
    cond_h = kin.site_positions(robot, qf_h).astype(np.float32)

    qf_c = np.clip(nominal + rng.normal(0, 0.08, (M, j)), lo, hi)
    target = kin.site_positions(robot, qf_c).astype(np.float32)
    dur_c = np.full(M, 0.75, np.float32)
    meta = DatabaseMeta(robot.name, robot.mjcf, tuple(names), robot.site_name, True, "test")

    def database(q_evolved, valid, generation):
        db = make_database(q_h, dur_h, cond_h, rng.uniform(50, 80, N_HUMAN), N_HUMAN + M)
        sl = slice(N_HUMAN, None)
        db.q[sl], db.duration[sl], db.condition[sl] = q_evolved, dur_c, target
        db.valid[sl], db.generation[sl] = valid, generation
        db.cost[sl] = np.where(valid, 40.0 - generation, np.inf)
        return db

    path.mkdir(parents=True)
    # configs/tiny.yaml's settings and sizes: the report then compiles what the notebook's
    # figures of the tiny run compile (the test run's XLA cache serves both; conftest runs them
    # on one worker)
    cfg = load_config(TINY, [f"evolution.generations={generations}"])
    assert (cfg.demos.count, cfg.demos.samples, cfg.evolution.conditions) == (N_HUMAN, T, M)
    (path / "config.yaml").write_text(config_to_yaml(cfg))
    (path / "robot.xml").write_text(robot.mjcf)
    zeros = np.zeros((M, T, j), np.float32)
    save_database(path / "db_initial.npz", database(zeros, False, 0), meta)
    q_first = _motions(rng, robot, qf_c, rng.normal(0, 0.10, (M, j)))
    q_last = _motions(rng, robot, qf_c, rng.normal(0, 0.03, (M, j)))
    save_database(path / "db_gen1.npz", database(q_first, True, 1), meta)
    save_database(path / "db_final.npz", database(q_last, True, generations), meta)
    rows = []
    for g in range(1, generations + 1):
        row = {"generation": g, "seconds": 0.1}
        row.update({k: float(100.0 / g + i) for i, k in enumerate(GEN_FIELDS)})
        rows.append(row)
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    baseline = {"human_only_cost_mean": 120.0, "human_only_torque_sum_mean": 110.0}
    (path / "summary.json").write_text(json.dumps({"generations": generations, **baseline}))
    (path / "checkpoints").mkdir()
    (path / "plots").mkdir()
    return path


def _parse(argv):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command", required=True)
    add_report_parser(sub)
    return parser.parse_args(argv)


def _check_image(path: Path) -> None:
    with Image.open(path) as im:
        im.load()
        frames = getattr(im, "n_frames", 1)
        arr = np.asarray(im.convert("RGB"), float)
    assert arr.ndim == 3 and min(arr.shape[:2]) >= 64, (path, arr.shape)
    assert arr.std() > PIXEL_STD_MIN, f"{path.name}: blank image (std {arr.std():.2f})"
    if path.suffix == ".gif":
        assert frames >= 10, f"{path.name}: {frames} frames"


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    return make_fake_run(tmp_path_factory.mktemp("run") / "run")


@pytest.fixture(scope="module")
def full_report(fake_run, tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("EVOJAX_MOTION_JAX_CACHE", "off")  # no XLA cache in the user's home from tests
    out = tmp_path_factory.mktemp("report")
    args = _parse(["report", str(fake_run), "--out", str(out), "--gif-frames", "12", "--quiet"])
    try:
        status = run_report(args)
    finally:
        mp.undo()
    return status, out


@pytest.mark.slow
def test_report_writes_every_figure(full_report):
    status, out = full_report
    assert status == 0
    for name in ALL_FIGURES:
        _check_image(out / name)
    page = (out / HTML_FILE).read_text()
    assert page.count("data:image/png;base64,") == len(ALL_FIGURES) - 1
    assert page.count("data:image/gif;base64,") == 1
    assert "<img" in page and "src='figures/" not in page  # self-contained


def test_missing_files_are_named_and_the_rest_is_written(fake_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("EVOJAX_MOTION_JAX_CACHE", "off")
    run = tmp_path / "run"
    shutil.copytree(fake_run, run)
    (run / "db_final.npz").unlink()
    (run / "metrics.jsonl").write_text("{not json\n")
    out = tmp_path / "out"
    status = run_report(_parse(["report", str(run), "--out", str(out), "--quiet"]))
    err = capsys.readouterr().err
    assert status == 1
    assert "db_final.npz" in err and "metrics.jsonl" in err
    _check_image(out / "fig4_basis.png")  # needs only db_initial and the config
    for name in ("fig5_costs.png", "fig8_generations.png", "fig10_interp_vs_optim.png",
                 "catch.gif", "fig7_snapshots.png"):  # fmt: skip
        assert not (out / name).exists(), name
    page = (out / HTML_FILE).read_text()
    assert "db_final.npz: missing" in page and "line 1: not JSON" in page


def test_no_run_is_a_user_error(tmp_path):
    from evojax_motion.errors import UserError

    with pytest.raises(UserError, match="no such directory"):
        report.make_report(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="holds no training run"):
        report.make_report(tmp_path / "empty")


def test_bad_options_write_nothing(fake_run, tmp_path):
    from evojax_motion.errors import UserError

    out = tmp_path / "out"
    with pytest.raises(UserError, match=rf"--condition: expected an index in 0\.\.{M - 1}"):
        report.make_report(fake_run, out, condition=M)
    with pytest.raises(UserError, match="--joint: expected one of"):
        report.make_report(fake_run, out, joint="knee")
    assert not out.exists()


def test_cli_exit_status_for_no_run(tmp_path, capsys):
    """Through the console script when the lead has wired ``report`` into cli.py."""
    from evojax_motion.cli import entry as cli

    try:
        cli.build_parser().parse_args(["report", str(tmp_path)])
    except Exception:
        pytest.skip("report is not wired into cli.py yet")
    assert cli.main(["report", str(tmp_path / "nowhere")]) == 2
    assert "no such directory" in capsys.readouterr().err


# ------------------------------------------------------------------------------- renderer


@pytest.fixture(scope="module")
def reach():
    """A rest-to-reach motion of mahru_arm, 3 frames, and a front camera that frames it."""
    robot = load_robot("mahru_arm")
    q = np.zeros((3, robot.n_joints))
    q[1, 1], q[2, 1], q[2, 4] = 0.8, 1.5, 1.0
    cam = kin.fit_camera(robot, [q], kin.VIEWS["three_quarter"])
    return robot, q, cam


def test_fit_camera_keeps_every_geom_in_the_picture(reach):
    robot, q, cam = reach
    w, h = 320, 240
    pts = kin.geom_points(robot, [q])
    u, v, depth, _ = kin.project(pts, cam, robot.mj_model.vis.global_.fovy, w, h)
    assert (depth > 0).all()
    assert u.min() >= -1 and u.max() <= w + 1 and v.min() >= -1 and v.max() <= h + 1
    # ... and tight: the extent fills most of the picture along one axis (perspective: ~0.8)
    assert max((u.max() - u.min()) / w, (v.max() - v.min()) / h) > 0.75


ASSETS = Path(__file__).resolve().parents[1] / "assets"
TOL_MESH_M = 1e-6  # [m] a mesh box's segment against its vertices (MuJoCo keeps them in float32)


def _body_frames(robot, q):
    """``(xpos (F, nbody, 3), xmat (F, nbody, 3, 3))`` by MuJoCo's forward kinematics."""
    import mujoco

    m, d = robot.mj_model, mujoco.MjData(robot.mj_model)
    out = []
    for qpos in kin.full_qpos(robot, q):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        out.append((d.xpos.copy(), d.xmat.reshape(-1, 3, 3).copy()))
    return np.stack([x for x, _ in out]), np.stack([r for _, r in out])


def test_a_robot_made_of_meshes_is_drawn_from_their_boxes():
    """Published arms are meshes only, each also as a hidden collision geom (group 3): one
    segment per visible mesh, along the longest axis of its box through the box's centre, as
    the vertices written in the model give it in the body's frame; radius its smallest half
    extent. A model without any drawable geom is its bodies' chain; a report's floor and camera
    come out finite for both."""
    robot = load_robot(ASSETS / "mesh_arm.xml")
    q = np.array([[0.0, 0.0], [0.7, -1.1], [-1.5, 0.4]])
    seg = kin.segments(robot, q)
    assert seg.a.shape == (3, 2, 3)
    np.testing.assert_allclose(seg.radius, [0.04, 0.02])
    xpos, xmat = _body_frames(robot, q)
    # the centres of each box's two end faces, in its body's frame (see the model's vertices)
    ends = {1: ([0.01, 0.0, 0.02], [0.01, 0.0, 0.32]), 2: ([0.0, 0.0, 0.0], [0.25, 0.0, 0.0])}
    for g, body in enumerate((1, 2)):
        p0, p1 = (xpos[:, body] + np.einsum("fij,j->fi", xmat[:, body], e) for e in ends[body])
        got = np.stack([seg.a[:, g], seg.b[:, g]], axis=1)
        straight = np.abs(got - np.stack([p0, p1], axis=1)).max()
        turned = np.abs(got - np.stack([p1, p0], axis=1)).max()
        assert min(straight, turned) <= TOL_MESH_M
    for r in (robot, load_robot(ASSETS / "continuous_arm.xml")):
        pose = np.zeros((2, r.n_joints))
        assert np.isfinite(kin.floor_height(r, [pose]))
        cam = kin.fit_camera(r, [pose], kin.VIEWS["three_quarter"])
        assert np.isfinite(cam.distance) and cam.distance > 0

    bare = load_robot(ASSETS / "continuous_arm.xml")  # inertials and a site, no geom
    pose = np.array([[0.3, -0.4, 0.2, 0.05]])
    chain = kin.segments(bare, pose)
    xpos, _ = _body_frames(bare, pose)
    m = bare.mj_model
    np.testing.assert_allclose(chain.b[0, :-1], xpos[0, 1:])
    np.testing.assert_allclose(chain.a[0, :-1], xpos[0, m.body_parentid[1:]])
    np.testing.assert_allclose(chain.b[0, -1], kin.site_positions(bare, pose)[0])


def test_catch_frames_timeline(reach):
    """Arm at rest until the motion starts, then on it, then held; ball on its flight until the
    catch, then at the hand."""
    robot, q, _ = reach
    t_motion = np.linspace(0.3, 0.9, q.shape[0])  # the motion's grid [s after release]
    ball_t = np.linspace(0.0, 1.5, 16)
    ball = np.stack([2.0 - ball_t, -0.3 + 0 * ball_t, 1.0 + ball_t - ball_t**2], axis=1)
    times = np.array([0.0, 0.2, 0.3, 0.6, 0.9, 1.0, 1.2])
    q_f, ball_f = kin.catch_frames(robot, t_motion, q, ball_t, ball, 0.9, times)
    np.testing.assert_allclose(q_f[:3], np.tile(q[0], (3, 1)), atol=1e-12)
    np.testing.assert_allclose(q_f[3], q[1], atol=1e-12)  # the grid's middle sample
    np.testing.assert_allclose(q_f[4:], np.tile(q[-1], (3, 1)), atol=1e-12)
    np.testing.assert_allclose(ball_f[:1], ball[:1], atol=1e-12)
    for k in range(3):  # linear in time between flight samples
        np.testing.assert_allclose(ball_f[1:4, k], np.interp(times[1:4], ball_t, ball[:, k]))
    hand = kin.site_positions(robot, q[-1:])[0]
    np.testing.assert_allclose(ball_f[4:], np.tile(hand, (3, 1)), atol=1e-12)


def _foreground(images):
    """Pixels that differ from the frame's corner colour (background): ``(F, H, W)`` bool."""
    corner = images[:, :4, -4:].reshape(images.shape[0], -1, 3).mean(axis=1)[:, None, None]
    return np.abs(images.astype(float) - corner).sum(axis=-1) > 40


def test_stick_figures_asked_for_are_not_called_a_fallback(reach, monkeypatch):
    """``renderer="stick"``: the frames say "stick figure" only; the fallback's label (no
    OpenGL) is kept for frames drawn because MuJoCo could not render."""
    from evojax_motion.report import sticks

    robot, q, cam = reach
    labels = []

    def spy(*args, **kwargs):
        labels.append(args[7] if len(args) > 7 else kwargs.get("label"))
        return np.zeros((len(q), 4, 4, 3), np.uint8)

    monkeypatch.setattr(rnd, "render_sticks", spy)
    monkeypatch.setattr(rnd, "gl_status", lambda: rnd.GLStatus(None, "no GL here"))
    assert rnd.render_motion(robot, q, [cam], renderer="stick").renderer == "stick figure"
    rnd.render_motion(robot, q, [cam], renderer="auto")
    assert labels == [sticks.ASKED_LABEL, sticks.STICK_LABEL]
    assert "fallback" in sticks.STICK_LABEL and "fallback" not in sticks.ASKED_LABEL


def test_stick_fallback_matches_mujoco_framing(reach):
    robot, q, cam = reach
    sticks = render_sticks(robot, q, [cam], label="")
    assert sticks.shape == (3, 240, 320, 3) and sticks.dtype == np.uint8
    assert _foreground(sticks).mean(axis=(1, 2)).min() > 0.02  # a figure in every frame
    # the arm moves: frames differ
    assert np.abs(sticks[0].astype(float) - sticks[2]).mean() > 1.0
    if not rnd.gl_status().available:
        pytest.skip(f"no GL backend: {rnd.gl_status().message}")
    gl = rnd.render_mujoco(robot, q, [cam], sky=False)  # black background, no floor
    a, b = _foreground(gl), _foreground(sticks)
    iou = (a & b).sum(axis=(1, 2)) / (a | b).sum(axis=(1, 2))
    assert iou.min() > SILHOUETTE_IOU_MIN, iou


def test_no_gl_backend_falls_back_to_labelled_sticks(reach, monkeypatch):
    robot, q, cam = reach
    monkeypatch.setattr(rnd, "gl_status", lambda: rnd.GLStatus(None, "no backend (test)"))
    frames = rnd.render_motion(robot, q[:1], [cam])
    assert frames.fallback and frames.renderer.startswith("stick")
    with pytest.raises(rnd.RenderUnavailable, match="no backend"):
        rnd.render_motion(robot, q[:1], [cam], renderer="mujoco")


def test_failing_backend_is_reported_not_raised(monkeypatch):
    """The real probe path (a child process per backend) with a backend MuJoCo refuses."""
    monkeypatch.setattr(rnd, "GL_BACKENDS", ("nonexistent",))
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    rnd.gl_status.cache_clear()
    try:
        status = rnd.gl_status()
    finally:
        rnd.gl_status.cache_clear()
    assert not status.available
    assert status.message.startswith("no OpenGL backend") and "nonexistent" in status.message


def test_gl_disabled_by_environment(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "disable")
    rnd.gl_status.cache_clear()
    try:
        status = rnd.gl_status()
        assert not status.available and "disable" in status.message
    finally:
        rnd.gl_status.cache_clear()


def test_save_gif_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (5, 32, 48, 3), dtype=np.uint8)
    path = rnd.save_gif(frames, tmp_path / "a.gif", fps=10)
    with Image.open(path) as im:
        assert im.n_frames == 5 and im.size == (48, 32)
        assert im.info["duration"] == 100


# ---------------------------------------------------------------- what the figures show


def _metrics(cost, deviation):
    """metrics.jsonl rows for generations 1.. with these mean costs and deviations."""
    return [
        {
            "generation": g,
            "db_cost_mean": c,
            "offspring_cost_mean": c + 0.5,
            "torque_sum_mean": 0.8 * c,
            "human_deviation_deg": d,
        }
        for g, (c, d) in enumerate(zip(cost, deviation), 1)
    ]


BASELINE = {"human_only_cost_mean": 14.0, "human_only_torque_sum_mean": 11.5}


@pytest.mark.parametrize("baseline", [None, BASELINE])
def test_fig5_legend_names_every_curve(baseline):
    from evojax_motion.report.plots import costs_figure

    fig = costs_figure(_metrics([13.7, 13.45, 13.36, 13.36], [10, 11, 11, 11]), baseline)
    names = {t.get_text() for legend in fig.legends for t in legend.get_texts()}
    lines = [line for ax in fig.axes for line in ax.get_lines()]
    assert len(lines) == 3 + 2 * (baseline is not None)
    for line in lines:  # an unlabelled line's label is "_child<n>"
        assert line.get_label() in names, (line.get_label(), names)


def test_joint_angle_legend_names_every_curve():
    from evojax_motion.report.plots import joint_angles_figure

    rng = np.random.default_rng(0)
    q = [rng.normal(size=(T, 3)) for _ in range(3)]
    fig = joint_angles_figure(q[0], q[1], 0.7, ["a", "b", "c"], q_human=q[2])
    names = {t.get_text() for t in fig.axes[0].get_legend().get_texts()}
    for ax in fig.axes:
        for line in ax.get_lines():
            assert line.get_label() in names, (line.get_label(), names)


def _tradeoff_labels(metrics):
    """Texts and their window extents of the trade-off plot's generation labels."""
    import matplotlib.pyplot as plt

    fig = tradeoff_figure(metrics, BASELINE)
    try:
        renderer = fig.canvas.get_renderer()
        ax = fig.axes[0]
        frame = ax.get_window_extent(renderer)
        boxes = [t.get_window_extent(renderer) for t in ax.texts]
        for box in boxes:  # inside the axes: clear of the colour bar and the tick labels
            assert frame.contains(box.x0, box.y0) and frame.contains(box.x1, box.y1)
        return [t.get_text() for t in ax.texts], boxes
    finally:
        plt.close(fig)


@pytest.mark.parametrize(
    "case",
    [
        # the tiny run's: generations 3 and 4 at the same point (their labels overlapped)
        ([13.7, 13.45, 13.36, 13.36], [10.1, 11.33, 11.04, 11.04]),
        # 40 generations crowding together, one without a deviation
        (
            list(13 - 0.5 * np.log(np.arange(1, 41))),
            [10 + 0.3 * np.log(g) if g != 7 else np.nan for g in range(1, 41)],
        ),
    ],
    ids=["same-point", "crowded"],
)
def test_tradeoff_generation_labels_do_not_overlap(case):
    cost, deviation = case
    texts, boxes = _tradeoff_labels(_metrics(cost, deviation))
    for i in range(len(boxes)):
        for k in range(i + 1, len(boxes)):
            assert not boxes[i].overlaps(boxes[k]), (texts[i], texts[k])
    last = len(cost)
    assert texts[0].endswith(str(last)) and "1" in texts  # the last and the first are labelled
    if last == 4:
        assert texts == ["3-4", "1", "2"]  # same spot: one label


def test_catch_animation_keeps_the_ball_in_view(reach):
    """The catch.gif camera frames every ball position of a report's throw (release, arc above
    the head, catch) with the ball's radius; framing only the arm would not."""
    robot, q, _ = reach
    width, height = 320, 240  # report.py's frame size (fit_camera's 4:3)
    target = kin.site_positions(robot, q[-1:])[0]
    gravity = np.asarray(robot.mj_model.opt.gravity, float)
    p0, v0, t_pass = throw(target, 0.65, gravity, 0.1)
    t = np.linspace(0.0, t_pass, 40)[:, None]
    balls = p0 + v0 * t + 0.5 * gravity * t**2
    assert balls[:, 2].max() > target[2] + 0.5  # the arc rises well above the catch point
    np.testing.assert_allclose(balls[-1], target, atol=1e-9)
    fovy = robot.mj_model.vis.global_.fovy

    def inside(cam):
        u, v, depth, focal = kin.project(balls, cam, fovy, width, height)
        r = focal * BALL_RADIUS / depth  # the ball's radius [px]
        return (depth > 0) & (u - r >= 0) & (u + r <= width) & (v - r >= 0) & (v + r <= height)

    assert inside(catch_camera(robot, q, balls)).all()
    assert not inside(kin.fit_camera(robot, [q], kin.VIEWS["catch"], target[None])).all()
