"""Rendering of the hand-written parts of an export (API header, driver, example program,
Makefile, README) from the Jinja2 templates in ``templates/`` next to this module.

Template files: ``solver.h.j2``, ``solver.c.j2``, ``solver_main.c.j2`` (identification
solver), ``model.h.j2``, ``model.c.j2``, ``model_main.c.j2`` (model-only export),
``Makefile.j2``, ``README_solver.md.j2``, ``README_model.md.j2``; files starting with ``_``
are pieces included by the others.  ``{{ NAME }}`` is the export's C prefix, ``{{ UNAME }}``
its upper-case macro prefix; every other variable is a string prepared by
:mod:`volcal.outputs.codegen.export`.  An undefined variable is an error, a file keeps its last
newline, and nothing is escaped: what a template holds is what is written.  A C array
initialiser is written ``{ {{- values }}}`` (the ``-`` removes the space, so the output
reads ``{values}``).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import jinja2

TEMPLATE_DIR = Path(__file__).parent / "templates"


@lru_cache(maxsize=1)
def environment() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        undefined=jinja2.StrictUndefined,
        autoescape=False,
        keep_trailing_newline=True,
    )


def render(template: str, mapping: dict) -> str:
    """The template file ``template`` (e.g. ``"solver.c.j2"``) rendered with ``mapping``."""
    return environment().get_template(template).render(mapping)


def template_files() -> list[Path]:
    """Every template file, sorted (for the generator hash of an export)."""
    return sorted(TEMPLATE_DIR.glob("*.j2"))
