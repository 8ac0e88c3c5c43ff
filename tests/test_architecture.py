"""The package's import rules (docs/architecture.md), checked on the source: every import, module-level or not.

* Pure computation (the model, features, segmentation, inverses, estimator,
  diagnosis) imports no I/O: not slipest.io, slipest.live or slipest.cli,
  and none of the libraries that talk to ports, buses, networks,
  processes, signals, threads, screens or terminals.
* Nothing in slipest imports firmware_sim.
* The command line imports the library, never the reverse: only slipest.cli
  modules (and slipest.__main__, which is `python -m slipest`) import slipest.cli.
* The I/O edge (slipest.io) does not import the live runtime or the CLI.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Pure-computation modules and packages (a name covers its submodules).
PURE = ("slipest.model", "slipest.inverse", "slipest.diagnosis", "slipest.features", "slipest.segmentation",
        "slipest.estimator", "slipest.cycle_estimator", "slipest.online", "slipest.units", "slipest.latency",
        "slipest.calibration", "slipest.rover", "slipest.swap_timing", "slipest.despike")
#: Edge modules inside pure packages (they write files or draw).
PURE_EXCEPTIONS = ("slipest.diagnosis.plots",)
#: Libraries that do I/O (ports, buses, networks, processes, signals, threads, plots, terminals).
IO_LIBRARIES = ("serial", "can", "cantools", "cobs", "socket", "asyncio", "subprocess", "signal", "threading",
                "matplotlib", "tqdm", "argparse", "select", "termios", "tty", "fcntl")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Absolute names of every module a source file imports (relative imports resolved)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                prefix = ".".join(base)
                mod = f"{prefix}.{node.module}" if node.module else prefix
            else:
                mod = node.module
            out.add(mod)
            out.update(f"{mod}.{alias.name}" for alias in node.names)  # "from pkg import submodule"
    return out


def _modules(*top: str) -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for t in top for p in sorted((ROOT / t).rglob("*.py"))}


def _under(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


SLIPEST = _modules("slipest")


def test_the_rules_see_every_module():
    assert len(SLIPEST) > 40 and "slipest.online" in SLIPEST and "slipest.cli.main" in SLIPEST


@pytest.mark.parametrize("module", sorted(m for m in SLIPEST if _under(m, PURE) and m not in PURE_EXCEPTIONS))
def test_pure_computation_imports_no_io(module):
    bad = sorted(i for i in SLIPEST[module]
                 if _under(i, ("slipest.io", "slipest.live", "slipest.cli", "firmware_sim") + IO_LIBRARIES))
    assert not bad, f"{module} imports I/O: {bad}"


def test_nothing_in_slipest_imports_firmware_sim():
    bad = {m: sorted(i for i in imps if _under(i, ("firmware_sim",))) for m, imps in SLIPEST.items()}
    assert not {m: v for m, v in bad.items() if v}


#: The command line's entry points besides slipest.cli itself (`python -m slipest`).
CLI_ENTRY_POINTS = ("slipest.__main__",)


def test_only_the_command_line_imports_the_command_line():
    bad = {m: sorted(i for i in imps if _under(i, ("slipest.cli",)))
           for m, imps in SLIPEST.items() if not _under(m, ("slipest.cli",)) and m not in CLI_ENTRY_POINTS}
    assert not {m: v for m, v in bad.items() if v}


def test_the_io_edge_does_not_import_the_runtime_or_the_command_line():
    bad = {m: sorted(i for i in imps if _under(i, ("slipest.live", "slipest.cli")))
           for m, imps in SLIPEST.items() if _under(m, ("slipest.io",))}
    assert not {m: v for m, v in bad.items() if v}


def test_a_violation_is_caught(tmp_path, monkeypatch):
    """The checker itself: a pure module importing a port library or slipest.cli is seen (relative import too)."""
    pkg = tmp_path / "slipest" / "model"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "bad.py").write_text("def f():\n    import serial\n    from ..cli import main\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    imps = _imports(pkg / "bad.py")
    assert "serial" in imps and "slipest.cli.main" in imps


def test_only_the_drawing_modules_import_matplotlib():
    drawing = ("slipest.plotting", "slipest.offline.replay_plot", "slipest.diagnosis.plots")
    bad = {m: sorted(i for i in imps if _under(i, ("matplotlib",))) for m, imps in SLIPEST.items() if m not in drawing}
    assert not {m: v for m, v in bad.items() if v}
