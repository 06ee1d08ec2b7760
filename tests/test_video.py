"""Episode videos and frames a person can review: mp4 / GIF export, colour bar, stick/slip markers.

Runtime: two short episodes (the reactive controller, 1.5 s each) rendered at 320 x 240, a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.controllers import make_policy
from msdgrasp.envs.core import GraspLiftConfig
from msdgrasp.envs.grasp_lift import GraspLiftEnv
from msdgrasp.envs.render import SLIP_COLOUR, STICK_COLOUR, render_rgb
from msdgrasp.envs.video import read_video, record_video, write_video
from msdgrasp.physics.config import ConfigError

SHORT = GraspLiftConfig(time_limit_s=1.5)  # 46 agent steps: the jaws close and grip


def _reactive(env):
    policy = make_policy("reactive", env.unwrapped.config)

    def act(obs):
        return policy.act(obs[None])[0]

    return policy, act


@pytest.mark.parametrize("suffix, fps", [(".mp4", 1 / SHORT.agent_dt_s), (".gif", 1 / SHORT.agent_dt_s / 3)])
def test_an_episode_becomes_a_video_with_one_frame_per_step(tmp_path, suffix, fps):
    env = GraspLiftEnv(SHORT)
    policy, act = _reactive(env)
    _, info = env.reset(seed=1, options={"mu": 0.5})
    policy.reset([info])
    out = tmp_path / f"episode{suffix}"
    summary = record_video(env, act, out, seed=1, options={"mu": 0.5}, width=320, height=240,
                           still=tmp_path / "last.png")
    assert summary["steps"] == SHORT.max_episode_steps == 46
    frames = read_video(out)
    import imageio.v3 as iio

    last = iio.imread(tmp_path / "last.png")
    assert last.shape == (240, 320, 3)
    assert np.abs(last.astype(int) - frames[-1].astype(int)).mean() < 8  # the video's last frame (lossy mp4)
    (tmp_path / "last.png").unlink()
    # mp4: the reset frame + one per agent step; GIF: every 3rd step at ~10 fps (+ reset and last frame)
    expected = 47 if suffix == ".mp4" else 1 + 46 // 3 + (46 % 3 != 0)
    assert summary["frames"] == expected and frames.shape == (expected, 240, 320, 3)
    assert summary["fps"] == pytest.approx(fps, rel=1e-6)
    # the jaws close: early and late frames differ in many pixels (the mp4 is lossy: a loose threshold)
    diff = np.abs(frames[0].astype(int) - frames[-1].astype(int)).max(axis=2) > 40
    assert diff.sum() > 500
    assert len(list(tmp_path.iterdir())) == 1  # no temp file left behind


def test_bad_video_input_names_the_problem(tmp_path):
    with pytest.raises(ConfigError, match=r"\.mp4 or \.gif"):
        write_video([np.zeros((16, 16, 3), np.uint8)], tmp_path / "x.avi", 30)
    with pytest.raises(ConfigError, match="no frames"):
        write_video([], tmp_path / "x.mp4", 30)
    with pytest.raises(ConfigError, match="uint8"):
        write_video([np.zeros((16, 16, 3))], tmp_path / "x.mp4", 30)
    assert list(tmp_path.iterdir()) == []


def _rgb255(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)])


def test_frame_has_a_colour_bar_and_stick_slip_markers_at_the_contact_nodes():
    from mpl_toolkits.mplot3d import proj3d

    env = GraspLiftEnv(GraspLiftConfig())
    policy, act = _reactive(env)
    obs, info = env.reset(seed=1, options={"mu": 0.3})
    policy.reset([info])
    for _ in range(70):  # closed and pulling: contact nodes stick or slip
        obs, *_ = env.step(act(obs))
    core = env.core
    img = render_rgb(core, 0, 640, 480)
    frame = core._render_cache[(640, 480)]
    state = core.sim.contact_state[0]
    nodes = np.flatnonzero(state > 0)
    assert nodes.size >= 5
    # colour bar: a vertical viridis gradient (dark purple at the bottom, yellow at the top)
    bbox = frame.cax.get_window_extent()
    x = int(bbox.x0 + bbox.width / 2)
    top, bottom = img[480 - int(bbox.y1) + 3, x].astype(int), img[480 - int(bbox.y0) - 3, x].astype(int)
    assert top[0] > 200 and top[1] > 200 and top[2] < 100  # yellow
    assert bottom[0] < 100 and bottom[1] < 50 and bottom[2] > 60  # dark purple
    # markers: a pixel of the node's state colour within 3 px of each contact node's projection
    ax = frame.ax
    xs, ys, _ = proj3d.proj_transform(*core.sim.x[0][nodes].T, ax.get_proj())
    disp = ax.transData.transform(np.column_stack([xs, ys]))
    hits = 0
    for (px, py), code in zip(disp, state[nodes]):
        col = _rgb255(STICK_COLOUR if code == 1 else SLIP_COLOUR)
        r, c = int(round(480 - py)), int(round(px))
        patch = img[max(r - 3, 0) : r + 4, max(c - 3, 0) : c + 4].reshape(-1, 3).astype(int)
        hits += bool(np.any(np.abs(patch - col).max(axis=1) < 40))
    assert hits >= 0.8 * nodes.size, (hits, nodes.size)
    # the title names mu and the outcome so far
    assert frame.title.get_text().startswith("mu=0.30")


def test_record_cli_rejects_a_bad_video_name_before_writing(tmp_path, capsys):
    from msdgrasp.cli.main import main

    rc = main(["record", "--policy", "fixed", "--out", str(tmp_path / "ep.rrd"), "--video", str(tmp_path / "ep.avi")])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "must end in .mp4 or .gif" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_a_recording_and_its_video_come_from_one_run_of_the_episode(tmp_path, monkeypatch):
    """record --out ep.rrd --video ep.mp4: the episode runs once; the recording and the video show it."""
    from msdgrasp.agents.evaluation import record_policy_episode

    env = GraspLiftEnv(SHORT)
    calls = []
    step = env.core.step
    monkeypatch.setattr(env.core, "step", lambda a: calls.append(1) or step(a))
    summary = record_policy_episode(make_policy("reactive", SHORT), env, tmp_path / "ep.rrd", 0.5, seed=1,
                                    video=tmp_path / "ep.mp4", still=tmp_path / "ep.png")
    assert len(calls) == summary["steps"] == SHORT.max_episode_steps
    assert read_video(tmp_path / "ep.mp4").shape[0] == summary["frames"] == summary["steps"] + 1
    assert summary["path"] == str(tmp_path / "ep.rrd") and summary["size_bytes"] > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ep.mp4", "ep.png", "ep.rrd"]
