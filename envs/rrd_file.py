"""One rerun output file, written safely: a :class:`RrdSink` logs into a temp file ``.NAME.XXXX.part`` next
to the destination and :meth:`RrdSink.commit` fsyncs it, checks it with rerun's own reader and renames it
onto the destination (so the destination never holds a partial recording). Failures raise
:class:`RecordingError` (an ``OSError``) naming the path.
"""

from __future__ import annotations

import os
import uuid
import warnings
import weakref
from pathlib import Path
from typing import Any

from ..physics.config import needs_extra, publish, temp_beside

APPLICATION_ID = "msdgrasp"


class RecordingError(OSError):
    """A recording cannot be written (unusable path, I/O failure, rerun failure)."""

    def __init__(self, message: str, path: str | os.PathLike | None = None) -> None:
        super().__init__(message)
        self.filename = None if path is None else str(path)

    def __str__(self) -> str:
        return str(self.args[0])


class RecordingWarning(UserWarning):
    """A recording failed with ``on_error="warn"``: the recording was dropped, the env runs on."""




def recording_error(message: str, path, exc: BaseException | None = None) -> RecordingError:
    """A RecordingError for ``path`` whose message ends with the cause's ``strerror`` (or text)."""
    detail = ""
    if exc is not None:
        detail = f": {getattr(exc, 'strerror', None) or exc}"
    return RecordingError(f"{message}{detail}", path)


def _prepare_destination(path: Path) -> None:
    """Raise RecordingError unless a file can be created at ``path`` (creates missing folders)."""
    if path.is_dir():
        raise RecordingError(f"cannot record to {path}: it is a directory", path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise recording_error(f"cannot record to {path}: cannot create its folder {path.parent}", path, exc) from None
    if not path.parent.is_dir():
        raise RecordingError(f"cannot record to {path}: {path.parent} is not a folder", path)


def check_destination(path: Path) -> None:
    """Raise RecordingError unless a recording can be written at ``path`` (a temp file is created beside
    it and removed again)."""
    _prepare_destination(path)
    _make_temp(path).unlink()


def _make_temp(path: Path) -> Path:
    try:
        return temp_beside(path, suffix=".part")
    except OSError as exc:
        raise recording_error(f"cannot record to {path}: cannot create a file in {path.parent}", path, exc) from None


class RrdSink:
    """A RecordingStream writing to a temp file that becomes ``path`` on :meth:`commit`."""

    def __init__(self, path: Path, name: str) -> None:
        with needs_extra("viz", "rerun recordings"):
            import rerun as rr

        self.path = path
        _prepare_destination(path)
        self.tmp = _make_temp(path)
        self.episodes: list[str] = []
        try:
            self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4(), default_enabled=True)
            if not self.rec.is_enabled():
                raise RecordingError(
                    f"cannot record to {path}: rerun logging is disabled (environment variable RERUN=off)", path
                )
            self.rec.save(str(self.tmp))
            self.rec.set_log_time_enabled(False)
            self.rec.set_log_tick_enabled(False)
            self.rec.send_recording_name(name)
        except RecordingError:
            self.tmp.unlink(missing_ok=True)
            raise
        except Exception as exc:
            self.tmp.unlink(missing_ok=True)
            raise recording_error(f"cannot record to {path}: rerun could not open the file sink", path, exc) from None
        # garbage-collected unfinished (no close()): remove the temp file. Not at interpreter exit, where
        # the recorder's own atexit hook finishes the file instead.
        self._gc = weakref.finalize(self, _discard_unfinished, self.rec, self.tmp, path)
        self._gc.atexit = False

    def log(self, *args: Any, **kwargs: Any) -> None:
        """``RecordingStream.log`` in strict mode: bad data raises instead of a logged warning."""
        self.rec.log(*args, strict=True, **kwargs)

    def commit(self, blueprint) -> Path:
        """Finish the file (footer), check it, and move it onto the destination atomically."""
        from rerun.chunk import RrdReader

        try:
            if blueprint is not None:
                self.rec.send_blueprint(blueprint, make_active=True, make_default=True)
            self.rec.flush()
            self.rec.disconnect()  # writes the footer and closes the file
            if not self.tmp.is_file():
                raise RecordingError(f"recording {self.path} failed: its temp file {self.tmp} disappeared", self.path)
            with open(self.tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            if not RrdReader(self.tmp).recordings():  # raises on a truncated/corrupt file
                raise RecordingError(f"recording {self.path} failed: the written file holds no recording", self.path)
            publish(self.tmp, self.path)
            self._gc.detach()
        except RecordingError:
            self.discard()
            raise
        except Exception as exc:
            self.discard()
            raise recording_error(f"recording {self.path} failed while finishing the file", self.path, exc) from None
        return self.path

    def discard(self) -> None:
        self._gc.detach()
        try:
            self.rec.disconnect()
        except Exception:  # noqa: BLE001 - best effort
            pass
        self.tmp.unlink(missing_ok=True)


def _discard_unfinished(rec, tmp: Path, path: Path) -> None:
    try:
        rec.disconnect()
    except Exception:  # noqa: BLE001 - best effort
        pass
    tmp.unlink(missing_ok=True)
    warnings.warn(f"rerun recording {path} dropped: its recorder was garbage-collected without close()",
                  RecordingWarning, stacklevel=2)
