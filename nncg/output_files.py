"""The generated files written as one set (CompiledModel.write): every file replaces its target or none
does, no temporary is left behind, and folders created for the files are removed again on failure.
File-system failures are NncgError saying what to do: they are the user's to fix, not NNCG bugs."""

from __future__ import annotations

import errno
import os
import secrets
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from .errors import NncgError
from .safe_text import shown

T = TypeVar("T")
PATH_LIMIT = 240  # characters of a path shown in a message
DEFAULT_NAME_MAX = 255  # bytes of a file name, where the file system does not say (os.pathconf)

_HINTS = {
    errno.EACCES: "choose a writable -o",
    errno.EPERM: "choose a writable -o",
    errno.EROFS: "choose another -o",
    errno.ENOSPC: "free some space or choose another -o",
    getattr(errno, "EDQUOT", errno.ENOSPC): "free some space or choose another -o",
    errno.ENAMETOOLONG: "choose a shorter --name or -o",
    errno.ENOTDIR: "a part of the path is not a folder: choose another -o",
    errno.EISDIR: "remove the folder or choose another --name or -o",
}


def write_files(directory: str | os.PathLike, files: Mapping[str, bytes]) -> tuple[Path, ...]:
    """Writes `files` (file name -> bytes) into `directory`, created if missing, all or nothing;
    returns their paths. New files get the usual mode (0666 minus the umask)."""
    out = Path(directory)
    check_output_folder(out)
    _check_names(out, list(files))
    targets = [out / name for name in files]
    _check_targets(targets)
    created = _make_folders(out)
    try:
        _write_staged(out, targets, list(files.values()))
    except BaseException:
        _remove_folders(created)
        raise
    return tuple(targets)


def _write_staged(out: Path, targets: list[Path], contents: list[bytes]) -> None:
    """Stages every file in a temporary, then swaps them all in; no temporary outlives the call."""
    staged: list[_Replacement] = []
    try:
        for target, data in zip(targets, contents):
            staged.append(_Replacement(target, _stage(out, target, data)))
        _swap_in(staged)
    finally:
        for rep in staged:
            if not rep.done:  # one swapped in is gone under this name (which may be taken again)
                _remove(rep.temp)


def check_output_folder(out: Path) -> None:
    """Raises NncgError unless `out` is a folder or can be created as one (no file in the way)."""
    existing = _existing_ancestor(out)
    if existing.is_dir():
        return
    if existing == out:
        raise NncgError(f"the output folder {_path(out)} exists and is not a folder: choose another -o")
    raise NncgError(
        f"{_path(existing)} is not a folder, so the output folder {_path(out)} cannot be created: choose another -o"
    )


def _existing_ancestor(path: Path) -> Path:
    while not os.path.lexists(path) and path.parent != path:
        path = path.parent
    return path


def _check_names(out: Path, names: list[str]) -> None:
    """Each name is one plain file name the file system takes (temporaries are short, so only these matter)."""
    limit = _name_max(_existing_ancestor(out))
    for name in names:
        if name in ("", ".", "..") or "/" in name or os.sep in name or (os.altsep and os.altsep in name):
            raise NncgError(f"{shown(name)} is not a plain file name; give a C identifier as --name")
        size = len(os.fsencode(name))
        if size > limit:
            raise NncgError(
                f"the file name {shown(name)} is {size} bytes, more than the {limit} this file system allows: "
                "choose a shorter --name"
            )


def _name_max(folder: Path) -> int:
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (AttributeError, OSError, ValueError):  # no pathconf (Windows) or no answer
        return DEFAULT_NAME_MAX


def _check_targets(targets: list[Path]) -> None:
    for target in targets:
        if target.is_dir() and not target.is_symlink():
            raise NncgError(f"{_path(target)} is a folder: remove it or choose another --name or -o")


