"""Files written atomically: to a temporary name beside the destination, then renamed, so that
an interrupted write never leaves a half-written file (used by :mod:`rsmooth.viz` and
:func:`rsmooth.sim.save_model`; no heavy imports here).

An output folder of the command line also lists the files that its run wrote, in
:data:`MANIFEST`, so that the next run into the same folder removes them (and nothing else)
before it writes its own: figures of a previous run never sit beside new metrics, and files
that rsmooth did not write are never deleted.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator

# The list of the files a run of the command line wrote into its output folder.
MANIFEST = "rsmooth-files.json"
_MANIFEST_FORMAT = "rsmooth-files/1"

# Called with the path of every file that atomic_path has put in place (see `recording`).
_listeners: list[Callable[[Path], None]] = []


class OutputFolderError(ValueError):
    """An output folder that a run cannot use (a file, or a folder of files rsmooth did not write)."""


def _ordinary_permissions(path: Path) -> None:
    """mkstemp creates a file private (0600); give it the permissions of an ordinary file."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yields a temporary path beside `path`; renames it to `path` if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    _ordinary_permissions(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    for listener in list(_listeners):
        listener(path)


@contextlib.contextmanager
def recording(listener: Callable[[Path], None]) -> Iterator[None]:
    """Calls ``listener(path)`` after each file that :func:`atomic_path` writes in the block."""
    _listeners.append(listener)
    try:
        yield
    finally:
        _listeners.remove(listener)


def _read_manifest(folder: Path) -> list[str] | None:
    """The relative paths listed in the folder's manifest; None if it has none (or not ours)."""
    try:
        data = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):  # missing, unreadable, or not JSON
        return None
    if not isinstance(data, dict) or data.get("format") != _MANIFEST_FORMAT or not isinstance(data.get("files"), list):
        return None
    return [name for name in data["files"] if isinstance(name, str)]


def listed_files(folder: str | os.PathLike) -> list[str]:
    """The files, relative to `folder`, that the last run into it wrote and that exist."""
    folder = Path(folder)
    return [name for name in _read_manifest(folder) or () if (path := _inside(folder, name)) is not None and path.is_file()]


def _write_manifest(folder: Path, files: list[str]) -> None:
    text = json.dumps({"format": _MANIFEST_FORMAT, "files": sorted(set(files))}, indent=2)
    # Written by hand rather than through atomic_path, whose listeners would record it.
    fd, tmp = tempfile.mkstemp(prefix=".rsmooth-files-", suffix=".json", dir=folder)
    try:
        with os.fdopen(fd, "w") as file:
            file.write(text + "\n")
        _ordinary_permissions(Path(tmp))
        os.replace(tmp, folder / MANIFEST)
    finally:
        Path(tmp).unlink(missing_ok=True)


def _inside(folder: Path, name: str) -> Path | None:
    """``folder / name`` if it names a path inside `folder` (links followed), else None."""
    relative = Path(name)
    if relative.is_absolute() or not relative.parts or ".." in relative.parts:
        return None
    path = folder / relative
    try:
        path.parent.resolve().relative_to(folder.resolve())
    except ValueError:  # through a link to elsewhere
        return None
    return path


def _is_output_folder(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink() and _read_manifest(path) is not None


def prepare_output_folder(folder: str | os.PathLike, option: str = "--out") -> Path:
    """Makes `folder` ready for a run: creates it, or removes the files that the previous run
    into it wrote (those its :data:`MANIFEST` lists), leaving every other file in place.

    Args:
        folder: the output folder.
        option: how the folder is named in errors (the command-line option).

    Returns:
        The folder, as a `Path`.

    Raises:
        OutputFolderError: if `folder` is a file, or a non-empty folder that no run of rsmooth
            wrote into (no manifest), whose files could be taken for the new run's.
        OSError: if the folder cannot be created or read (e.g. permission denied).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"{option} {folder} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputFolderError(f"{option} {folder} is a file, not a folder") from None
    except NotADirectoryError:
        raise OutputFolderError(f"{option} {folder}: a parent of it is a file, not a folder") from None
    listed = _read_manifest(folder)
    if listed is None:
        # A folder made by hand, or by another program: refuse it unless it is empty (apart from
        # the output folders of other runs, such as `control solo-lift --foot all`'s).
        foreign = sorted(entry.name for entry in folder.iterdir() if not _is_output_folder(entry))
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise OutputFolderError(
                f"{option} {folder} is not empty ({shown}) and holds no previous run of rsmooth (no {MANIFEST}): "
                "choose a new or empty folder"
            )
    else:
        for name in listed:
            path = _inside(folder, name)
            # Only plain files, as written: anything since replaced by a folder or a link is kept.
            if path is not None and path.is_file() and not path.is_symlink():
                path.unlink()
    _write_manifest(folder, [])
    return folder


@contextlib.contextmanager
def recording_outputs(folder: str | os.PathLike) -> Iterator[None]:
    """Lists in `folder`'s :data:`MANIFEST` every file that :func:`atomic_path` writes inside it
    during the block (the manifest is updated after each file, so that it is complete even
    when the run stops half-way)."""
    folder = Path(folder)
    root = folder.resolve()
    written: list[str] = []

    def listener(path: Path) -> None:
        try:
            relative = path.resolve().relative_to(root)
        except ValueError:  # written outside the folder
            return
        written.append(relative.as_posix())
        _write_manifest(folder, written)

    with recording(listener):
        yield
