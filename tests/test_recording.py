"""Headless rerun recordings: read back with rerun's own reader, verified by the rerun CLI, atomic, fail-safe."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import rerun as rr  # noqa: E402,F401  (a dependency: a missing rerun fails, never skips)
from rerun.chunk import RrdReader  # noqa: E402

from msdgrasp.envs.grasp_lift import GraspLiftEnv  # noqa: E402
from msdgrasp.envs.recording import RecordingError, RecordingWarning, RerunRecorder, record_episode  # noqa: E402

N_STEPS = 20
PINCH = "/episode_0000/forces/pinch"


def scripted(i: int) -> np.ndarray:
    """Close the jaws for 12 steps, then keep closing and pull."""
    return np.array([1.0, 0.0]) if i < 12 else np.array([1.0, 1.0])


@pytest.fixture(scope="module", autouse=True)
def rerun_home(tmp_path_factory):
    """rerun (SDK and CLI) keeps config/analytics under HOME/XDG dirs: point them at a temp folder."""
    home = tmp_path_factory.mktemp("home")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HOME", str(home))
        for var in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME", "XDG_STATE_HOME"):
            mp.setenv(var, str(home / var.lower()))
        mp.setenv("RERUN", "on")
        yield home


@pytest.fixture(scope="module")
def env():
    e = GraspLiftEnv()
    yield e
    e.close()


@pytest.fixture(scope="module")
def recorded(env, tmp_path_factory):
    """One ~20-step episode recorded to a file; the infos the env returned along the way."""
    path = tmp_path_factory.mktemp("rec") / "episode.rrd"
    rec = RerunRecorder(env, path)
    _, info0 = rec.reset(seed=3, options={"mu": 0.8})
    infos = [info0]
    for i in range(N_STEPS):
        _, _, terminated, truncated, info = rec.step(scripted(i))
        infos.append(info)
        assert not (terminated or truncated)
    rec.finish()
    return path, infos


def read_series(path: Path, entity: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(step, sim_time s, value) of a Scalars entity, read with rerun's RrdReader, sorted by step."""
    steps, times, values = [], [], []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        names = rb.schema.names
        steps += rb.column(names.index("step")).to_pylist()
        times += [t.total_seconds() if hasattr(t, "total_seconds") else t * 1e-9
                  for t in rb.column(names.index("sim_time")).to_pylist()]
        values += [v[0] for v in rb.column(names.index("Scalars:scalars")).to_pylist()]
    order = np.argsort(steps, kind="stable")
    return np.asarray(steps)[order], np.asarray(times)[order], np.asarray(values, dtype=np.float64)[order]


def rerun_exe() -> str:
    """The rerun CLI binary shipped with rerun-sdk. (Not ``python -m rerun_cli``: in 0.41 its
    ``__main__`` drops the binary's exit status, so a failed verify would still exit 0.)"""
    import rerun_cli

    exe = Path(rerun_cli.__file__).with_name("rerun")
    if exe.is_file():
        return str(exe)
    found = shutil.which("rerun")
    if found is None:
        pytest.skip("the rerun executable is not installed")
    return found


def rerun_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([rerun_exe(), *args], capture_output=True, text=True, timeout=120, env=os.environ.copy())


