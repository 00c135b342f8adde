"""The package's layers (docs/architecture.md): every import points down, and only the CLI knows flags.

Layers bottom to top: core < signals < io < gp < method < evaluation < reporting < diagnosis < world < cli.
A module's layer is its subpackage; the top-level files are core or cli (``TOP_LEVEL``). A module may
import from its own layer or a lower one; imports inside functions count like module-level ones.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "crashfuse"
LAYERS = ("core", "signals", "io", "gp", "method", "evaluation", "reporting", "diagnosis", "world", "cli")
# The package __init__ runs before any submodule is imported, so it is core like errors and units.
TOP_LEVEL = {"__init__": "core", "errors": "core", "units": "core", "catalogue": "core",
             "cli": "cli", "reproduce": "cli", "__main__": "cli", "forkserver": "cli"}
# Imports that break the rule on purpose, (importer, imported) -> why.
EXCEPTIONS = {("crashfuse", "crashfuse.signals.pulse"): "the package re-exports Pulse, its one public type"}
FLAG = re.compile(r"--[A-Za-z]")


def module_name(path: Path, package: Path = PACKAGE) -> str:
    """``crashfuse/io/campaign.py`` -> ``crashfuse.io.campaign``; a package's __init__ is the package."""
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str, package: Path = PACKAGE) -> bool:
    """Whether a dotted name under crashfuse is a module or subpackage (not a name defined in one)."""
    path = package.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def layer(name: str, package: Path = PACKAGE) -> str:
    """The layer of a crashfuse module given by its dotted name."""
    parts = name.split(".")
    if len(parts) == 1:
        return TOP_LEVEL["__init__"]
    if (package / parts[1] / "__init__.py").is_file():
        if parts[1] not in LAYERS:
            raise AssertionError(f"subpackage crashfuse.{parts[1]} is in no layer: add it to LAYERS")
        return parts[1]
    if parts[1] not in TOP_LEVEL:
        raise AssertionError(f"top-level module {name} is in no layer: add it to TOP_LEVEL")
    return TOP_LEVEL[parts[1]]


def imported_modules(path: Path, package: Path = PACKAGE) -> list[tuple[int, str]]:
    """(line, dotted module name) of every crashfuse import in a file, module-level or lazy."""
    name = module_name(path, package)
    parent = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the importing module's package
                anchor = parent.split(".")[:len(parent.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:  # `from crashfuse import units` imports the module crashfuse.units
                full = f"{base}.{alias.name}"
                found.append((node.lineno, full if is_module(full, package) else base))
    return sorted({(line, mod) for line, mod in found if mod == "crashfuse" or mod.startswith("crashfuse.")})


def layer_violations(path: Path, package: Path = PACKAGE) -> list[str]:
    """One message per import of ``path`` that points to a higher layer."""
    name = module_name(path, package)
    own = layer(name, package)
    messages = []
    for line, target in imported_modules(path, package):
        other = layer(target, package)
        if (name, target) in EXCEPTIONS or LAYERS.index(other) <= LAYERS.index(own):
            continue
        messages.append(f"{path.relative_to(package.parent)}:{line}: {name} (layer {own}) imports "
                        f"{target} (layer {other}), a higher layer")
    return messages


def docstring_nodes(tree: ast.Module) -> set[int]:
    """ids of the string constants that are docstrings of the module, classes or functions."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def flag_literals(source: str) -> list[tuple[int, str]]:
    """(line, text) of every string literal that starts with a command-line flag (``--name``).

    Docstrings are skipped; of an f-string only the leading text counts (a later part like
    ``f"{a}--b"`` does not start the literal).
    """
    tree = ast.parse(source)
    skip = docstring_nodes(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            skip.update(id(part) for part in node.values[1:])
    return sorted((node.lineno, node.value) for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip
                  and FLAG.match(node.value))


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_the_package_is_found():
    assert len(MODULES) > 30 and PACKAGE / "cli.py" in MODULES


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path):
    found = layer_violations(path)
    assert not found, "\n".join(found)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_only_the_cli_knows_flag_names(path):
    if layer(module_name(path)) == "cli":
        return
    found = flag_literals(path.read_text())
    assert not found, "\n".join(f"{path.relative_to(PACKAGE.parent)}:{line}: flag name {text!r} outside the CLI"
                                for line, text in found)


# --- the checks themselves -----------------------------------------------------------------

def test_layer_of_modules():
    assert layer("crashfuse") == "core"
    assert layer("crashfuse.units") == "core"
    assert layer("crashfuse.io.campaign") == "io"
    assert layer("crashfuse.world") == "world"
    assert layer("crashfuse.reproduce") == "cli"


def test_a_higher_import_is_reported_with_both_layers(tmp_path):
    fake = tmp_path / "crashfuse"
    (fake / "signals").mkdir(parents=True)
    (fake / "io").mkdir()
    for f in ("__init__.py", "units.py", "signals/__init__.py", "io/__init__.py", "io/campaign.py"):
        (fake / f).write_text("")
    (fake / "signals" / "pulse.py").write_text(
        "from crashfuse import units\n"
        "def f():\n    from crashfuse.io.campaign import read_campaign\n"
        "import crashfuse.io\n")
    assert layer_violations(fake / "signals" / "pulse.py", fake) == [
        "crashfuse/signals/pulse.py:3: crashfuse.signals.pulse (layer signals) imports crashfuse.io.campaign "
        "(layer io), a higher layer",
        "crashfuse/signals/pulse.py:4: crashfuse.signals.pulse (layer signals) imports crashfuse.io "
        "(layer io), a higher layer"]


def test_flag_literals_skip_docstrings_and_prose():
    source = ('"""Use --k here."""\n'
              'def f(k):\n    """--k is fine in a docstring."""\n'
              '    raise ValueError("bad", "--k")\n'
              'x = ["-", "--", "-k", "---", "a --k", f"{x}--y", f"--seed {x}", "--2"]\n')
    assert flag_literals(source) == [(4, "--k"), (5, "--seed ")]
