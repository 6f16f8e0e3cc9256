"""Outputs that appear complete or not at all, and never destroy what gcgs did not write.

A folder output (:func:`atomic_dir`) is claimed before any work: the path is checked (not
the current folder or one holding it, not equal to, inside or around an input, not a file,
and, if it exists, either empty or a folder gcgs wrote for the same kind of output, known
by its marker file ``.gcgs-output``), and a lock next to it keeps a second writer out.
The work writes into a temporary sibling folder; on success that folder is swapped in
atomically (Linux ``renameat2(RENAME_EXCHANGE)``; elsewhere the old folder is renamed
aside first and recovered by the next run if a kill falls between the two renames), and
the old output is deleted only after the new one is in place. On any error the temporary
folder is removed and the old output is untouched. Temporary folders a killed run left
behind are removed by the next writer of the same output.

A file output (:func:`atomic_file`) is written to a temporary sibling and renamed over the
target. :func:`check_output_file` refuses, before any work, a target that is a folder, an
input or inside an input folder, or an existing non-empty file gcgs did not write: gcgs
knows its files by the extended attribute ``user.gcgs.output`` it sets on each (their bytes
stay what the writer wrote). Both checks also make sure the output can be created and
swapped into place (a writable folder, not a mount point), so a long run never ends in a
traceback at its last step.

Rerunning into an earlier output folder never deletes what a user added there: every file
of a finished output carries the same mark, and entries of the old folder without it that
the new run does not replace are moved to a sibling ``NAME.kept-*`` folder, with a warning
that says where.
"""
from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline.errors import OutputError, print_warning

MARKER = ".gcgs-output"  # in every finished output folder: JSON {"written_by": "gcgs", "kind": KIND}
PARTIAL = ".gcgs-partial"  # in a temporary folder until it is swapped in
FILE_XATTR = "user.gcgs.output"  # on every file gcgs writes, its kind: lets a later run replace it


def resolved_path(path: str | Path) -> Path:
    """``path`` absolute, user-expanded and with links resolved: the form every overlap check compares."""
    return Path(os.path.abspath(Path(path).expanduser())).resolve()


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def overlapping_inputs(out: Path, inputs: Iterable[str | Path | None]) -> Iterator[tuple[str | Path, str]]:
    """The inputs (as given) that the resolved output path ``out`` overlaps, each with how:
    ``"is"``, ``"lies inside"`` (``out`` is under the input) or ``"holds"`` (the input is under ``out``)."""
    for given in inputs:
        if given is None:
            continue
        src = resolved_path(given)
        if _within(out, src) or _within(src, out):
            yield given, "is" if out == src else ("lies inside" if _within(out, src) else "holds")


