"""The folders and files a command writes to, checked before it runs.

A command that evaluates or trains for minutes, then fails to write its results, loses the run:
:func:`output_dir` and :func:`output_file` create and probe the place first, and say what to do
when it cannot be written (a path under a file, a read-only folder, a file where a folder is
meant).
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
import tempfile
from typing import Any

from suit_ros.errors import SuitRosError


def output_dir(path: str | os.PathLike[str], what: str = 'output folder') -> Path:
    """Create ``path`` (with its parents) and check that a file can be written in it.

    :raises SuitRosError: it cannot be made or written.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise SuitRosError(f'{what} {p} is a file: give a folder')
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as exc:
        raise SuitRosError(f'cannot write the {what} {p}: {exc.strerror or exc}; give a '
                           'folder you can write to') from exc
    return p


def output_file(path: str | os.PathLike[str], what: str = 'output file') -> Path:
    """Check that the file ``path`` can be written (its folder made now; the file itself is
    written later).

    :raises SuitRosError: it is a folder, or its folder cannot be made or written.
    """
    p = Path(path)
    if p.is_dir():
        raise SuitRosError(f'{what} {p} is a folder: give a file name')
    output_dir(p.parent if str(p.parent) else '.', f'folder of the {what}')
    return p


def durable_replace(tmp: str | os.PathLike[str], path: str | os.PathLike[str]) -> None:
    """Move the finished file ``tmp`` over ``path`` so that a crash or power loss leaves
    either the old file or the new one whole: ``tmp``'s data on disk first, then the rename,
    then the folder's entry."""
    with open(tmp, 'rb') as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    try:
        fd = os.open(Path(path).parent, os.O_RDONLY)
    except OSError:              # a folder that cannot be opened (some filesystems): done
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def json_text(obj: Any, indent: int = 2) -> str:
    """``obj`` as standard JSON (indented): an undefined figure (nan, inf: a ratio with
    nothing to divide, an interval with no resample) is written as null, since NaN is not
    JSON and jq, JavaScript and strict parsers refuse a file that holds it."""
    def clean(x: Any) -> Any:
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x
    return json.dumps(clean(obj), indent=indent, allow_nan=False)
