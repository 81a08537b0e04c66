"""Several instruments in one identification problem, as one :class:`Instrument`.

The problem (:mod:`volcal.problem.residuals`) maps one reading function over every
reading; to put a tracker, an interferometer and a ballbar in it, the combined instrument's
station vector is ``instrument_index`` (which part reads at that station, held) followed by
the union of the parts' station parameters (by name: the tracker's and the ballbar's
``x_mm, y_mm, z_mm`` share columns); a station's parameters that its part does not have
are held.  Its reading selects the part's reading with ``if_else`` on the index (all in
CasADi: no callback, the unselected branch contributes an exact zero, NaN-safe).  Global
parameters are the parts' globals prefixed with the part's name (``tracker.frame_tx_mm``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from volcal.measurement.instruments.base import Instrument

INDEX = "instrument_index"


@dataclass(frozen=True, repr=False)
class CombinedInstrument(Instrument):
    """Parts (distinct instruments), the part of every station ``kinds`` ((station id,
    part index), ...) and extra held parameters ``held`` ((station id, names), ...)."""

    parts: tuple[Instrument, ...] = ()
    kinds: tuple[tuple[str, int], ...] = ()
    held: tuple[tuple[str, tuple[str, ...]], ...] = ()
    #: per part, station values at which its reading and derivatives are finite (one of
    #: its stations' start values); fed to it at the other parts' stations
    neutral: tuple[tuple[float, ...], ...] = ()
    name: str = field(init=False, default="combined")
    station_param_names: tuple[str, ...] = field(init=False, default=())
    global_param_names: tuple[str, ...] = field(init=False, default=())
    positive_readings: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError("a combined instrument needs at least one part")
        names: list[str] = [INDEX]
        for part in self.parts:
            names += [n for n in part.station_param_names if n not in names]
        glob = [f"{p.name}.{g}" for p in self.parts for g in p.global_param_names]
        # "tracker_and_ballbar": a CasADi Function name (letters, digits, single "_")
        label = "_and_".join(re.sub(r"[^A-Za-z0-9]+", "", p.name) for p in self.parts)
        object.__setattr__(self, "name", label)
        object.__setattr__(self, "station_param_names", tuple(names))
        object.__setattr__(self, "global_param_names", tuple(glob))

    # where each part's parameters sit in the combined vectors
    def station_columns(self, k: int) -> list[int]:
        """Columns of part k's station parameters in the combined station vector."""
        return [self.station_param_names.index(n) for n in self.parts[k].station_param_names]

    def global_columns(self, k: int) -> list[int]:
        """Positions of part k's global parameters in the combined global vector."""
        p = self.parts[k]
        return [self.global_param_names.index(f"{p.name}.{g}") for g in p.global_param_names]

    def part_of(self, station_id: str) -> int:
        """Index of the part that reads at a station."""
        return dict(self.kinds)[str(station_id)]

    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        out = None
        for k, part in enumerate(self.parts):
            gc = self.global_columns(k)
            # |index - k| < 0.5 rather than == k: the index passes through the solver's
            # scaling and is not an exact integer there
            mine = ca.fabs(station[0] - k) < 0.5
            s = station[self.station_columns(k)]
            if self.neutral:
                # at another part's station this part reads at its neutral values: the
                # chain rule multiplies the unselected branch's derivatives by 0, and
                # 0 * NaN (a tracker at its station, an interferometer with u = 0) is NaN
                s = ca.if_else(mine, s, ca.DM(self.neutral[k]))
            r = part.reading(point, s, glob[gc] if gc else ca.SX(0, 1))
            out = r if out is None else ca.if_else(mine, r, out)
        assert out is not None  # at least one part (__post_init__)
        return out

    def held_station_params(self, station_id: str) -> tuple[str, ...]:
        k = self.part_of(station_id)
        own = set(self.parts[k].station_param_names)
        names = [INDEX] + [n for n in self.station_param_names[1:] if n not in own]
        names += list(self.parts[k].held_station_params(station_id))
        names += list(dict(self.held).get(str(station_id), ()))
        return tuple(dict.fromkeys(names))

    def start(self, station_ids, station_index, points, readings):
        """Each part's start values on its own stations, in the combined columns."""
        K = len(station_ids)
        est = np.zeros((K, self.n_station_params))
        glob = np.zeros(self.n_global_params)
        kind = np.array([self.part_of(s) for s in station_ids], int)
        est[:, 0] = kind
        idx = np.asarray(station_index, int)
        for k, part in enumerate(self.parts):
            ks = np.flatnonzero(kind == k)
            if not len(ks):
                continue
            local = np.full(K, -1)
            local[ks] = np.arange(len(ks))
            sel = np.isin(idx, ks)
            st, g = part.start(
                [station_ids[i] for i in ks], local[idx[sel]], points[sel], readings[sel]
            )
            est[np.ix_(ks, self.station_columns(k))] = st
            glob[self.global_columns(k)] = g
        return est, glob

    def start_values(self, station_ids, station_index, points, readings) -> np.ndarray:
        return self.start(station_ids, station_index, points, readings)[0]

    def start_note(self) -> str:
        return "; ".join(p.start_note() for p in self.parts)