def _make_folders(out: Path) -> list[Path]:
    """Creates `out` and its missing parents; returns those created, outermost first."""
    missing = []
    path = out
    while not os.path.lexists(path) and path.parent != path:
        missing.insert(0, path)
        path = path.parent
    created: list[Path] = []
    try:
        for folder in missing:
            with _failing_as("cannot create the folder", folder):
                folder.mkdir()
            created.append(folder)
    except BaseException:
        _remove_folders(created)
        raise
    return created


def _remove_folders(created: list[Path]) -> None:
    for folder in reversed(created):
        try:
            folder.rmdir()
        except OSError:  # something else put a file there meanwhile: keep it
            return


def _stage(folder: Path, target: Path, data: bytes) -> Path:
    """`data` in a new temporary file in `folder`, for `target`."""
    with _failing_as("cannot write", target):
        # 0o666: the kernel applies the umask (and default ACLs) as for any new file.
        temp, fd = _new_file(folder, lambda path: os.open(path, _CREATE_FLAGS, 0o666))
        try:
            try:
                _write_all(fd, data)
            finally:
                os.close(fd)
        except BaseException:
            _remove(temp)
            raise
    return temp


_CREATE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)


def _new_file(folder: Path, create: Callable[[Path], T]) -> tuple[Path, T]:
    """A fresh short hidden name in `folder` and what `create(path)` returns for it (create fails with
    FileExistsError where the name is taken)."""
    for _ in range(100):
        path = folder / f".nncg-{secrets.token_hex(4)}"
        try:
            return path, create(path)
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no unused temporary name", str(folder))


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


@dataclass
class _Replacement:
    """One target being replaced by a staged file, and what it takes to undo that."""

    target: Path
    temp: Path
    backup: Path | None = None  # a second name of the target's old file while the set is swapped in
    done: bool = False


def _swap_in(replacements: list[_Replacement]) -> None:
    """Renames every staged file onto its target; if one fails, puts back those already replaced."""
    try:
        for rep in replacements:
            with _failing_as("cannot replace", rep.target):
                rep.backup = _backup(rep.target)
                os.replace(rep.temp, rep.target)
            rep.done = True
    except BaseException:
        for rep in reversed(replacements):
            _undo(rep)
        raise
    for rep in replacements:
        if rep.backup is not None:
            _remove(rep.backup)


def _backup(target: Path) -> Path | None:
    """A second name for the file at `target` (None if there is none), so it can be put back."""
    if not os.path.lexists(target):
        return None
    if target.is_dir() and not target.is_symlink():
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(target))
    try:  # a hard link: the target stays in place until the rename replaces it
        return _new_file(target.parent, lambda path: os.link(target, path, follow_symlinks=False))[0]
    except (OSError, NotImplementedError):  # no hard links here (or no link to a link): move the old file aside
        return _new_file(target.parent, lambda path: _rename_unless_taken(target, path))[0]


def _rename_unless_taken(source: Path, path: Path) -> None:
    if os.path.lexists(path):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(path))
    os.replace(source, path)


def _undo(rep: _Replacement) -> None:
    """Puts the target's old file back (best effort: a backup that cannot be renamed stays, nothing is lost)."""
    with suppress(OSError):
        if rep.backup is None:
            if rep.done:
                os.unlink(rep.target)
        elif rep.done or not os.path.lexists(rep.target):
            os.replace(rep.backup, rep.target)
        else:  # the rename failed and the target is untouched: only the extra link goes
            os.unlink(rep.backup)


def _remove(path: Path) -> None:
    with suppress(OSError):  # best effort: gone already, or the error being reported matters more
        os.unlink(path)


@contextmanager
def _failing_as(action: str, path: Path) -> Iterator[None]:
    """OSError inside becomes NncgError: `action` `path`, the system's reason and what to do."""
    try:
        yield
    except OSError as exc:
        hint = _HINTS.get(exc.errno, "check the output folder (-o)")
        raise NncgError(f"{action} {_path(path)}: {exc.strerror or exc} ({hint})") from None


def _path(path: Path) -> str:
    return shown(path, PATH_LIMIT)
