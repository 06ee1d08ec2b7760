"""Where independent jobs run: local worker processes (the default) or Ray (``--ray`` / ``--address``).

Multi-seed training, hyper-parameter sweeps and evaluation sweeps are bags of independent jobs (one seed's
training, one (policy, mu) cell). :class:`Runner` runs such a bag and hands back each job's result as it
finishes; what differs between a laptop and a cluster is only the runner:

* ``Runner.processes(workers)``: a spawn-context process pool on the local machine (no extra dependency);
* ``Runner.ray(address=None, workers=None)``: Ray tasks of one CPU each. Without an address Ray starts a
  local instance with ``workers`` CPUs (default: all cores); with one (``auto``, ``ray://head:10001`` or
  ``head:6379``) the jobs go to that cluster, whose nodes need msdgrasp installed (same version).

Results land in one place, the driver's output folder, on a cluster too: a job that writes files gets its
folder through :func:`run_in_folder`; on the driver's node it writes there directly, on another node it
writes into a temporary folder that travels back as a tar archive, and the driver unpacks it into place
(paths that point into the temporary folder are rewritten to the final one, in the job's result and in the
JSON files it wrote: a run's ``train_summary.json`` and ``validation.json`` name its models).

Ray's usage-statistics upload is switched off unless ``RAY_USAGE_STATS_ENABLED`` is set.
"""

from __future__ import annotations

import io
import json
import os
import sys
import tarfile
import tempfile
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from ..physics.config import ConfigError, atomic_write_text

#: a job: a module-level function (picklable by reference) and its positional arguments
Job = tuple[Callable[..., Any], tuple]

_ARCHIVE_KEY = "__folder_archive__"


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    return fn(*args)


def _one_thread() -> None:
    """A pool worker's initializer: torch on one intra-op thread, the workers being the parallelism (two recurrent
    seeds, each with torch's default of one thread per core, ran five times slower on two cores than with one). It
    overrides an ``OMP_NUM_THREADS`` of the caller's: more threads per worker only contend with the other workers."""
    os.environ["OMP_NUM_THREADS"] = "1"  # (read when torch is imported, which a spawned worker has not yet done)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _check_workers(workers: int | None) -> None:
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"--workers must be an integer >= 1, got {workers!r}")


class Runner:
    """Runs independent jobs in parallel; see the module docstring. Use as a context manager."""

    def __init__(self, kind: str, workers: int | None = None, address: str | None = None) -> None:
        if kind not in ("processes", "ray"):
            raise ConfigError(f"runner kind must be 'processes' or 'ray', got {kind!r}")
        _check_workers(workers)
        if address is not None and kind != "ray":
            raise ConfigError("--address names a Ray cluster; it needs the Ray runner")
        if address is not None and not str(address).strip():
            raise ConfigError("--address is empty; give 'auto', host:port or ray://host:port")
        self.kind, self.workers, self.address = kind, workers, address
        self._pool: ProcessPoolExecutor | None = None
        self._started_ray = False
        self.driver_node: str | None = None

    @classmethod
    def processes(cls, workers: int | None = None) -> "Runner":
        return cls("processes", workers)

    @classmethod
    def ray(cls, address: str | None = None, workers: int | None = None) -> "Runner":
        return cls("ray", workers, address)

    @property
    def is_ray(self) -> bool:
        return self.kind == "ray"

    @property
    def label(self) -> str:
        """Where the jobs run, for reports: 'processes', 'ray' or 'ray (<address>)'."""
        return self.kind if self.address is None else f"{self.kind} ({self.address})"

    def __enter__(self) -> "Runner":
        if self.is_ray:
            self._start_ray()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start_ray(self) -> None:
        try:
            import ray
        except ImportError:
            raise ConfigError("--ray / --address need Ray: pip install 'msdgrasp[ray]'") from None
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True,
                                      "configure_logging": False}
            if self.address is None:
                kwargs["num_cpus"] = self.workers or os.cpu_count() or 1
            else:
                kwargs["address"] = self.address
            try:
                ray.init(**kwargs)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                where = f"--address {self.address}" if self.address else "a local Ray instance"
                raise ConfigError(f"{where}: Ray could not start or connect ({str(exc).splitlines()[0]})") from None
            self._started_ray = True
        self.driver_node = ray.get_runtime_context().get_node_id()

    def capacity(self) -> int:
        """How many one-CPU jobs run at once."""
        if self.is_ray:
            import ray

            return max(1, int(ray.cluster_resources().get("CPU", 1)))
        return self.workers or os.cpu_count() or 1

    def run(self, jobs: Sequence[Job], on_done: Callable[[int, Any], None] | None = None) -> list[Any]:
        """Run every job; return their results in job order. ``on_done(index, result)`` is called as each
        finishes (in completion order). A job's exception is raised here (the others are cancelled)."""
        results: list[Any] = [None] * len(jobs)
        for k, res in self._completed(jobs):
            results[k] = res
            if on_done is not None:
                on_done(k, res)
        return results

    def _completed(self, jobs: Sequence[Job]) -> Iterator[tuple[int, Any]]:
        if not jobs:
            return
        if self.is_ray:
            import ray

            if self.driver_node is None:
                self._start_ray()
            # one remote function for every job: any picklable callable runs (builtins too); one CPU each, and
            # a failed job is not retried (the error is the answer)
            call = ray.remote(num_cpus=1, max_retries=0)(_call)
            refs = {call.remote(fn, *args): k for k, (fn, args) in enumerate(jobs)}
            pending = list(refs)
            try:
                while pending:
                    done, pending = ray.wait(pending, num_returns=1)
                    yield refs[done[0]], ray.get(done[0])
            finally:
                for ref in pending:
                    ray.cancel(ref, force=True)
            return
        if self._pool is None:
            # spawn: fork would copy torch/numba thread pools into the workers
            self._pool = ProcessPoolExecutor(max_workers=self.capacity(), mp_context=get_context("spawn"),
                                             initializer=_one_thread)
        futures = {self._pool.submit(fn, *args): k for k, (fn, args) in enumerate(jobs)}
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield futures[fut], fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
        if self._started_ray:
            import ray

            ray.shutdown()
            self._started_ray = False
        self.driver_node = None


