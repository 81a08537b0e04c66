"""The Jinja2 environment of the HTML report's templates (``templates/report``) and its
number format, shared by :mod:`volcal.outputs.html_report` and
:mod:`volcal.outputs.compare_report` (the comparison section both render) so that neither
imports the other."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jinja2
from markupsafe import Markup, escape

TEMPLATE_DIR = Path(__file__).parent / "templates" / "report"


def number(v: Any, digits: int = 4, missing: str = "") -> str:
    """A number with ``digits`` significant digits; ``missing`` for None / NaN / inf."""
    if v is None or isinstance(v, bool):
        return missing if v is None else ("yes" if v else "no")
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    return format(x, f".{digits}g") if math.isfinite(x) else missing


def code_spans(text: Any) -> Markup:
    """Escaped text whose Markdown code spans (`` `x` ``, as notes and messages write
    them) become ``<code>x</code>``: no literal backticks in the document."""
    parts = str(text).split("`")
    if len(parts) % 2 == 0:  # an unpaired backtick: leave the text as it is
        return escape(str(text))
    return Markup("").join(
        escape(p) if k % 2 == 0 else Markup("<code>%s</code>") % p for k, p in enumerate(parts)
    )


def environment() -> jinja2.Environment:
    """The report templates' environment, autoescaped."""
    # autoescape on: model descriptions, file names and notes are user text in HTML
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        undefined=jinja2.StrictUndefined,
        autoescape=True,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["code_spans"] = code_spans
    return env
