"""File helpers: atomic writes and map files with one-line errors."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from agents.errors import UserError
from mapping.wireframe import Wireframe


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()


def is_number(text: str) -> bool:
    """Whether ``float(text)`` reads it (``nan`` and ``inf`` included)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def write_atomic(path: str | os.PathLike[str], data: bytes | str, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same directory, fsync,
    then ``os.replace``. A reader sees the old file or the new one, never half of either.

    The file gets ``mode`` (default: 0666 less the umask). The temporary file is created 0600,
    so a secret written with ``mode=0o600`` is never readable by others, not even for a moment."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    raw = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _FILE_MODE if mode is None else mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def check_output_dir(flag: str, path: str | os.PathLike[str]) -> Path:
    """Check, before any work and leaving nothing behind, that directory ``path`` exists or
    can be made: the nearest existing ancestor is a writable directory (not a file). Else a
    one-line ``UserError`` naming ``flag``, e.g. ``--out afile/sub: afile is a file, not a
    directory``. An empty path is refused (it would be the current directory, which a run
    clears of its previous outputs). Writability is tried, not inferred from the mode bits
    (which a superuser passes even in ``/proc``): a directory is made in the nearest existing
    ancestor and removed at once."""
    if not str(path).strip():
        raise UserError(f"{flag}: empty path (give a directory, e.g. {flag} out/run1)")
    p = Path(path)
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        what = ("is a file, not a directory" if probe == p
                else f"cannot create it: {probe} is a file, not a directory")
        raise UserError(f"{flag} {p}: {what}")
    if probe.exists():
        if not os.access(probe, os.W_OK | os.X_OK):
            raise UserError(f"{flag} {p}: {probe} is not writable")
        try:
            os.rmdir(tempfile.mkdtemp(dir=probe, prefix=".wiremap-probe-"))
        except OSError as exc:
            raise UserError(f"{flag} {p}: cannot write in {probe}: {exc.strerror or exc}") from None
    return p


def check_output_file(flag: str, path: str | os.PathLike[str]) -> Path:
    """Check, before any work and leaving nothing behind, that file ``path`` can be written:
    it is not a directory and its directory exists or can be made (:func:`check_output_dir`)."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{flag} {p}: is a directory")
    check_output_dir(flag, p.parent if str(p.parent) else ".")
    if p.parent.is_dir() and not os.access(p.parent, os.W_OK | os.X_OK):
        raise UserError(f"{flag} {p}: {p.parent} is not writable")
    return p


def output_file(flag: str, path: str | os.PathLike[str]) -> Path:
    """Check a command's output file option before anything runs (:func:`check_output_file`)
    and make its directory. Else a one-line ``UserError`` naming ``flag``."""
    p = check_output_file(flag, path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{flag} {p}: cannot create its directory: {exc.strerror or exc}") from None
    return p


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    write_atomic(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def read_json(path: str | os.PathLike[str]) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON: {exc}") from None
    except OSError as exc:
        raise UserError(f"{path}: {exc.strerror}") from None


def save_wireframe_geojson(
    path: str | os.PathLike[str], wf: Wireframe, properties: dict[str, Any] | None = None
) -> None:
    write_json(path, wf.to_geojson(properties))


def load_wireframe_geojson(path: str | os.PathLike[str]) -> Wireframe:
    doc = read_json(path)
    try:
        return Wireframe.from_geojson(doc)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None
