"""What an instrument is to volcal: the one interface every observation model implements.

An instrument turns the actual tool point of a reading into the value the instrument
reports.  It declares

* its parameters: per *station* (a set-up position of a tracker, a laser of a multi-laser
  head, a measuring direction of a probe) and global (shared by all readings), with units;
* ``reading(point, station, glob)``: one reading as a CasADi SX expression (mm).  This is
  the only place an observation model is written: the identification NLP, its Jacobian,
  the reading uncertainties, the simulator and the C export all evaluate it;
* ``start_values``: start values of the station parameters from nominal points and
  readings (no guess needed from the user), and which station parameters are held by the
  instrument's own convention (e.g. the frame of a multi-laser head);
* the data it reads: every instrument reads the standard measurement table (axis
  positions, tool offset, ``station``, ``length_mm`` = the reading in mm, optional
  ``sigma_mm``); ``length_mm`` is the reading whatever it measures.

A new instrument is one class in one file (see ``tests/coordinate_probe.py`` for a probe
that reads 3-D coordinates), registered with :func:`volcal.measurement.instruments.register`;
nothing in the problem, the solvers or the analyses changes.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from functools import cached_property, lru_cache
from pathlib import Path

import casadi as ca
import numpy as np
import pandas as pd

from volcal.model.numpy_call import NumpyCall


class Instrument(ABC):
    """Base class of observation models (see the module docstring)."""

    #: short name used in files and on the command line
    name: str = "instrument"
    #: per-station parameter names (units as suffix: ``_mm``, ``_rad``, or none)
    station_param_names: tuple[str, ...] = ()
    #: global parameter names
    global_param_names: tuple[str, ...] = ()
    #: readings are distances (positive); False for signed readings (coordinates, ...)
    positive_readings: bool = True

    # ---- parameters -------------------------------------------------------------------
    @staticmethod
    def _unit(name: str) -> str:
        return "rad" if name.endswith("_rad") else ("mm" if name.endswith("_mm") else "1")

    @property
    def station_param_units(self) -> tuple[str, ...]:
        return tuple(self._unit(n) for n in self.station_param_names)

    @property
    def global_param_units(self) -> tuple[str, ...]:
        return tuple(self._unit(n) for n in self.global_param_names)

    @property
    def n_station_params(self) -> int:
        return len(self.station_param_names)

    @property
    def n_global_params(self) -> int:
        return len(self.global_param_names)

    # ---- the observation model ----------------------------------------------------------
    @abstractmethod
    def reading(self, point: ca.SX, station: ca.SX, glob: ca.SX) -> ca.SX:
        """One reading (mm) for the actual tool point ``point`` (3,) mm, the station's
        parameters (n_station_params,) and the global parameters (n_global_params,)."""

    @cached_property
    def reading_function(self) -> ca.Function:
        """``reading(point, station, glob) -> (value, d value / d point)`` as one CasADi
        Function (built once per instrument object; map it over readings)."""
        p = ca.SX.sym("p", 3)
        s = ca.SX.sym("s", self.n_station_params)
        g = ca.SX.sym("g", self.n_global_params)
        v = self.reading(p, s, g)
        return ca.Function(
            f"{self.name}_reading",
            [p, s, g],
            [v, ca.jacobian(v, p)],
            ["point", "station", "glob"],
            ["value", "dvalue_dpoint"],
            {"cse": True},
        )

    def evaluate(
        self, points: np.ndarray, stations: np.ndarray, glob: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Readings (N,) mm and their gradients wrt the point (N, 3) for points (N, 3) mm
        and the station parameters of every reading (N, n_station_params)."""
        points = np.atleast_2d(np.asarray(points, float))
        N = len(points)
        glob = np.zeros(self.n_global_params) if glob is None else np.asarray(glob, float)
        if N == 0:
            return np.zeros(0), np.zeros((0, 3))
        stations = np.asarray(stations, float)
        # the raw buffers below check only that an input is large enough: a wrong shape
        # would be read silently as other numbers
        if points.shape != (N, 3) or stations.shape != (N, self.n_station_params):
            raise ValueError(
                f"{self.name}: expected points (N, 3) and stations (N, "
                f"{self.n_station_params}), got {points.shape} and {stations.shape}"
            )
        if glob.shape != (self.n_global_params,):
            raise ValueError(
                f"{self.name}: expected {self.n_global_params} global parameters, got "
                f"shape {glob.shape}"
            )
        try:
            mapped = _mapped(self, N)
        except TypeError:  # an instrument that cannot be hashed is mapped every time
            mapped = self.reading_function.map(N)
        # through the raw buffers (DM conversions cost more than the evaluation); every
        # input of a mapped Function has N columns
        v, d = NumpyCall(mapped)(points.T, stations.T, np.repeat(glob[:, None], N, axis=1))
        # map stacks the (1, 3) gradients side by side: (1, 3N)
        return v.ravel(), d.reshape(N, 3)

    # ---- start values --------------------------------------------------------------------
    @abstractmethod
    def start_values(
        self,
        station_ids: list[str],
        station_index: np.ndarray,
        points: np.ndarray,
        readings: np.ndarray,
    ) -> np.ndarray:
        """Start values (K, n_station_params) of every station from the nominal points
        (N, 3) mm of its readings and the readings (N,) mm.  Raises
        :class:`volcal.base.exceptions.SolverError` when a station cannot be located."""

    def start(
        self,
        station_ids: list[str],
        station_index: np.ndarray,
        points: np.ndarray,
        readings: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(station start values as :meth:`start_values`, global start values consistent
        with them).  The globals are zero unless the instrument expresses its stations in
        a frame of its own (then it overrides this method)."""
        return (
            self.start_values(station_ids, station_index, points, readings),
            np.zeros(self.n_global_params),
        )

    def held_station_params(self, station_id: str) -> tuple[str, ...]:
        """Station parameters this instrument's own convention holds at their start value
        (none by default)."""
        return ()

    def held_from_points(
        self, station_ids: list[str], station_index: np.ndarray, points: np.ndarray
    ) -> dict[str, tuple[str, ...]]:
        """Station parameters the geometry of a station's nominal points (N, 3) mm leaves
        undetermined and that are therefore held too, {station id: names} (e.g. the
        ballbar's centre coordinate normal to its circle); none by default."""
        return {}

    def read_table(self, source: str | Path | pd.DataFrame, spec) -> str | Path | pd.DataFrame:
        """The instrument's own table as volcal's measurement table (a DataFrame whose
        rows are the source's rows, in order, so that row numbers in messages stay the
        source's).  By default the source is that table already."""
        return source

    def start_note(self) -> str:
        """One line for the result's notes: where the station start values came from."""
        return f"station start values: {self.name} start values from the nominal points"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, stations: "
            f"{', '.join(self.station_param_names)}; global: "
            f"{', '.join(self.global_param_names) or 'none'})"
        )


@lru_cache(maxsize=16)
def _mapped(instrument: Instrument, n: int) -> ca.Function:
    """The reading Function mapped over ``n`` readings, shared by equal instruments
    (building it costs more than evaluating it on thousands of readings)."""
    return instrument.reading_function.map(n)
