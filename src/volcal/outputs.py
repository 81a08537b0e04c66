"""All-or-nothing output folders: write into a temporary folder, then rename into place.

Every command that writes a folder (identify, simulate, analyze, iso230-2, ...) goes
through :func:`write_folder`, so an interrupted run never leaves a half-written folder that
looks whole, and an existing folder is replaced only when it holds nothing but an earlier
output of the same kind (never a user's other files).
"""
from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Callable, Iterable

from volcal.exceptions import InputError

__all__ = ["check_out_dir", "write_folder"]


def check_out_dir(out: str | Path, allowed: Iterable[str], what: str,
                  marker: str | None = None) -> Path:
    """``out`` must be absent, empty, or hold only files named in ``allowed`` (an earlier
    output, which will be replaced; with ``marker``, that file must be among them);
    anything else is refused, never deleted.  Returns ``out`` as a Path."""
    out = Path(out)
    allowed = set(allowed)
    if out.exists():
        if not out.is_dir():
            raise InputError("exists and is not a folder; expected a folder for the results",
                             source=str(out))
        items = list(out.iterdir())
        other = sorted(p.name for p in items if p.name not in allowed or p.is_dir())
        if items and marker is not None and not (out / marker).is_file():
            other = other or [f"(no {marker})"]
        if other:
            raise InputError(f"the folder exists and holds other files, not results of {what} "
                             f"({', '.join(other[:5])}{', ...' if len(other) > 5 else ''}); "
                             "choose a new or empty folder", source=str(out))
    return out


def write_folder(out_dir: str | Path, allowed: Iterable[str], what: str,
                 writer: Callable[[Path], None], *, marker: str | None = None) -> Path:
    """Call ``writer(tmp)`` to fill a temporary folder next to ``out_dir`` and rename it to
    ``out_dir``.  On any error the temporary folder is removed and ``out_dir`` is untouched.
    """
    allowed = tuple(allowed)
    out = Path(out_dir).absolute()
    check_out_dir(out, allowed, what, marker)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        writer(tmp)
        # mkdtemp makes a private folder; results are meant to be shared
        for p in tmp.iterdir():
            os.chmod(p, 0o644)
        os.chmod(tmp, 0o755)
        if out.exists():
            check_out_dir(out, allowed, what, marker)  # it may have changed meanwhile
            old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
            os.rename(out, old)
            try:
                os.rename(tmp, out)
            except BaseException:
                os.rename(old, out)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