def marker_kind(folder: Path) -> str | None:
    """The output kind recorded in ``folder``'s marker, ``None`` without a readable one."""
    try:
        return str(json.loads((folder / MARKER).read_text())["kind"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check_output_dir(out_dir: str | Path, kind: str, inputs: Iterable[str | Path | None] = ()) -> Path:
    """Refuse (:class:`OutputError`, one line) an output folder whose replacement could lose
    data: the current folder or one holding it, a path equal to, inside or holding an input,
    an existing file, or an existing non-empty folder that is not a gcgs ``kind`` output.
    Returns the resolved path. Cheap: stages call it before any long work."""
    out = resolved_path(out_dir)
    cwd = resolved_path(Path.cwd())
    if _within(cwd, out):
        raise OutputError(f"{out_dir}: output folder is the current folder or holds it; "
                          "replacing it would delete the current folder: choose a new folder")
    for given, where in overlapping_inputs(out, inputs):
        raise OutputError(f"{out_dir}: output folder {where} the input {given}; "
                          "writing it would destroy the input: choose another output folder")
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise OutputError(f"{out_dir}: output path exists and is not a folder; remove it or choose another path")
    if out.is_dir() and os.path.ismount(out):
        raise OutputError(f"{out_dir}: output folder is a mount point; a finished output is renamed into place, "
                          "which a mount point refuses: give a folder inside it")
    check_creatable(out, out_dir)
    if out.is_dir() and any(out.iterdir()):
        found = marker_kind(out)
        if found is None:
            raise OutputError(f"{out_dir}: folder exists, is not empty and was not written by gcgs (no {MARKER} "
                              "marker); refusing to replace it: choose a new folder or remove it yourself")
        if found != kind:
            raise OutputError(f"{out_dir}: folder holds a gcgs {found} output, not a {kind} output; "
                              "refusing to replace it: choose another output folder")
    return out


class _OutputLock:
    """An exclusive ``flock`` on ``.NAME.lock`` beside the output, released (and the file
    removed) on exit or when the process dies. Fails at once when another process holds it."""

    def __init__(self, out: Path, shown: str | Path):
        self.path = out.parent / f".{out.name}.lock"
        self.shown = shown
        self.fd: int | None = None

    def __enter__(self) -> _OutputLock:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise OutputError(f"{self.shown}: another gcgs process is writing this output (lock {self.path}); "
                                      "wait for it to finish") from None
                raise
            try:  # the holder before us may have removed the file after we opened it
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self.fd = fd
                return self
            os.close(fd)

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            Path(self.path).unlink(missing_ok=True)  # while still held: no one else holds this inode
            os.close(self.fd)
            self.fd = None


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE); ``False`` where the
    system or file system cannot."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _clean_leftovers(out: Path) -> None:
    """Remove the temporary folders a killed writer of ``out`` left; put back an old output
    that a kill left renamed aside (the non-exchange swap). Called with the lock held."""
    for p in sorted(out.parent.glob(f".{out.name}.old-*")):
        if p.is_dir() and (p / MARKER).is_file():
            if not out.exists():
                os.replace(p, out)
            else:
                shutil.rmtree(p, ignore_errors=True)
    for p in out.parent.glob(f".{out.name}.tmp-*"):
        if p.is_dir() and (p / PARTIAL).is_file():
            shutil.rmtree(p, ignore_errors=True)


def _holds_marked(folder: Path) -> bool:
    return any(written_kind(Path(d) / f) is not None for d, _, files in os.walk(folder) for f in files)


def _foreign_entries(old: Path, new: Path) -> list[Path]:
    """Entries of the earlier output ``old`` that gcgs did not write (no mark) and that the
    new output ``new`` does not replace: a user's notes, edits, extra files and folders."""
    foreign: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(old):
        rel = Path(dirpath).relative_to(old)
        for name in list(dirnames):
            sub = old / rel / name
            if sub.is_symlink() or not ((new / rel / name).is_dir() or _holds_marked(sub)):
                foreign.append(rel / name)  # kept whole
                dirnames.remove(name)
        for name in filenames:
            if rel == Path(".") and name in (MARKER, PARTIAL):
                continue
            if written_kind(old / rel / name) is None and not (new / rel / name).is_file():
                foreign.append(rel / name)
    return foreign


def _keep_foreign(old: Path, new: Path, shown: str | Path) -> None:
    """Move :func:`_foreign_entries` to a sibling ``NAME.kept-*`` folder, so that replacing
    the output never deletes them; warn with the list and the place."""
    foreign = _foreign_entries(old, new)
    if not foreign:
        return
    stamp = time.strftime("%Y%m%d-%H%M%S")
    kept = Path(tempfile.mkdtemp(prefix=f"{old.name}.kept-{stamp}-", dir=old.parent))
    os.chmod(kept, 0o755)
    for rel in foreign:
        (kept / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(old / rel, kept / rel)
    names = ", ".join(str(r) + ("/" if (kept / r).is_dir() else "") for r in foreign[:8])
    more = f" and {len(foreign) - 8} more" if len(foreign) > 8 else ""
    print_warning(f"{shown}: {len(foreign)} entries gcgs did not write were moved to {kept} (not deleted): "
                  f"{names}{more}")


def _swap_in(tmp: Path, out: Path) -> None:
    if not out.exists():
        os.replace(tmp, out)
        return
    if _exchange(tmp, out):
        shutil.rmtree(tmp)  # the old output, now at tmp
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    os.rmdir(aside)
    os.replace(out, aside)
    os.replace(tmp, out)
    shutil.rmtree(aside)


def _unwritable(path: str | Path, exc: OSError) -> OutputError:
    return OutputError(f"{path}: cannot write the output there ({exc.strerror or exc})")


@contextmanager
def atomic_dir(out_dir: str | Path, kind: str, inputs: Iterable[str | Path | None] = ()) -> Iterator[Path]:
    """Claim ``out_dir`` (:func:`check_output_dir`, then a lock) and yield an empty temporary
    folder; when the block succeeds its contents, with the marker of ``kind``, replace
    ``out_dir`` atomically. Open it before the long work, so bad paths fail first and a
    second writer is refused."""
    out = check_output_dir(out_dir, kind, inputs)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        lock = _OutputLock(out, out_dir).__enter__()
    except OSError as exc:
        raise _unwritable(out.parent, exc) from exc
    try:
        _clean_leftovers(out)
        check_output_dir(out_dir, kind, inputs)  # again, now that no one else writes it
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        except OSError as exc:
            raise _unwritable(out.parent, exc) from exc
        try:
            (tmp / PARTIAL).touch()
            yield tmp
            os.chmod(tmp, 0o755)  # mkdtemp creates 0700
            for d, _, files in os.walk(tmp):  # a rerun deletes these, and keeps anything else
                for f in files:
                    _mark_written(Path(d) / f, kind)
            (tmp / MARKER).write_text(json.dumps({"written_by": "gcgs", "kind": kind}) + "\n")
            (tmp / PARTIAL).unlink()
            if out.is_dir():
                _keep_foreign(out, tmp, out_dir)
            _swap_in(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    finally:
        lock.__exit__()


def check_creatable(out: Path, shown: str | Path) -> None:
    """Refuse (one line) an output path whose folder cannot be created or written: a file
    where a folder is needed, or no permission. Tried for real (a probe file created and
    removed in the nearest existing folder), so read-only mounts fail here too, root or not."""
    folder = out.parent
    while not folder.exists() and not folder.is_symlink():
        folder = folder.parent
    if not folder.is_dir():
        raise OutputError(f"{shown}: cannot create the output: {folder} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".gcgs-probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{shown}: cannot write the output in {folder} ({exc.strerror or exc})") from None


def written_kind(path: str | Path) -> str | None:
    """The kind gcgs recorded on a file it wrote (:data:`FILE_XATTR`), ``None`` for any other."""
    try:
        return os.getxattr(path, FILE_XATTR).decode()
    except (OSError, AttributeError, UnicodeDecodeError):
        return None


def _mark_written(path: str | Path, kind: str) -> None:
    try:
        os.setxattr(path, FILE_XATTR, kind.encode())
    except (OSError, AttributeError):
        pass  # no user attributes on this file system: a rerun then refuses to replace the file


def check_output_file(path: str | Path, inputs: Iterable[str | Path | None] = (), kind: str = "file") -> Path:
    """Refuse (:class:`OutputError`, one line) an output file path whose writing could lose
    data or fail late: a folder, an input or a path inside an input folder, an existing
    non-empty file that gcgs did not write (or wrote as another ``kind``), a mount point, or
    a place that cannot be written. Cheap: stages call it before any long work."""
    out = resolved_path(path)
    if out.is_dir():
        raise OutputError(f"{path}: output file path is a folder; give a file name")
    for given, where in overlapping_inputs(out, inputs):
        if where == "is":
            raise OutputError(f"{path}: output file is the input {given}; writing it would destroy the input")
        if where == "lies inside":
            raise OutputError(f"{path}: output file lies inside the input folder {given}; "
                              "writing it would change the input: choose a path outside it")
    if out.is_file() and out.stat().st_size > 0:
        found = written_kind(out)
        if found is None:
            raise OutputError(f"{path}: file exists and was not written by gcgs; refusing to overwrite it: "
                              "choose another path or remove it yourself")
        if found != kind:
            raise OutputError(f"{path}: file holds a gcgs {found}, not a {kind}; refusing to overwrite it: "
                              "choose another path")
    if os.path.ismount(out):
        raise OutputError(f"{path}: output file is a mount point; choose a path inside a folder")
    check_creatable(out, path)
    return out


@contextmanager
def atomic_file(path: str | Path, suffix: str | None = None,
                inputs: Iterable[str | Path | None] = (), kind: str = "file") -> Iterator[Path]:
    """Yield a temporary file path; it becomes ``path`` (marked as a gcgs ``kind``) when the
    block succeeds. ``suffix`` (default: ``path``'s) keeps writers that infer the format
    from it happy."""
    path = Path(path)
    check_output_file(path, inputs, kind)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix if suffix is None else suffix,
                                   dir=path.parent)
    except OSError as exc:
        raise _unwritable(path, exc) from exc
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600
        _mark_written(tmp, kind)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    with atomic_file(path) as tmp:
        tmp.write_text(text)
