"""Whether an identification fits in memory, checked before it starts.

The peak resident memory of ``volcal identify`` grows with the readings times the
unknowns (the Jacobian and the arrays of its size that the solver and the covariance
hold) plus a part per reading (the table, the residuals, the per-reading results).  The
factors below were measured with ``python benchmarks/bench_memory.py --solver ipopt
--grids 5 8 14 18`` (peak resident set of ``volcal identify --no-plots`` on simulated
mcv754_wxyzt tables of 3,000 to 139,968 readings with 75 to 147 unknowns; least-squares
fit, residuals below 26 MB; benchmarks/results/memory_ipopt.txt):

    peak ~ 133 MB + readings x (4.14 kB + 14.0 B x unknowns)

That is the whole-graph path (IPOPT: the NLP's CasADi graph holds every reading's
sparsity).  Gauss-Newton evaluates the problem in chunks of poses and never holds a
Jacobian-sized array; measured the same way (``bench_memory.py --solver gauss-newton
--grids 5 8 14 18``, 3,000 to 139,968 readings, largest residual 12.5 MB;
benchmarks/results/memory.txt; checked at 997,536 readings x 111 unknowns: 1.47 GB
measured without plots, 1.50 GB estimated):

    peak ~ 128 MB + readings x (1.08 kB + 2.7 B x unknowns)

(The base fell by some 15 MB when scipy left the identification's imports.)

:func:`check_memory` refuses a run whose estimate exceeds the memory available
(the smaller of ``MemAvailable`` in /proc/meminfo and the room left under the control
group's limit, plus what this process already holds) with the estimate and the limit,
instead of the kernel ending the process (the OOM killer) minutes later.
"""

from __future__ import annotations

import os
from pathlib import Path

from volcal.base.exceptions import InputError

__all__ = [
    "BASE_BYTES",
    "CHUNKED_FACTORS",
    "BYTES_PER_READING",
    "BYTES_PER_READING_UNKNOWN",
    "estimate_peak_bytes",
    "available_bytes",
    "check_memory",
]

#: measured (see the module docstring): the interpreter, CasADi, the model
BASE_BYTES = 133e6
#: per reading, whatever the unknowns (table, residuals, per-reading results)
BYTES_PER_READING = 4.14e3
#: per reading and unknown (the Jacobian and the arrays of its size)
BYTES_PER_READING_UNKNOWN = 14.0
#: the same three factors for the chunked path (Gauss-Newton), measured likewise
CHUNKED_FACTORS = (128e6, 1.08e3, 2.7)


def estimate_peak_bytes(readings: int, unknowns: int, *, chunked: bool = False) -> float:
    """Estimated peak resident memory (bytes) of an identification of ``readings``
    readings with ``unknowns`` unknowns (error parameters, station parameters, ...):
    through the whole CasADi graph (IPOPT), or ``chunked`` (Gauss-Newton)."""
    base, per_reading, per_cell = (
        CHUNKED_FACTORS if chunked else (BASE_BYTES, BYTES_PER_READING, BYTES_PER_READING_UNKNOWN)
    )
    return base + readings * (per_reading + per_cell * unknowns)


def _read_int(path: str) -> int | None:
    try:
        text = Path(path).read_text().split()[0]
    except (OSError, IndexError):
        return None
    return int(text) if text.isdigit() else None


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> int | None:
    """Limit less usage of this process's control group (v2, else v1); None without one."""
    try:
        rel = next(
            (
                line.split(":", 2)[2]
                for line in Path("/proc/self/cgroup").read_text().splitlines()
                if line.startswith("0::")
            ),
            None,
        )
    except OSError:
        rel = None
    if rel is not None:
        base = "/sys/fs/cgroup" + rel.rstrip("/")
        limit, used = _read_int(f"{base}/memory.max"), _read_int(f"{base}/memory.current")
        if limit is not None and used is not None:
            return max(limit - used, 0)
    limit = _read_int("/sys/fs/cgroup/memory/memory.limit_in_bytes")
    used = _read_int("/sys/fs/cgroup/memory/memory.usage_in_bytes")
    if limit is not None and used is not None and limit < 1 << 60:
        return max(limit - used, 0)
    return None


def _own_resident() -> int:
    """Resident bytes of this process now (0 where unknown)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def available_bytes() -> int | None:
    """Memory this process may still take (bytes): the smaller of the system's available
    memory and its control group's room; None where neither is known (not Linux)."""
    room = [v for v in (_meminfo_available(), _cgroup_room()) if v is not None]
    return min(room) if room else None


def check_memory(
    readings: int,
    unknowns: int,
    *,
    limit_gb: float | None = None,
    what: str = "the data",
    chunked: bool = False,
) -> float:
    """Raise :class:`InputError` when the estimated peak of an identification
    (:func:`estimate_peak_bytes`, ``chunked`` for the Gauss-Newton path) does not fit:
    in ``limit_gb`` (GB = 1e9 bytes) when given, else in what this process holds plus
    :func:`available_bytes`.  ``limit_gb = inf`` skips the check.  Returns the estimate
    in bytes."""
    need = estimate_peak_bytes(readings, unknowns, chunked=chunked)
    if limit_gb is not None:
        limit = float(limit_gb) * 1e9
        source = "--max-memory-gb"
    else:
        room = available_bytes()
        if room is None:
            return need
        limit = float(room + _own_resident())
        source = "the memory available now"
    if need > limit:
        raise InputError(
            f"{readings:,} readings x {unknowns} unknowns need about {need / 1e9:.2f} GB "
            f"of memory at the peak of the identification, more than the limit of "
            f"{limit / 1e9:.2f} GB ({source}); refused before the solve. Use fewer "
            "readings (a subset of poses or stations) or a lower degree, run it on a "
            "machine with more memory, or pass --max-memory-gb with a larger limit "
            "if you know the estimate is too high",
            source=what,
        )
    return need
