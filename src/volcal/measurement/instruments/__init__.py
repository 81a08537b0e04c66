"""Observation models behind one interface (:class:`Instrument`), and their registry.

``get_instrument("tracker")`` (the default, sequential multilateration) or
``"multilaser"`` (paper 001's head), ``"interferometer"`` (a laser interferometer along
lines), ``"ballbar"`` (circles); :class:`CombinedInstrument` puts several in one problem;
:func:`register` adds one (a class in one file).
"""

from __future__ import annotations

from volcal.base.exceptions import InputError
from volcal.measurement.instruments.ballbar import Ballbar
from volcal.measurement.instruments.base import Instrument
from volcal.measurement.instruments.combined import CombinedInstrument
from volcal.measurement.instruments.interferometer import LaserInterferometer
from volcal.measurement.instruments.multilaser import MultiLaserInstrument
from volcal.measurement.instruments.tracker import SequentialMultilateration

__all__ = [
    "Instrument",
    "SequentialMultilateration",
    "MultiLaserInstrument",
    "LaserInterferometer",
    "Ballbar",
    "CombinedInstrument",
    "register",
    "get_instrument",
    "instruments",
]

_REGISTRY: dict[str, type[Instrument]] = {
    "tracker": SequentialMultilateration,
    "multilaser": MultiLaserInstrument,
    "interferometer": LaserInterferometer,
    "ballbar": Ballbar,
}


def register(cls: type[Instrument]) -> type[Instrument]:
    """Register an :class:`Instrument` subclass under its ``name`` (usable as a decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, Instrument)):
        raise TypeError(f"{cls!r} is not an Instrument subclass")
    _REGISTRY[cls.name] = cls
    return cls


def instruments() -> list[str]:
    """Names of the registered instruments."""
    return sorted(_REGISTRY)


def get_instrument(instrument: str | Instrument | None = None) -> Instrument:
    """An instrument object from a name (or the object itself; None: the tracker)."""
    if instrument is None:
        return SequentialMultilateration()
    if isinstance(instrument, Instrument):
        return instrument
    try:
        return _REGISTRY[str(instrument)]()
    except KeyError:
        raise InputError(
            f"unknown instrument {instrument!r}; expected one of {', '.join(instruments())}"
        ) from None
