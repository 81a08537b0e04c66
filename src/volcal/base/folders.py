"""All-or-nothing output folders: write into a temporary folder, then rename into place.

Every command that writes a folder (identify, simulate, analyze, mc, iso230-2, ...) goes
through :func:`write_folder`:

* the folder is filled under a temporary name beside the target and renamed into place at
  the end, so an interrupted run never leaves a half-written folder that looks whole, and
  no temporary folder stays behind (it is removed on any error, Ctrl-C or SIGTERM);
* it holds ``manifest.json``: what wrote it, and the SHA-256 of every file;
  :func:`verify_manifest` refuses a folder whose files no longer match;
* an existing folder is replaced only when it is an earlier output of the same kind
  (its manifest says so, or it holds nothing but that output's files); a user's other
  files, another command's output and the inputs of the run are never touched.  On the
  command line replacing an earlier output needs ``--force`` (:func:`output_policy`); the
  Python API replaces it as before;
* a lock file beside the target (``.NAME.lock``, removed afterwards) makes a second process
  writing the same folder fail with a clear error instead of mixing two runs;
* a writer killed outright (SIGKILL, a power cut) cannot clean up: its temporary folder
  (``.NAME.tmp-PID-*``, named with the writer's process id, which the lock file records
  too) stays.  The next writer of the same folder, holding the lock, removes the
  temporaries whose process no longer runs, and only those (:func:`remove_stale`);
* files get the modes the user's umask gives (0644 / 0755 under the usual 022).

:func:`check_out_dir` runs the same checks up front: commands call it before any solving,
so a bad output path costs no computing time.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from volcal.base.exceptions import InputError

__all__ = [
    "check_out_dir",
    "write_folder",
    "verify_manifest",
    "output_policy",
    "MANIFEST",
    "folder_lock",
    "remove_stale",
    "stale_temporaries",
]

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "volcal-output-manifest"

# None: Python API (an earlier output of the same kind is replaced); False: command line
# without --force (refused); True: command line with --force (replaced)
_FORCE: contextvars.ContextVar[bool | None] = contextvars.ContextVar(
    "volcal_output_force", default=None
)


@contextlib.contextmanager
def output_policy(force: bool) -> Iterator[None]:
    """Within this block an earlier output folder is replaced only with ``force`` (the
    command line's ``--force``)."""
    token = _FORCE.set(bool(force))
    try:
        yield
    finally:
        _FORCE.reset(token)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _read_manifest(folder: Path) -> dict | None:
    f = folder / MANIFEST
    if not f.is_file():
        return None
    try:
        doc = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if (
        not isinstance(doc, dict)
        or doc.get("format") != MANIFEST_FORMAT
        or not isinstance(doc.get("files"), dict)
    ):
        return None
    return doc


def verify_manifest(folder: str | Path, *, required: bool = False) -> None:
    """Raise :class:`InputError` when a file listed in ``folder/manifest.json`` is missing or
    its SHA-256 differs (a file changed after volcal wrote it, or files of two runs mixed).
    A folder without a manifest (written before manifests existed) passes unless
    ``required``."""
    folder = Path(folder)
    if not (folder / MANIFEST).exists():
        if required:
            raise InputError(f"no {MANIFEST}: not a folder written by volcal", source=str(folder))
        return
    doc = _read_manifest(folder)
    if doc is None:
        raise InputError(
            f"{MANIFEST} is unreadable or not a volcal manifest", source=str(folder / MANIFEST)
        )
    missing, changed = [], []
    for rel, digest in doc["files"].items():
        p = folder / rel
        if not p.is_file():
            missing.append(rel)
        elif _sha256(p) != digest:
            changed.append(rel)
    if missing or changed:
        why = []
        if changed:
            why.append(
                f"changed since volcal wrote it: {', '.join(changed[:5])}"
                f"{', ...' if len(changed) > 5 else ''}"
            )
        if missing:
            why.append(f"missing: {', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}")
        raise InputError(
            f"the folder does not match its {MANIFEST} ({'; '.join(why)}); "
            "it was edited or mixed with another run: write it again",
            source=str(folder),
        )


def _write_manifest(folder: Path, what: str) -> None:
    from volcal import __version__

    files = {
        p.relative_to(folder).as_posix(): _sha256(p)
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p != folder / MANIFEST
    }
    doc = {
        "format": MANIFEST_FORMAT,
        "format_version": 1,
        "what": what,
        "volcal_version": __version__,
        "files": files,
    }
    (folder / MANIFEST).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")


def _umask() -> int:
    m = os.umask(0o022)
    os.umask(m)
    return m


def _apply_umask(folder: Path) -> None:
    """mkdtemp / mkstemp create private entries: give them the modes a plain ``open`` /
    ``mkdir`` would under the user's umask (results are meant to be shared)."""
    m = _umask()
    for p in folder.rglob("*"):
        if not p.is_symlink():
            os.chmod(p, (0o777 if p.is_dir() else 0o666) & ~m)
    os.chmod(folder, 0o777 & ~m)


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _check_parents(out: Path) -> None:
    """Every existing ancestor must be a folder, and the nearest one writable."""
    anc = out.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if anc.exists() and not anc.is_dir():
        raise InputError(
            f"{anc} is a file, not a folder; cannot create the output folder there", source=str(out)
        )
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(
            f"cannot write in {anc} (permission denied); choose another output folder",
            source=str(out),
        )


def check_out_dir(
    out: str | Path,
    allowed: Iterable[str],
    what: str,
    marker: str | None = None,
    *,
    inputs: Iterable[str | Path | None] = (),
    allowed_dirs: Iterable[str] = (),
    force: bool | None = None,
) -> Path:
    """Raise :class:`InputError` (naming ``out``) unless ``out`` can be written.

    ``out`` must be absent, an empty folder, or an earlier output of ``what``: its manifest
    says so, or it holds only files named in ``allowed`` and folders named in
    ``allowed_dirs`` (with ``marker``, that file among them; a folder holding only
    ``allowed_dirs`` is an interrupted run that may be resumed).  An earlier output is
    replaced only with ``force`` (default: the command line's ``--force`` within
    :func:`output_policy`, else allowed).  ``inputs``: paths read by the run; ``out`` may
    neither be nor hold one, nor lie inside an input folder.  Anything else is refused,
    never deleted.  Returns ``out`` as given (a Path)."""
    given = Path(out)
    out = given.absolute()
    allowed, allowed_dirs = set(allowed), set(allowed_dirs)
    force = _FORCE.get() if force is None else force
    ro = Path(os.path.realpath(out))
    for p in inputs:
        if p is None:
            continue
        p = Path(p)
        if not p.exists():
            continue
        rp = Path(os.path.realpath(p))
        if _inside(rp, ro):
            raise InputError(
                f"the input {p} is {'the' if rp == ro else 'inside the'} output "
                "folder, which is replaced; write the output elsewhere "
                "(inputs are never modified)",
                source=str(given),
            )
        if rp.is_dir() and _inside(ro, rp):
            raise InputError(
                f"the output folder lies inside the input folder {p}; write it "
                "elsewhere (inputs are never modified)",
                source=str(given),
            )
    _check_parents(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise InputError(
                "exists and is not a folder; expected a folder for the results", source=str(given)
            )
        try:
            items = list(out.iterdir())
        except OSError as exc:
            raise InputError(
                f"cannot read the folder: {exc.strerror or exc}", source=str(given)
            ) from None
        if not items:
            return given
        doc = _read_manifest(out)
        if doc is not None and doc.get("what") != what:
            raise InputError(
                f"the folder holds the output of {doc.get('what')}, not of "
                f"{what}; choose a new or empty folder",
                source=str(given),
            )
        listed = {r.split("/")[0] for r in doc["files"]} if doc is not None else set()
        other = sorted(
            p.name
            for p in items
            if not (
                (p.name in allowed and p.is_file())
                or (p.name in allowed_dirs and p.is_dir())
                or p.name in listed
                or p.name == MANIFEST
            )
        )
        only_dirs = all(p.name in allowed_dirs for p in items)
        if doc is None and marker is not None and not (out / marker).is_file() and not only_dirs:
            other = other or [f"(no {marker})"]
        if other:
            raise InputError(
                f"the folder exists and holds other files, not results of "
                f"{what} ({', '.join(other[:5])}"
                f"{', ...' if len(other) > 5 else ''}); choose a new or "
                "empty folder",
                source=str(given),
            )
        if doc is None:
            if only_dirs:
                return given  # an interrupted run: resumed, not replaced
        if force is False:
            raise InputError(
                f"the folder holds an earlier output of {what}; pass --force to "
                "replace it, or choose a new folder",
                source=str(given),
            )
        if not os.access(out.parent, os.W_OK | os.X_OK):
            raise InputError(f"cannot replace it: {out.parent} is not writable", source=str(given))
    return given


@contextlib.contextmanager
def folder_lock(out: str | Path) -> Iterator[None]:
    """An exclusive lock on writing ``out`` (``.NAME.lock`` beside it, removed on release);
    a second holder gets :class:`InputError` at once instead of waiting."""
    out = Path(out).absolute()
    lock = out.parent / f".{out.name}.lock"
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX
        yield
        return
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise InputError(
                    "another volcal process is writing this folder right now "
                    f"(lock {lock.name}); wait for it or choose another folder",
                    source=str(out),
                ) from None
            raise
        # the previous holder may have removed the file between our open and lock
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    # record the holder (process id and host): what a later writer checks before it
    # removes temporaries that a killed holder left behind
    previous = _read_lock_owner(fd)
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {_host()}\n".encode(), 0)
    try:
        if previous is None or previous[1] == _host():
            remove_stale(out)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _host() -> str:
    import socket

    return socket.gethostname()


def _read_lock_owner(fd: int) -> tuple[int, str] | None:
    """(pid, host) a lock file records, None when empty or unreadable (written by a
    version of volcal that recorded nothing)."""
    try:
        text = os.pread(fd, 256, 0).decode("utf-8", "replace").split()
        return int(text[0]), text[1]
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int) -> bool:
    """Whether a process with this id runs on this host (a process of another user
    counts as running)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stale_temporaries(folder: str | Path, prefix: str) -> list[Path]:
    """Entries ``folder/PREFIX<pid>-*`` whose process ``pid`` no longer runs: left by a
    writer killed outright.  Entries of a running process, and entries without a process
    id in their name (not written this way), are not listed."""
    out = []
    folder = Path(folder)
    try:
        entries = list(folder.iterdir())
    except OSError:
        return []
    for p in entries:
        if not p.name.startswith(prefix):
            continue
        pid = p.name[len(prefix) :].split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            out.append(p)
    return out


def remove_stale(out: str | Path) -> list[Path]:
    """Remove the temporary (``.NAME.tmp-PID-*``) and replaced (``.NAME.old-PID-*``)
    folders that writers of ``out`` killed outright left beside it, when their process
    no longer runs; returns what was removed.  Called by :func:`folder_lock` once the
    lock is held (no other writer of ``out`` is running then)."""
    out = Path(out).absolute()
    gone = []
    # a writer killed between moving the earlier output aside and moving its new one in
    # leaves no ``out``: its ``.old-`` folder is then the only copy of that output and is
    # kept (the user may rename it back; the next write leaves it alone)
    kinds = ("tmp", "old") if out.exists() else ("tmp",)
    for kind in kinds:
        for p in stale_temporaries(out.parent, f".{out.name}.{kind}-"):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()
            if not p.exists():
                gone.append(p)
    if gone:
        import logging

        logging.getLogger(__name__).info(
            "removed %d temporary folder(s) of an earlier run that was killed: %s",
            len(gone),
            ", ".join(p.name for p in gone),
        )
    return gone


def write_folder(
    out_dir: str | Path,
    allowed: Iterable[str],
    what: str,
    writer: Callable[[Path], None],
    *,
    marker: str | None = None,
    inputs: Iterable[str | Path | None] = (),
    allowed_dirs: Iterable[str] = (),
    force: bool | None = None,
) -> Path:
    """Call ``writer(tmp)`` to fill a temporary folder next to ``out_dir``, add the
    manifest and rename it to ``out_dir`` (checked by :func:`check_out_dir` first and again
    under the lock).  On any error, Ctrl-C or SIGTERM (turned into KeyboardInterrupt by the
    command line) the temporary folder is removed and ``out_dir`` is untouched."""
    allowed = tuple(allowed) + (MANIFEST,)
    allowed_dirs, inputs = tuple(allowed_dirs), tuple(inputs)
    out = Path(out_dir).absolute()
    check_out_dir(out, allowed, what, marker, inputs=inputs, allowed_dirs=allowed_dirs, force=force)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(
            f"cannot create the output folder: {exc.strerror or exc}", source=str(out_dir)
        ) from None
    with folder_lock(out):
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-{os.getpid()}-", dir=out.parent))
        try:
            writer(tmp)
            _write_manifest(tmp, what)
            _apply_umask(tmp)
            if out.exists():
                # it may have changed meanwhile
                check_out_dir(
                    out,
                    allowed,
                    what,
                    marker,
                    inputs=inputs,
                    allowed_dirs=allowed_dirs,
                    force=force,
                )
                old = out.parent / f".{out.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
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


# --------------------------------------------------------------------------------------
# writes that a signal must not cut in two

_CRITICAL = 0
_PENDING: list[int] = []


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Defer Ctrl-C and SIGTERM (which the command line turns into KeyboardInterrupt) until
    the block ends, so that a file written there and renamed into place is whole or
    absent.  Outside the command line (no volcal handler installed) it changes nothing."""
    global _CRITICAL
    _CRITICAL += 1
    try:
        yield
    finally:
        _CRITICAL -= 1
        if _CRITICAL == 0 and _PENDING:
            sig = _PENDING[-1]
            _PENDING.clear()
            raise KeyboardInterrupt(f"signal {sig}")


def interrupt_deferred(signum: int) -> bool:
    """For the command line's signal handler: inside :func:`uninterrupted`, note the signal
    and return True (the handler then returns); otherwise False."""
    if _CRITICAL:
        _PENDING.append(signum)
        return True
    return False


# --------------------------------------------------------------------------------------
# where a write failed


def _mount_of(path: Path) -> tuple[str, str, str] | None:
    """(mount point, file-system type, device) of the file system holding ``path`` (an
    existing path), from /proc/self/mountinfo (Linux); None elsewhere."""
    try:
        st = os.stat(path)
        lines = Path("/proc/self/mountinfo").read_text(encoding="utf-8").splitlines()
    except OSError:
        return None
    real = os.path.realpath(path)
    want = f"{os.major(st.st_dev)}:{os.minor(st.st_dev)}"
    best = None
    for line in lines:
        left, _, right = line.partition(" - ")
        f, r = left.split(), right.split()
        if len(f) < 5 or len(r) < 2 or f[2] != want:
            continue
        mnt = f[4].replace("\\040", " ")
        if (real == mnt or real.startswith(mnt.rstrip("/") + "/")) and (
            best is None or len(mnt) > len(best[0])
        ):
            best = (mnt, r[0], r[1])
    return best


def describe_device(path: str | Path) -> str:
    """A sentence naming the file system that holds ``path`` (or would hold it): its
    device, type and mount point and the space left on it, e.g. ``"/dev/sda1 (ext4)
    mounted at /home, 0 B free"``."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    where = _mount_of(p)
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        free = None
    text = f"{where[2]} ({where[1]}) mounted at {where[0]}" if where else f"the disk of {p}"
    if free is not None:
        size = float(free)
        for unit in ("B", "kB", "MB", "GB", "TB"):
            if size < 1000 or unit == "TB":
                break
            size /= 1000
        text += f", {size:.3g} {unit} free" if unit != "B" else f", {free} B free"
    return text
