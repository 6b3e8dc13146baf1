"""Every notebook in notebooks/ runs top to bottom (a failing cell fails the test) and is stored without outputs.

The kernel is the interpreter running the tests (``sys.executable -m ipykernel_launcher``) through a kernel spec
written to a temporary folder, so no globally installed ``python3`` kernel is needed in a fresh venv.
"""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
KERNEL = "dcc-fg-test-python"


@pytest.fixture(scope="module")
def kernel_manager_factory(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    pytest.importorskip("ipykernel", reason="notebook tests need the [dev] extra (ipykernel)")
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    kdir = tmp_path_factory.mktemp("kernels")
    (kdir / KERNEL).mkdir()
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "dcc-fg tests",
        "language": "python",
        "env": {"PYTHONPATH": str(ROOT), "MPLBACKEND": "module://matplotlib_inline.backend_inline"},
    }
    (kdir / KERNEL / "kernel.json").write_text(json.dumps(spec))

    def make() -> KernelManager:
        return KernelManager(kernel_name=KERNEL, kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(kdir)]))

    return make


def test_there_are_notebooks() -> None:
    assert any(p.name == "calibration_analysis.ipynb" for p in NOTEBOOKS)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_outputs_are_stripped(path: Path) -> None:
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None, f"{path.name}: cell {i} has outputs"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_imports_resolve(path: Path) -> None:
    """The notebook's import statements run (fast-lane guard for moved modules; the full run is slow)."""
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    imports: list[ast.stmt] = []
    for cell in nb.cells:
        if cell.cell_type == "code":
            python = "\n".join(ln for ln in cell.source.splitlines() if not ln.lstrip().startswith(("%", "!")))
            tree = ast.parse(python)
            imports += [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)]
    assert imports, f"{path.name}: no import statements found"
    exec(compile(ast.Module(body=imports, type_ignores=[]), str(path), "exec"), {})  # noqa: S102


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path, kernel_manager_factory) -> None:  # noqa: ANN001
    nbformat = pytest.importorskip("nbformat")
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb, km=kernel_manager_factory(), timeout=600, resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError naming the cell when one fails
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    figure_cells = sum("figure(" in c.source for c in nb.cells if c.cell_type == "code")
    assert images >= figure_cells, f"{path.name}: {figure_cells} cells draw figures but only {images} images came out"