def test_pinch_series_read_back_equals_info(recorded, env):
    path, infos = recorded
    steps, times, pinch = read_series(path, PINCH)
    expected = np.array([info["pinch_force_N"] for info in infos])
    assert len(pinch) == len(expected) == N_STEPS + 1  # the reset frame + one row per step
    np.testing.assert_array_equal(steps, np.arange(N_STEPS + 1))
    np.testing.assert_allclose(times, steps * env.config.agent_dt_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(pinch, expected, rtol=1e-6, atol=1e-7)  # float32 precision (rerun keeps f64)
    assert np.count_nonzero(expected) >= 5, "the scripted grasp should have touched the tissue"
    # the other per-step series are there, same length
    for entity in ("/episode_0000/grasp/lift_m", "/episode_0000/grasp/slip_distance_m", "/episode_0000/stress/peak_pa",
                   "/episode_0000/forces/normal/jaw_0", "/episode_0000/forces/tangential/jaw_2"):
        assert len(read_series(path, entity)[2]) == N_STEPS + 1, entity
    lift = read_series(path, "/episode_0000/grasp/lift_m")[2]
    np.testing.assert_allclose(lift, [info["lifted_m"] for info in infos], rtol=1e-6, atol=1e-9)
    for term in infos[-1]["reward_terms"]:
        vals = read_series(path, f"/episode_0000/reward/{term}")[2]
        np.testing.assert_allclose(vals, [info["reward_terms"][term] for info in infos[1:]], rtol=1e-6, atol=1e-9)
    # mesh topology is static (logged once), positions per step
    tissue = [c for c in RrdReader(path).stream() if c.entity_path == "/episode_0000/world/tissue"]
    assert sum(c.num_rows for c in tissue if c.is_static) == 1
    assert sum(c.num_rows for c in tissue if not c.is_static) == N_STEPS + 1


def test_rrd_verify_accepts_file(recorded):
    path, _ = recorded
    res = rerun_cli("rrd", "verify", str(path))
    assert res.returncode == 0, res.stdout + res.stderr
    assert "verified without error" in res.stdout + res.stderr


def test_rrd_verify_rejects_truncated_file(recorded, tmp_path):
    """The check above can fail: a truncated copy is rejected."""
    bad = tmp_path / "truncated.rrd"
    data = recorded[0].read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    assert rerun_cli("rrd", "verify", str(bad)).returncode != 0


def test_unwritable_destination_raises_at_construction(env, tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    dest = blocker / "sub" / "rec.rrd"
    with pytest.raises(RecordingError) as err:
        RerunRecorder(env, dest)
    assert str(dest) in str(err.value)
    assert isinstance(err.value, OSError) and err.value.filename == str(dest)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not_a_folder"]
    assert blocker.read_text() == "x"
    with pytest.raises(RecordingError, match="is a directory"):
        RerunRecorder(env, tmp_path)
    # on_error="warn": a warning, and a pass-through wrapper that does not crash the run
    with pytest.warns(RecordingWarning, match="not_a_folder"):
        rec = RerunRecorder(env, dest, on_error="warn")
    rec.reset(seed=0)
    rec.step(np.zeros(2))
    assert rec.finish() == [] and rec.errors
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not_a_folder"]


def test_destination_appears_only_complete(env, recorded, tmp_path):
    dest = tmp_path / "out.rrd"
    previous = recorded[0].read_bytes()
    dest.write_bytes(previous)  # a complete earlier recording
    rec = RerunRecorder(env, dest)
    rec.reset(seed=1)
    for i in range(5):
        rec.step(scripted(i))
        assert dest.read_bytes() == previous  # untouched while recording
    parts = [p for p in tmp_path.iterdir() if p.name.endswith(".part")]
    assert len(parts) == 1 and parts[0].name.startswith(".out.rrd.")
    rec.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.rrd"]  # temp renamed, nothing left over
    assert dest.read_bytes() != previous
    assert len(read_series(dest, PINCH)[2]) == 6


def test_one_file_per_episode(env, tmp_path):
    rec = RerunRecorder(env, tmp_path / "runs" / "ep_{episode:02d}.rrd")
    rec.reset(seed=0)
    for i in range(3):
        rec.step(scripted(i))
    assert not (tmp_path / "runs" / "ep_00.rrd").exists()
    rec.reset(seed=1)  # ends episode 0: its file is finished now
    assert (tmp_path / "runs" / "ep_00.rrd").exists()
    rec.step(scripted(0))
    rec.close()
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["ep_00.rrd", "ep_01.rrd"]
    assert len(read_series(tmp_path / "runs" / "ep_00.rrd", PINCH)[2]) == 4
    assert len(read_series(tmp_path / "runs" / "ep_01.rrd", "/episode_0001/forces/pinch")[2]) == 2


@pytest.mark.parametrize("on_error", ["raise", "warn"])
def test_failure_while_recording(env, tmp_path, on_error):
    """The temp file vanishes mid-recording (folder cleaned up): no corrupt destination, clear error."""
    dest = tmp_path / "lost.rrd"
    rec = RerunRecorder(env, dest, on_error=on_error)
    rec.reset(seed=0)
    rec.step(scripted(0))
    for p in tmp_path.glob("*.part"):
        p.unlink()
    if on_error == "raise":
        with pytest.raises(RecordingError, match="lost.rrd"):
            rec.finish()
    else:
        with pytest.warns(RecordingWarning, match="lost.rrd"):
            rec.finish()
        rec.reset(seed=1)  # the env keeps working
        rec.step(scripted(0))
    assert not dest.exists()
    assert list(tmp_path.iterdir()) == []


def test_record_episode_summary(env, tmp_path):
    summary = record_episode(env, lambda obs: np.array([1.0, 0.0]), tmp_path / "one.rrd", seed=2, max_steps=4)
    assert summary["steps"] == 4 and summary["path"] == str(tmp_path / "one.rrd")
    assert isinstance(summary["return"], float) and summary["success"] is False
    assert summary["size_bytes"] == (tmp_path / "one.rrd").stat().st_size
    with pytest.raises(ZeroDivisionError):
        record_episode(env, lambda obs: 1 / 0, tmp_path / "two.rrd", seed=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.rrd"]  # a failed episode leaves no file


def test_unclosed_recorder_leaves_no_temp_file(env, tmp_path):
    import gc

    rec = RerunRecorder(env, tmp_path / "forgotten.rrd")
    rec.reset(seed=0)
    rec.step(scripted(0))
    assert len(list(tmp_path.glob("*.part"))) == 1
    with pytest.warns(RecordingWarning, match="garbage-collected"):
        del rec
        gc.collect()
    assert list(tmp_path.iterdir()) == []


def test_replay_cli(recorded, tmp_path, capsys):
    import argparse

    from msdgrasp.cli.main import UsageError
    from msdgrasp.cli.replay import add_replay_arguments, replay_cli

    parser = add_replay_arguments(argparse.ArgumentParser())
    with pytest.raises(UsageError, match="recording not found: .*missing.rrd"):
        replay_cli(parser.parse_args([str(tmp_path / "missing.rrd")]))
    (tmp_path / "bogus.rrd").write_text("not a recording")
    with pytest.raises(UsageError, match="not a rerun recording"):
        replay_cli(parser.parse_args([str(tmp_path / "bogus.rrd")]))
    assert replay_cli(parser.parse_args([str(recorded[0]), "--web", "--print-command"])) == 0
    out = capsys.readouterr().out.split()
    assert Path(out[0]).name == "rerun" and "--web-viewer" in out and out[-1] == str(recorded[0])


def test_replay_web_ports_are_passed_to_rerun_and_checked_before_anything_starts():
    from msdgrasp.cli.main import UsageError
    from msdgrasp.cli.replay import viewer_command, web_viewer_url

    cmd = viewer_command("ep.rrd", web=True, port=8123, grpc_port=9123)
    # rerun: --web-viewer-port is the page, --port the gRPC server the page streams the recording from
    assert cmd[cmd.index("--web-viewer-port") + 1] == "8123" and cmd[cmd.index("--port") + 1] == "9123"
    assert web_viewer_url(8123, 9123) == "http://127.0.0.1:8123/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9123%2Fproxy"
    with pytest.raises(UsageError, match=r"^--grpc-port must be a TCP port in 1-65535, got 70000$"):
        viewer_command("ep.rrd", web=True, grpc_port=70000)
    with pytest.raises(UsageError, match=r"^--port must be a TCP port in 1-65535, got 0$"):
        viewer_command("ep.rrd", web=True, port=0)
    with pytest.raises(UsageError, match="need --web"):
        viewer_command("ep.rrd", port=8123)
    with pytest.raises(UsageError, match="are both 9090: the viewer page and the data it streams need two ports"):
        viewer_command("ep.rrd", web=True, port=9090, grpc_port=9090)
    with pytest.raises(UsageError, match="are both 9876"):  # (one port given, the other's default)
        viewer_command("ep.rrd", web=True, port=9876)


@pytest.mark.parametrize("launcher", [["-m", "msdgrasp.cli.main"],
                                      ["-c", "import sys; from msdgrasp.cli.main import main; sys.exit(main())"]])
def test_a_missing_recording_is_one_line_and_exit_2_however_the_cli_is_started(launcher, tmp_path):
    """``python -m msdgrasp.cli.main`` runs cli.py as __main__; the error class must still be caught."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, *launcher, "replay", str(tmp_path / "nope.rrd")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"msdgrasp replay: error: recording not found: {tmp_path / 'nope.rrd'}"]


def test_recordings_are_readable_like_every_other_output(recorded, tmp_path):
    """A recording gets the permissions of a normally created file (umask), not mkstemp's 0600."""
    import os

    from msdgrasp.physics.config import atomic_write_text

    other = atomic_write_text(tmp_path / "other.json", "{}")
    umask = os.umask(0)
    os.umask(umask)
    assert recorded[0].stat().st_mode & 0o777 == 0o666 & ~umask
    assert other.stat().st_mode & 0o777 == 0o666 & ~umask
