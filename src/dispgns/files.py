"""Files and directories written whole or not at all (the one atomic-write helper).

Everything dispgns writes (datasets, checkpoints' small files, exported
models, pictures) is first written under a temporary name beside its target
(same directory, same file system) and renamed into place only when complete:
an interruption leaves the old file or nothing, never half a file. Temporary
names start with ``.<target name>.``, contain ``.tmp`` and the writing
process's id; a process killed outright (SIGKILL, power loss) cannot remove
its own, and :func:`remove_leftovers` removes them on the next run once that
process is gone.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["atomic_path", "check_output_directory", "leftovers", "remove_leftovers", "staged_directory", "write_atomic"]


def _umask() -> int:
    """The process's umask, read without changing it where the system allows.

    Setting it to read it (the portable way) opens a moment in which files
    that other threads create (checkpoint writers run in threads) get no
    umask; Linux reports it in ``/proc/self/status``.
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):  # no /proc, or a line not in the expected form
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` when the block ends without error.

    The temporary name keeps ``path``'s extension (writers such as Pillow,
    ffmpeg and matplotlib infer the format from it). On any error, an
    interruption included, the temporary file is removed and ``path`` is
    untouched. The file gets the usual permissions (``0o666`` less the umask).
    """
    path = Path(path).absolute()
    suffix = path.suffix
    temporary = path.parent / f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:12]}.tmp{suffix}"
    try:
        yield temporary
        if temporary.exists():
            os.chmod(temporary, 0o666 & ~_umask())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def write_atomic(path: str | os.PathLike, data: bytes | str | Callable[[Path], None]) -> Path:
    """Write ``data`` (bytes, text, or a ``write(temporary_path)`` callable) to ``path`` atomically."""
    path = Path(path)
    with atomic_path(path) as temporary:
        if callable(data):
            data(temporary)
        elif isinstance(data, str):
            temporary.write_text(data)
        else:
            temporary.write_bytes(data)
    return path


_PID = re.compile(r"(?:^|[.-])(\d+)-[0-9a-z_]+(?:\.tmp|$)")


def _writer_alive(name: str) -> bool:
    """Whether the process that made the temporary ``name`` still runs (names without a pid: no)."""
    match = _PID.search(name)
    if match is None:
        return False
    pid = int(match.group(1))
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


def leftovers(target: str | os.PathLike) -> list[Path]:
    """Temporary files and folders that writes of ``target`` left beside it and whose writer is gone."""
    target = Path(target).absolute()
    try:
        entries = list(target.parent.iterdir())
    except OSError:
        return []
    prefix = f".{target.name}."
    return sorted(p for p in entries if _temporary_of(p.name, prefix) and not _writer_alive(p.name))


def _temporary_of(name: str, prefix: str) -> bool:
    """Whether ``name`` is one of this module's temporary names for the target that ``prefix`` starts."""
    rest = name[len(prefix) :] if name.startswith(prefix) else ""
    return rest.startswith("tmp-") or ".tmp" in rest


def remove_leftovers(target: str | os.PathLike) -> list[tuple[Path, str]]:
    """Remove what interrupted writes of ``target`` left beside it; returns ``[(path, what was done)]``.

    A previous complete ``target`` set aside during a replacement (``.old-``)
    is put back when ``target`` itself is missing (the kill came between the
    two renames), and removed otherwise. Temporaries of a process that still
    runs are left alone. Errors (a read-only folder) leave the entry in place.
    """
    target = Path(target).absolute()
    done = []
    for path in leftovers(target):
        try:
            if ".old-" in path.name and not target.exists():
                os.replace(path, target)
                done.append((path, f"restored as {target}"))
            elif path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
                done.append((path, "removed"))
            else:
                path.unlink()
                done.append((path, "removed"))
        except OSError:
            continue
    return done


def check_output_directory(out_dir: str | os.PathLike, overwrite: bool, marker: str, kind: str) -> None:
    """Raise ``FileExistsError`` unless ``out_dir`` is missing, empty, or (``overwrite``) a ``kind`` with ``marker``.

    :func:`staged_directory` checks this itself; call it first to refuse before a long computation.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() or out_dir.is_symlink():
        if not out_dir.is_dir():
            raise FileExistsError(f"{out_dir} exists and is not a directory")
        if any(out_dir.iterdir()):
            if not overwrite:
                raise FileExistsError(
                    f"{out_dir} exists and is not empty; choose another directory or allow overwriting it"
                )
            if not (out_dir / marker).is_file():
                raise FileExistsError(f"refusing to overwrite {out_dir}: it is not a dispgns {kind} (no {marker})")


def _move_into_place(staging: Path, out_dir: Path) -> None:
    """Rename the finished ``staging`` directory to ``out_dir`` (replacing an old one)."""
    if out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    if not out_dir.exists():
        os.replace(staging, out_dir)
        return
    old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp"
    os.replace(out_dir, old)
    try:
        os.replace(staging, out_dir)
    except BaseException:
        os.replace(old, out_dir)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def staged_directory(out_dir: str | os.PathLike, *, overwrite: bool = False, marker: str, kind: str) -> Iterator[Path]:
    """Build an output directory atomically.

    Yields a fresh temporary directory beside ``out_dir`` (same file system);
    when the block finishes it is renamed to ``out_dir``, and when the block
    raises it is removed together with any parent directories created for it.

    ``out_dir`` may be missing or empty; a non-empty one is replaced only with
    ``overwrite`` and only if it holds a dispgns ``kind`` (its ``marker``
    file), and only once the new one is complete.

    Raises:
      FileExistsError: ``out_dir`` holds something that may not be replaced.
      OSError: the parent directory cannot be written.
    """
    out_dir = Path(out_dir).absolute()
    check_output_directory(out_dir, overwrite, marker, kind)
    created = []
    for parent in reversed(out_dir.parents):
        if not parent.exists():
            parent.mkdir()
            created.append(parent)
    try:
        staging = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}.tmp-{os.getpid()}-"))
        try:
            # mkdtemp makes the directory private (0700): give it the usual umask permissions.
            os.chmod(staging, 0o777 & ~_umask())
            yield staging
            _move_into_place(staging, out_dir)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        for parent in reversed(created):
            with contextlib.suppress(OSError):
                parent.rmdir()
        raise
