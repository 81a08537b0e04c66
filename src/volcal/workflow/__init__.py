"""The workflow layer: which strategy, which error-basis orders, in which order.

:func:`identify` (``volcal.identify``) is the entry of ``volcal identify``: it runs the
classic pipeline (:mod:`volcal.analysis.classic`) or chooses the orders of the error bases
(``degree="auto"``, :mod:`volcal.workflow.orders`), and otherwise calls the single fit
(:func:`volcal.analysis.identify.identify`).  :func:`compare` runs strategies side by side
(:mod:`volcal.workflow.comparison`).  The pieces live in :mod:`volcal.analysis` and are
imported downward only; nothing below imports this package (tests/test_layers.py).

Imported lazily: ``import volcal.workflow`` loads neither CasADi nor SymPy.
"""

from typing import Any

_LAZY = {
    "identify": ("volcal.workflow.dispatch", "identify"),
    "select_orders": ("volcal.workflow.orders", "select_orders"),
    "compare": ("volcal.workflow.comparison", "compare"),
}

__all__ = list(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        mod, attr = _LAZY[name]
        return getattr(importlib.import_module(mod), attr)
    raise AttributeError(f"module 'volcal.workflow' has no attribute {name!r}")
