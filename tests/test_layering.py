"""The imports obey the layering of docs/architecture.md, function-level imports included.

Every module of ``factors`` and ``dcc_fg`` belongs to one layer (longest matching prefix in
:data:`LAYERS`); a module may import modules of its own layer or of layers below it, never above.
Imports inside functions count the same as top-level ones, and are only allowed for the optional
heavy dependencies in :data:`LAZY_ALLOWED` (so a function-level import cannot hide a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Bottom to top. A module may import its own layer and every layer listed before it.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("factors: pure math", ("factors",)),
    ("util: version, logging, configuration, errors", ("dcc_fg.util",)),
    ("io: files and bags, no estimator types", ("dcc_fg.io",)),
    (
        "model/data: calibration model, measurements, targets, stream pairing",
        ("dcc_fg.model", "dcc_fg.cluster", "dcc_fg.cluster_data", "dcc_fg.data", "dcc_fg.targets", "dcc_fg.sync"),
    ),
    ("sim: synthetic data and ground truth", ("dcc_fg.sim",)),
    ("detection: target detection in images", ("dcc_fg.detection",)),
    ("sources: recordings -> measurements", ("dcc_fg.sources",)),
    (
        "estimators",
        (
            "dcc_fg.calibrate",
            "dcc_fg.calibration_health",
            "dcc_fg.noise_floor",
            "dcc_fg.calibration_graph",
            "dcc_fg.cluster_calibration",
            "dcc_fg.cluster_init",
            "dcc_fg.covariance",
            "dcc_fg.init",
            "dcc_fg.auto_init",
            "dcc_fg.global_fit",
            "dcc_fg.model_selection",
            "dcc_fg.incremental",
            "dcc_fg.time_offset",
            "dcc_fg.degeneracy",
            "dcc_fg.gauss_newton",
            "dcc_fg.projection",
            "dcc_fg.joint_motion",
            "dcc_fg.intrinsics",
            "dcc_fg.intrinsics_health",
            "dcc_fg.vio",
            "dcc_fg.planning",
        ),
    ),
    ("studies: estimators on simulated data", ("dcc_fg.studies",)),
    ("report/plots/export", ("dcc_fg.report", "dcc_fg.plots", "dcc_fg.export", "dcc_fg.viz")),
    ("commands", ("dcc_fg.commands", "dcc_fg.demo", "dcc_fg.batch")),
    ("cli", ("dcc_fg.cli", "dcc_fg.__main__")),
    ("package root: public API", ("dcc_fg",)),
]

# Third-party modules that may be imported inside a function (optional or heavy extras).
LAZY_ALLOWED = ("rerun", "dask", "distributed", "yourdfpy", "nbclient", "nbformat")


def _modules() -> dict[str, Path]:
    files = sorted((ROOT / "dcc_fg").rglob("*.py")) + sorted((ROOT / "factors").rglob("*.py"))
    out = {}
    for f in files:
        parts = list(f.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


MODULES = _modules()


def layer_of(module: str) -> int:
    """Index in LAYERS of the longest prefix that matches ``module``."""
    best, best_len = -1, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best_len:
                best, best_len = i, len(p)
    if best < 0:
        raise KeyError(module)
    return best


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> list[str]:
    if node.level == 0:
        base = node.module or ""
    else:
        pkg = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        pkg = pkg[: len(pkg) - (node.level - 1)]
        base = ".".join(pkg + ([node.module] if node.module else []))
    # "from pkg import sub" imports the submodule pkg.sub when it is one
    names = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in MODULES]
    return names or [base]


def _imports(module: str, path: Path) -> list[tuple[str, int, bool]]:
    """(imported module, line, inside a function) for every import in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top = {id(n) for n in tree.body}
    for n in tree.body:  # imports under "if TYPE_CHECKING:" / try blocks at module level are top level
        if isinstance(n, ast.If | ast.Try):
            top.update(id(c) for c in ast.walk(n))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno, id(node) not in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out += [(m, node.lineno, id(node) not in top) for m in _resolve(module, path, node)]
    return out


def _own(name: str) -> bool:
    return name == "dcc_fg" or name.startswith(("dcc_fg.", "factors"))


def test_every_module_has_a_layer() -> None:
    missing = []
    for m in MODULES:
        try:
            layer_of(m)
        except KeyError:
            missing.append(m)
    assert not missing, f"modules without a layer in tests/test_layering.py: {missing}"


def test_imports_follow_the_layering() -> None:
    bad = []
    for module, path in MODULES.items():
        mine = layer_of(module)
        for name, line, _ in _imports(module, path):
            if not _own(name):
                continue
            target = name if name in MODULES else name.rsplit(".", 1)[0]
            theirs = layer_of(target)
            if theirs > mine:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({LAYERS[mine][0]}) imports {name} ({LAYERS[theirs][0]})")
    assert not bad, "imports that reach up the layering:\n" + "\n".join(bad)


def test_no_function_level_imports() -> None:
    bad = []
    for module, path in MODULES.items():
        for name, line, inside in _imports(module, path):
            if inside and not name.startswith(LAZY_ALLOWED):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name} inside a function")
    assert not bad, "function-level imports (allowed only for optional heavy extras):\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("module", "expected"),
    [("factors.chain", 0), ("dcc_fg.io.bags", 2), ("dcc_fg.commands.vio", 10), ("dcc_fg.vio.frontend", 7)],
)
def test_layer_lookup(module: str, expected: int) -> None:
    assert layer_of(module) == expected


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    """The parser finds an upward import hidden inside a function (the test can fail)."""
    f = tmp_path / "mod.py"
    f.write_text("def f():\n    from dcc_fg.calibrate import calibrate\n    return calibrate\n")
    found = _imports("dcc_fg.io.fake", f)
    assert found == [("dcc_fg.calibrate", 2, True)]
    assert layer_of("dcc_fg.calibrate") > layer_of("dcc_fg.io.fake")
