"""All-or-nothing output folders: write into a temporary folder, then rename into place."""
from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Callable, Iterable

from volcal.exceptions import InputError

__all__ = ["check_out_dir", "write_folder"]


def check_out_dir(out: Path, allowed: Iterable[str], what: str) -> None:
    """``out`` must be absent, empty, or hold only files named in ``allowed`` (an earlier
    result, which will be replaced); anything else is refused, never deleted."""
    allowed = set(allowed)
    if out.exists():
        if not out.is_dir():
            raise InputError("exists and is not a folder; expected a folder for the results",
                             source=str(out))
        other = sorted(p.name for p in out.iterdir() if p.name not in allowed or p.is_dir())
        if other:
            raise InputError(f"the folder exists and holds files that are not results of "
                             f"{what} ({', '.join(other[:5])}{', ...' if len(other) > 5 else ''}"
                             "); choose a new or empty folder", source=str(out))


def write_folder(out_dir, allowed: Iterable[str], what: str,
                 writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp)`` to fill a temporary folder next to ``out_dir`` and rename it to
    ``out_dir``.  On any error the temporary folder is removed and ``out_dir`` is untouched.
    """
    allowed = tuple(allowed)
    out = Path(out_dir).absolute()
    check_out_dir(out, allowed, what)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        writer(tmp)
        if out.exists():
            check_out_dir(out, allowed, what)
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
