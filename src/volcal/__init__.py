"""volcal: identify the geometric errors of machine tools from multilateration lengths.

Units inside the code: lengths in mm, angles in rad. Files carry units in column names.

The main entry points, mirroring the command line, are importable from here (lazily: a
bare ``import volcal`` loads neither CasADi nor SymPy)::

    volcal.identify(...)   # volcal identify
    volcal.compare(...)    # volcal compare (strategies side by side)
    volcal.plan(...)       # volcal plan
    volcal.plots           # the plots of a result (volcal.outputs.plots)
"""

from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "identify": ("volcal.workflow.dispatch", "identify"),
    "compare": ("volcal.workflow.comparison", "compare"),
    "plan": ("volcal.analysis.planning.plan", "plan"),
    "plots": ("volcal.outputs.plots", None),
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        mod, attr = _LAZY[name]
        module = importlib.import_module(mod)
        return module if attr is None else getattr(module, attr)
    raise AttributeError(f"module 'volcal' has no attribute {name!r}")
