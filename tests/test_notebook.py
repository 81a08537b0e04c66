"""The tutorial notebook (docs/tutorial.ipynb) runs from top to bottom with the installed
volcal (nbclient, a fresh kernel); its outputs are not kept."""
from __future__ import annotations

from pathlib import Path

import pytest

NB = Path(__file__).resolve().parents[1] / "docs" / "tutorial.ipynb"


# A fresh Jupyter kernel through the tutorial (about 25 s): the calls it makes (plan,
# simulate, identify, the plots) are tested in the default suite, the notebook's own run
# and its rich displays here; CI runs this one (-m slow).
@pytest.mark.slow
def test_tutorial_notebook_runs(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(NB, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    # the rich reprs are there: the plan and the result show as HTML, the plots as PNG
    html = [o for o in outputs if "text/html" in o.get("data", {})]
    png = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(html) >= 3 and len(png) >= 4
    text = "".join(o.get("text", "") for o in outputs)
    assert "the plan predicted" in text
