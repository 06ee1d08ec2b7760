"""``msdgrasp replay FILE``: open a recorded episode (``.rrd``) in the rerun viewer shipped with rerun-sdk.

Recordings are written by :class:`msdgrasp.envs.recording.RerunRecorder` (``msdgrasp record``,
``msdgrasp evaluate --record``). The native viewer needs a display; ``--web`` serves the web viewer
instead (``http://localhost:9090`` by default; tests/test_replay_web.py opens it in headless Chromium).
Equivalent to ``rerun FILE`` / ``rerun --web-viewer FILE``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from .errors import UsageError

RRD_MAGIC = b"RRF"


def _usage_error(message: str) -> Exception:
    return UsageError(message)


def rerun_executable() -> str:
    """Path of the ``rerun`` binary of the installed rerun-sdk (the ``rerun_cli`` package), else on PATH.

    The binary is called directly: ``python -m rerun_cli`` (0.41) discards the viewer's exit status.
    """
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun.exe" if sys.platform.startswith("win") else "rerun")
        if exe.is_file():
            return str(exe)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found is None:
        raise _usage_error("the rerun viewer is not installed: pip install 'msdgrasp[viz]'")
    return found


def check_recording(path: str | os.PathLike) -> Path:
    """The recording's path, or a clear error if it is missing, a folder, empty or not an .rrd file."""
    p = Path(path)
    if not p.exists():
        raise _usage_error(f"recording not found: {p}")
    if p.is_dir():
        raise _usage_error(f"{p} is a folder, not a recording (.rrd file)")
    with open(p, "rb") as fh:
        head = fh.read(len(RRD_MAGIC))
    if not head:
        raise _usage_error(f"recording {p} is empty")
    if p.suffix == ".rrd" and head != RRD_MAGIC:
        raise _usage_error(f"{p} is not a rerun recording (no RRF header)")
    return p


def _check_port(name: str, port: int | None) -> None:
    if port is not None and not (isinstance(port, int) and 1 <= port <= 65535):
        raise _usage_error(f"{name} must be a TCP port in 1-65535, got {port!r}")


def viewer_command(path: str | os.PathLike, web: bool = False, port: int | None = None,
                   grpc_port: int | None = None) -> list[str]:
    """The ``rerun`` command line. With ``web``: the web viewer over HTTP on ``port`` (rerun's default
    9090) and the gRPC server it streams the recording from on ``grpc_port`` (rerun's default 9876)."""
    _check_port("--port", port)
    _check_port("--grpc-port", grpc_port)
    if not web and (port is not None or grpc_port is not None):
        raise _usage_error("--port and --grpc-port need --web (the native viewer serves nothing)")
    if (port or 9090) == (grpc_port or 9876):
        raise _usage_error(f"--port and --grpc-port are both {port or 9090}: the viewer page and the data it streams "
                           "need two ports")
    cmd = [rerun_executable()]
    if web:
        cmd.append("--web-viewer")
        if port is not None:
            cmd += ["--web-viewer-port", str(int(port))]
        if grpc_port is not None:
            cmd += ["--port", str(int(grpc_port))]
    return [*cmd, str(path)]


def web_viewer_url(port: int | None = None, grpc_port: int | None = None, host: str = "127.0.0.1") -> str:
    """The address to open in a browser for ``replay --web`` (the viewer page, told where the data is)."""
    return (f"http://{host}:{port or 9090}/?url=rerun%2Bhttp%3A%2F%2F{host}%3A{grpc_port or 9876}%2Fproxy")


def add_replay_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The ``replay`` subcommand's arguments (for the CLI)."""
    p.add_argument("file", type=Path, help="recording (.rrd) written by `msdgrasp record` or `evaluate --record`")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead of opening the native one")
    p.add_argument("--port", type=int, default=None, help="web viewer port (with --web; default 9090)")
    p.add_argument("--grpc-port", type=int, default=None,
                   help="port of the gRPC server the web viewer loads the recording from (with --web; default 9876)")
    p.add_argument("--print-command", action="store_true", help="print the viewer command and exit")
    return p


def replay_cli(args: argparse.Namespace) -> int:
    """Open ``args.file`` in the rerun viewer; returns the viewer's exit status.

    Raises the CLI's UsageError (exit status 2, one line) when the file is missing or not a recording, or
    when no display is available for the native viewer.
    """
    path = check_recording(getattr(args, "file"))
    web = bool(getattr(args, "web", False))
    port, grpc_port = getattr(args, "port", None), getattr(args, "grpc_port", None)
    cmd = viewer_command(path, web=web, port=port, grpc_port=grpc_port)
    if getattr(args, "print_command", False):
        print(" ".join(cmd))
        return 0
    if web:
        print(f"msdgrasp replay: open {web_viewer_url(port, grpc_port)} in a browser", file=sys.stderr, flush=True)
    if (not web and sys.platform.startswith("linux")
            and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))):
        raise _usage_error(
            f"no display for the native viewer (DISPLAY and WAYLAND_DISPLAY unset): use --web, or copy {path} to a "
            f"machine with a display and run `rerun {path.name}`"
        )
    try:
        return subprocess.call(cmd)
    except KeyboardInterrupt:
        return 130