# ------------------------------------------------------------------------------------------------
# jobs that write a folder
# ------------------------------------------------------------------------------------------------


def run_jobs(jobs: Sequence[Job], runner: "Runner | None",
             on_done: Callable[[int, Any], None] | None = None) -> list[Any]:
    """Every job's result in job order: with ``runner`` (entered by the caller) its :meth:`Runner.run`, without one in
    this process, one after the other; ``on_done(index, result)`` as each finishes."""
    if runner is not None:
        return runner.run(jobs, on_done=on_done)
    out = []
    for k, (fn, args) in enumerate(jobs):
        out.append(fn(*args))
        if on_done is not None:
            on_done(k, out[-1])
    return out


def _current_node() -> str | None:
    """The Ray node this code runs on, or None outside a Ray worker."""
    try:
        import ray
    except ImportError:
        return None
    if not ray.is_initialized():
        return None
    return ray.get_runtime_context().get_node_id()


def rewrite_paths(value: Any, old: str, new: str) -> Any:
    """``value`` (a JSON-like tree) with every string that is path ``old`` or lies under it moved to ``new``
    (whole path parts only: ``old + "x"`` stays)."""
    if isinstance(value, str):
        return new + value[len(old):] if value == old or value.startswith(old + os.sep) else value
    if isinstance(value, dict):
        return {k: rewrite_paths(v, old, new) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(rewrite_paths(v, old, new) for v in value)
    return value


def move_paths(result: Any, folder: str | Path, old: str, new: str) -> Any:
    """``result`` with its paths under ``old`` moved to ``new`` (:func:`rewrite_paths`), and the same done in
    every JSON file under ``folder`` (a job's files that name where they were written, now elsewhere). A file
    there that is not JSON is an error, never skipped."""
    for path in sorted(Path(folder).rglob("*.json")):
        try:
            data = json.loads(path.read_text())
        except ValueError as exc:
            raise ConfigError(f"{path}: not JSON ({exc})") from None
        moved = rewrite_paths(data, old, new)
        if moved != data:
            atomic_write_text(path, json.dumps(moved, indent=2))
    return rewrite_paths(result, old, new)


def pack(root: str | Path, paths: Sequence[str | Path]) -> bytes:
    """``paths`` (files or folders under ``root``) as a tar.gz archive, named relative to ``root``. Links are
    stored as what they point to: an archive holds regular files and folders only, all :func:`unpack` takes."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", dereference=True) as tar:
        for path in paths:
            tar.add(path, arcname=str(Path(path).relative_to(root)))
    return buf.getvalue()


def _has_data_filter() -> bool:
    """Whether this Python's tarfile has extraction filters (3.11.4+, 3.12); 3.11.0-3.11.3 lack them."""
    return hasattr(tarfile, "data_filter")


def _check_member(member: tarfile.TarInfo, dest: Path, where: str) -> None:
    """A member of a job archive is a regular file or a folder that lands inside ``dest``: no absolute path
    (which the "data" filter would only strip), no ``..``, no path through a link already in ``dest``, and no
    link, device or fifo. Links are refused outright, not checked for where they point: a target judged
    before extraction can change meaning once an earlier member is a link itself (``b -> .``, then
    ``a -> b/..`` leaves the folder), and :func:`pack` stores none."""
    name = member.name
    bad = None
    if name.startswith(("/", "\\")) or Path(name).is_absolute() or os.path.splitdrive(name)[0]:
        bad = "an absolute path"
    elif ".." in Path(name).parts:
        bad = "a '..' component"
    elif not (dest / name).resolve().is_relative_to(dest):
        bad = "a path outside the folder"
    elif member.issym() or member.islnk():
        bad = f"a link (to {member.linkname!r})"
    elif member.isdev():  # character or block device, fifo
        bad = "a device or fifo"
    elif not (member.isfile() or member.isdir()):
        bad = "an unsupported member type"
    if bad is not None:
        raise ConfigError(f"{where}: member {name!r} has {bad}; refused")


def _as_data(member: tarfile.TarInfo) -> None:
    """What tarfile's "data" filter changes on a checked member, for Pythons without it: no set-id or sticky
    bits and no write access for group and others; a file readable and writable by its owner, executable by
    the others only where by its owner; owned by the user who unpacks (the archive's owner is ignored)."""
    mode = member.mode & 0o755
    if member.isfile():
        if not mode & 0o100:
            mode &= ~0o111
        mode |= 0o600
    member.mode = mode
    if hasattr(os, "getuid"):  # (tarfile sets owners only on POSIX, as root)
        member.uid, member.gid, member.uname, member.gname = os.getuid(), os.getgid(), "", ""


def unpack(archive: bytes, folder: str | Path, source: str = "job archive") -> None:
    """Unpack a :func:`pack` archive into ``folder`` (made if missing).

    Nothing may land outside ``folder``: absolute paths, ``..`` components, paths through a link, links,
    devices and fifos are refused with a :class:`ConfigError` naming ``source`` (the archive) and the member,
    before anything is written. Extraction then goes through tarfile's "data" filter where it has one
    (Python >= 3.11.4); 3.11.0-3.11.3 lack it, and there :func:`_as_data` sets the modes and owners as that
    filter would."""
    dest = Path(folder).resolve()
    where = f"{source} for {folder}"
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r:gz") as tar:
        members = tar.getmembers()
        for member in members:
            _check_member(member, dest, where)
        dest.mkdir(parents=True, exist_ok=True)
        if _has_data_filter():
            try:
                tar.extractall(dest, filter="data")
            except tarfile.FilterError as exc:  # anything the checks above let through
                raise ConfigError(f"{where}: member {exc.tarinfo.name!r} refused ({exc})") from None
        else:
            for member in members:
                _as_data(member)
            tar.extractall(dest, members=members)


def run_in_folder(fn: Callable[..., dict[str, Any]], folder: str, driver_node: str | None,
                  *args: Any) -> dict[str, Any]:
    """Run ``fn(folder, *args)`` (a job body that writes into ``folder`` and returns a dict).

    On the driver's node (or outside Ray) it writes ``folder`` directly. On another node it writes a
    temporary folder, packs it as a tar archive into the result and moves the paths in the result and in its
    JSON files to ``folder``; :func:`land` unpacks it on the driver."""
    node = _current_node()
    if driver_node is None or node is None or node == driver_node:
        return fn(folder, *args)
    with tempfile.TemporaryDirectory(prefix="msdgrasp-job-") as tmp:
        result = move_paths(fn(tmp, *args), tmp, tmp, folder)
        archive = pack(tmp, [tmp])
    return {**result, _ARCHIVE_KEY: archive}


def land(result: dict[str, Any], folder: str | Path) -> dict[str, Any]:
    """Unpack a job's folder archive (if it came from another node) into ``folder``; the result without it."""
    archive = result.get(_ARCHIVE_KEY)
    if archive is None:
        return result
    unpack(archive, folder)
    return {k: v for k, v in result.items() if k != _ARCHIVE_KEY}
