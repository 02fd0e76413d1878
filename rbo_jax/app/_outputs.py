"""Output files of the command line: checked before any work, written whole.

A command that computes for minutes and then cannot write its result has lost it, so every
output path is checked first (:func:`output_problem`: its folder exists and is writable, nothing
is in the way, the name is not too long). And a result is either written whole or not at all:
every writer writes into a temporary beside the target (same folder, so the same file system)
and renames it into place (:func:`replacing`; ``os.replace`` is atomic on POSIX). A failure or
an interruption therefore leaves the previous file, or none, never a truncated one. Directories
(zarr stores) are renamed too: an existing store is first renamed aside, the new one renamed in,
then the old one deleted, so the name never points at half a store.

The temporaries in progress are listed in :data:`PENDING` (the interrupt handler of ``rbo-jax``
removes them before it exits) and the finished outputs in :data:`WRITTEN` (its message says what
was kept).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path

__all__ = ["PENDING", "WRITTEN", "output_problem", "replacing", "save_figure", "write_text"]

PENDING: set[Path] = set()
WRITTEN: list[str] = []


def _nearest_existing(path: Path) -> Path:
    """The nearest ancestor of ``path`` (or itself) that exists (as anything)."""
    p = path
    while not (p.exists() or p.is_symlink()) and p != p.parent:
        p = p.parent
    return p


def _name_too_long(path: Path, folder: Path) -> bool:
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):  # not POSIX, or no limit known
        limit = 255
    # the temporary's name is longer than the target's by about 30 characters
    return len(os.fsencode(path.name)) + 30 > limit


def output_problem(path, *, directory: bool = False, make_parents: bool = False) -> str | None:
    """Why ``path`` cannot be written, in words (None if it can). ``directory``: the output is
    a folder (a zarr store, the folder of a report); ``make_parents``: missing folders above it
    will be created (then the nearest existing one must be a writable folder)."""
    text = str(path)
    if not text.strip():
        return "an empty path"
    if "\0" in text:
        return "a path with a NUL character"
    p = Path(os.path.abspath(os.path.expanduser(text)))
    if any(len(os.fsencode(part)) > 255 for part in p.parts):
        return "a name in it is too long for a file system (more than 255 bytes)"
    try:
        return _problem(p, directory, make_parents)
    except OSError as e:  # e.g. a path too long as a whole, a loop of links
        return f"it cannot be examined ({e.strerror or e})"


def _problem(p: Path, directory: bool, make_parents: bool) -> str | None:
    if p.is_dir() and not directory:
        return "is a folder; give a file name"
    if p.exists() and directory and not p.is_dir():
        return "is a file, not a folder"
    if p.exists() and not os.access(p, os.W_OK):
        return "exists and is not writable"
    folder = p.parent
    if not folder.is_dir():
        existing = _nearest_existing(folder)
        if existing.exists() and not existing.is_dir():
            return f"{existing} is a file, not a folder"
        if not make_parents:
            return f"the folder {folder} does not exist"
        folder = existing
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"the folder {folder} is not writable"
    if _name_too_long(p, folder):
        return "the file name is too long for this file system"
    return None


def _temporary(path: Path, what: str) -> Path:
    """A hidden name beside ``path`` with the same suffix (writers choose formats by it)."""
    return path.with_name(f".{path.stem}.{what}-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


def _sync(path: Path) -> None:
    """Flush a written file to the disk before it is renamed into place (so that a crash of the
    machine cannot leave the new name on an empty file)."""
    if path.is_file():
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _move_into_place(tmp: Path, path: Path) -> None:
    if tmp.is_dir() and path.is_dir() and not path.is_symlink():
        old = _temporary(path, "old")  # rename() cannot replace a non-empty folder
        os.rename(path, old)
        PENDING.add(old)
        try:
            os.rename(tmp, path)
        except BaseException:
            os.rename(old, path)  # put the previous one back
            PENDING.discard(old)
            raise
        _remove(old)
        PENDING.discard(old)
    else:
        os.replace(tmp, path)


@contextlib.contextmanager
def replacing(path):
    """Write ``path`` whole: yields a temporary path beside it (same suffix) to write to, file
    or folder; on success it is renamed to ``path`` (replacing what was there), on any failure
    (or interruption) it is removed and ``path`` is left as it was."""
    path = Path(path)
    tmp = _temporary(path, "tmp")
    PENDING.add(tmp)
    try:
        yield tmp
        _sync(tmp)
        _move_into_place(tmp, path)
    finally:
        if tmp.exists() or tmp.is_symlink():
            _remove(tmp)
        PENDING.discard(tmp)
    WRITTEN.append(str(path))


def remove_pending() -> None:
    """Remove every temporary in progress (the interrupt handler calls it before exiting)."""
    for tmp in list(PENDING):
        _remove(tmp)
        PENDING.discard(tmp)


def save_figure(fig, path, **kwargs) -> None:
    """``fig.savefig(path, **kwargs)``, written whole (matplotlib picks the format by the
    suffix, which the temporary keeps)."""
    with replacing(path) as tmp:
        fig.savefig(tmp, **kwargs)


def write_text(path, text: str) -> None:
    """A text file (UTF-8), written whole."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
