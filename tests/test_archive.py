"""Job archives (agents.parallel.pack / unpack): how a job's folder travels from another node to the driver.

The specification: a packed folder comes back byte for byte; an archive holds regular files and folders only,
and any member that is something else or would land outside the folder is refused, naming it, before anything
is written. Unpacking uses tarfile's "data" filter where Python has it (3.11.4+) and its own equivalent where it
does not (3.11.0-3.11.3, Debian 12's 3.11.2): both paths run here, the second with the filter hidden.
"""

from __future__ import annotations

import io
import os
import stat
import tarfile
from pathlib import Path

import pytest

from msdgrasp.agents import parallel
from msdgrasp.physics.config import ConfigError

PATHS = ["data_filter", "own_checks"]


@pytest.fixture(params=PATHS)
def path_taken(request, monkeypatch) -> str:
    """Unpack through tarfile's "data" filter or through the equivalent used where it is missing."""
    if request.param == "data_filter" and not parallel._has_data_filter():
        pytest.skip("this Python's tarfile has no extraction filters")
    monkeypatch.setattr(parallel, "_has_data_filter", lambda: request.param == "data_filter")
    return request.param


def _tar(*members: tuple[str, str, bytes | str | None], mode: int = 0o644) -> bytes:
    """A tar.gz of (name, kind, data) members, names taken as given: kind "file" (data: bytes), "dir",
    "symlink" / "hardlink" (data: the link's target), "fifo" or "chardev"."""
    kinds = {"dir": tarfile.DIRTYPE, "symlink": tarfile.SYMTYPE, "hardlink": tarfile.LNKTYPE,
             "fifo": tarfile.FIFOTYPE, "chardev": tarfile.CHRTYPE}
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, kind, data in members:
            info = tarfile.TarInfo(name)
            info.mode = mode
            if kind == "file":
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
                continue
            info.type = kinds[kind]
            if kind in ("symlink", "hardlink"):
                info.linkname = data
            tar.addfile(info)
    return buf.getvalue()


def test_a_packed_folder_comes_back_byte_for_byte(tmp_path, path_taken):
    src = tmp_path / "src"
    (src / "sub").mkdir(parents=True)
    (src / "a.txt").write_text("alpha")
    (src / "sub" / "b.bin").write_bytes(bytes(range(256)))
    (src / "sub" / "run.sh").write_text("#!/bin/sh\n")
    (src / "sub" / "run.sh").chmod(0o755)
    out = tmp_path / "out"
    parallel.unpack(parallel.pack(src, [src / "a.txt", src / "sub"]), out)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["a.txt", "sub", "sub/b.bin",
                                                                             "sub/run.sh"]
    assert (out / "a.txt").read_text() == "alpha" and (out / "sub" / "b.bin").read_bytes() == bytes(range(256))
    assert os.access(out / "sub" / "run.sh", os.X_OK)


def test_pack_stores_a_link_as_what_it_points_to(tmp_path, path_taken):
    src = tmp_path / "src"
    src.mkdir()
    (src / "model.zip").write_bytes(b"weights")
    (src / "best_model.zip").symlink_to("model.zip")
    archive = parallel.pack(src, [src / "model.zip", src / "best_model.zip"])
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        assert all(m.isfile() for m in tar.getmembers())
    parallel.unpack(archive, tmp_path / "out")
    best = tmp_path / "out" / "best_model.zip"
    assert not best.is_symlink() and best.read_bytes() == b"weights"


def _refused(tmp_path: Path) -> dict[str, tuple[bytes, str]]:
    """Archive per refused member: (archive, what the message says the member has). Each archive starts with a
    harmless member, which must not be written either."""
    ok = ("ok.txt", "file", b"ok")
    return {
        "../evil": (_tar(ok, ("../evil", "file", b"x")), "a '..' component"),
        str(tmp_path / "abs_evil"): (_tar(ok, (str(tmp_path / "abs_evil"), "file", b"x")), "an absolute path"),
        "up": (_tar(ok, ("up", "symlink", "../../outside")), "a link (to '../../outside')"),
        "inside": (_tar(ok, ("inside", "symlink", "ok.txt")), "a link (to 'ok.txt')"),
        # each link points inside when judged before extraction, yet a/evil would land beside the folder
        "b": (_tar(ok, ("b", "symlink", "."), ("a", "symlink", "b/.."), ("a/evil", "file", b"x")), "a link"),
        "hard": (_tar(ok, ("hard", "hardlink", "ok.txt")), "a link (to 'ok.txt')"),
        "pipe": (_tar(ok, ("pipe", "fifo", None)), "a device or fifo"),
        "tty": (_tar(ok, ("tty", "chardev", None)), "a device or fifo"),
    }


def test_members_that_are_not_plain_files_and_folders_inside_are_refused_before_anything_is_written(
        tmp_path, path_taken):
    dest = tmp_path / "sub" / "bad"
    for member, (archive, has) in _refused(tmp_path).items():
        with pytest.raises(ConfigError) as err:
            parallel.unpack(archive, dest)
        message = str(err.value)
        assert message.startswith(f"job archive for {dest}: member {member!r} has {has}"), message
        assert message.endswith("; refused") and "\n" not in message
        assert not dest.exists() and not (tmp_path / "sub" / "evil").exists()
        assert not (tmp_path / "evil").exists() and not (tmp_path / "abs_evil").exists()


def test_a_path_through_a_link_already_in_the_folder_is_refused(tmp_path, path_taken):
    dest = tmp_path / "dest"
    dest.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (dest / "sub").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ConfigError, match=r"member 'sub/x' has a path outside the folder; refused$"):
        parallel.unpack(_tar(("sub/x", "file", b"x")), dest)
    assert list((tmp_path / "elsewhere").iterdir()) == []


def test_modes_and_owners_are_the_data_filters_on_both_paths(tmp_path, path_taken):
    """Set-id, sticky and group/other write bits are dropped; a file stays readable and writable by its owner
    and executable by the others only where by its owner; the unpacking user owns what it unpacks."""
    out = tmp_path / "out"
    parallel.unpack(_tar(("s.bin", "file", b"s"), mode=0o6777), out)
    parallel.unpack(_tar(("r.txt", "file", b"r"), mode=0o055), out)
    assert stat.S_IMODE((out / "s.bin").stat().st_mode) == 0o755
    assert stat.S_IMODE((out / "r.txt").stat().st_mode) == 0o644
    if hasattr(os, "getuid"):
        assert (out / "s.bin").stat().st_uid == os.getuid()
