"""Episode videos (mp4 or GIF) for review without a display: a cluster, CI, a notebook, a paper.

:func:`record_video` runs one episode of a policy on a :class:`~msdgrasp.envs.grasp_lift.GraspLiftEnv` and
writes every agent step as a frame of :func:`~msdgrasp.envs.render.render_rgb` (strain colours with a colour
bar, stick/slip markers, force arrows, a pinch/lift inset, mu and the outcome in the title).
:func:`write_video` encodes frames with imageio: mp4 through its ffmpeg plugin (H.264, the ffmpeg binary
ships with ``imageio-ffmpeg``), GIF through Pillow. Files are written atomically (a temp file in the same
folder, moved into place when complete) with normal permissions.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..physics.config import ConfigError, atomic_write, needs_extra, publish, temp_beside

VIDEO_SUFFIXES = (".mp4", ".gif")


def check_video_path(path: str | os.PathLike) -> Path:
    """The path, or a one-line error naming what is wrong with it (before anything is simulated)."""
    p = Path(path)
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"video {p}: the file name must end in .mp4 or .gif, got {p.suffix or 'no suffix'!r}")
    if p.is_dir():
        raise ConfigError(f"video {p} is a folder; give a file name such as {p / 'episode.mp4'}")
    return p


def check_still_path(path: str | os.PathLike) -> Path:
    """The path of a still frame (.png), or a one-line error."""
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise ConfigError(f"still {p}: the file name must end in .png")
    return p


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float) -> Path:
    """Encode (H, W, 3) uint8 frames to ``path`` (.mp4 or .gif), atomically; returns the path.

    Frames are streamed to the encoder as they come (a 10 s episode at 640 x 480 is ~280 MB of raw frames):
    pass a generator to render while encoding. On any error the partial file is removed.
    """
    p = check_video_path(path)
    with needs_extra("viz", "writing videos"):
        import imageio.v2 as imageio

        if p.suffix.lower() == ".mp4":
            import imageio_ffmpeg  # noqa: F401  (the ffmpeg binary imageio's FFMPEG plugin runs)
    if not 0 < fps <= 240:
        raise ConfigError(f"video fps must be in (0, 240], got {fps}")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_beside(p)
    try:
        if p.suffix.lower() == ".mp4":
            # macro_block_size 8: 480- and 360-pixel sides are encoded as they are (no silent resize)
            writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7,
                                        macro_block_size=8, pixelformat="yuv420p")
        else:
            writer = imageio.get_writer(tmp, format="GIF", mode="I", duration=1000.0 / fps, loop=0)
        shape = None
        try:
            for f in frames:
                f = np.asarray(f)
                shape = f.shape if shape is None else shape
                if len(shape) != 3 or shape[2] != 3 or f.shape != shape or f.dtype != np.uint8:
                    raise ConfigError(f"video {p}: frames must all be (H, W, 3) uint8 images of one size, "
                                      f"got {f.shape} {f.dtype} after {shape}")
                writer.append_data(f)
            if shape is None:
                raise ConfigError(f"video {p}: no frames to write")
        finally:
            writer.close()
        publish(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return p


def record_video(env: Any, policy_fn: Callable[[np.ndarray], np.ndarray], path: str | os.PathLike, *,
                 seed: int | None = None, options: dict[str, Any] | None = None, color_by: str = "strain",
                 width: int = 640, height: int = 480, gif_fps: float = 10.0,
                 still: str | os.PathLike | None = None) -> dict[str, Any]:
    """Run one episode of ``policy_fn(obs) -> action`` on ``env`` and write it as a video.

    An mp4 gets every agent step at the agent rate (~30 fps, real time); a GIF every k-th step at about
    ``gif_fps`` (still real time, a smaller file). ``still``: also write the episode's last frame (its
    outcome) as a PNG. Returns a summary (path, frames, steps, success).
    """
    from .render import render_rgb

    p = check_video_path(path)
    if still is not None:
        check_still_path(still)
    core = env.unwrapped.core
    obs, info = env.reset(seed=seed, options=options)
    agent_fps = 1.0 / core.config.agent_dt_s
    every = 1 if p.suffix.lower() == ".mp4" else max(1, int(round(agent_fps / gif_fps)))
    run = {"steps": 0, "frames": 0, "info": info, "last": None}

    def frames():  # rendered while the encoder consumes them: the reset state, every k-th step, the last
        nonlocal obs
        done = False
        while True:
            if run["steps"] % every == 0 or done:
                run["last"] = render_rgb(core, 0, width, height, color_by)
                run["frames"] += 1
                yield run["last"]
            if done:
                return
            obs, _, terminated, truncated, run["info"] = env.step(policy_fn(obs))
            run["steps"] += 1
            done = terminated or truncated

    write_video(frames(), p, agent_fps / every)
    summary = {"path": str(p), "frames": run["frames"], "steps": run["steps"], "fps": agent_fps / every,
               "success": bool(run["info"].get("is_success", False))}
    if still is not None:
        with needs_extra("viz", "writing stills"):
            import imageio.v3 as iio
        summary["still"] = str(atomic_write(still, lambda tmp: iio.imwrite(tmp, run["last"], extension=".png")))
    return summary


def read_video(path: str | os.PathLike) -> np.ndarray:
    """(n_frames, H, W, 3) uint8 frames of an mp4 or GIF (for tests and notebooks)."""
    with needs_extra("viz", "reading videos"):
        import imageio.v2 as imageio
    p = Path(path)
    if p.suffix.lower() == ".gif":
        frames = imageio.mimread(p, memtest=False)
        return np.stack([np.asarray(f)[..., :3] for f in frames])
    reader = imageio.get_reader(p, format="FFMPEG")
    try:
        return np.stack([np.asarray(f) for f in reader])
    finally:
        reader.close()
