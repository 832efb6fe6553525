"""The layout's promises, checked on the source: layers do not cross, modules stay small, every
configuration key is read by the code it configures."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from forcegrasp.config import Config

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = ROOT / "common" / "forcegrasp"
SERVICES = {role: ROOT / "services" / role / f"forcegrasp_{role}" for role in ("actor", "learner", "evaluator")}
MAX_LINES = 430  # "about 400": a module past this mixes jobs and should be split


def _modules(*folders: Path) -> list[Path]:
    return sorted(p for folder in folders for p in folder.rglob("*.py"))


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def test_every_package_sits_in_a_folder_of_its_own_name():
    assert (LIBRARY / "__init__.py").is_file() and (LIBRARY / "cli" / "__init__.py").is_file()
    for folder in SERVICES.values():
        assert (folder / "__init__.py").is_file() and (folder / "__main__.py").is_file(), folder


def test_the_library_imports_no_service():
    services = tuple(f"forcegrasp_{role}" for role in SERVICES)
    crossing = {str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.startswith(services))
                for p in _modules(LIBRARY)}
    assert not {k: v for k, v in crossing.items() if v}


def test_services_do_not_import_each_other():
    for role, folder in SERVICES.items():
        others = tuple(f"forcegrasp_{r}" for r in SERVICES if r != role)
        for p in _modules(folder):
            assert not [m for m in _imports(p) if m.startswith(others)], p


def test_no_module_is_too_long():
    long = {str(p.relative_to(ROOT)): n for p in _modules(LIBRARY, *SERVICES.values())
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long


def test_every_configuration_key_is_read_by_the_code():
    attributes = set()
    for p in _modules(LIBRARY, *SERVICES.values()):
        tree = ast.parse(p.read_text())
        if p == LIBRARY / "config.py":  # only the sections' own methods (endpoints_for reads connect, listen)
            tree = ast.Module([f for c in tree.body if isinstance(c, ast.ClassDef) for f in c.body
                               if isinstance(f, ast.FunctionDef)], [])
        attributes |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    config = Config()
    unread = [f"{section.name}.{f.name}" for section in dataclasses.fields(config)
              for f in dataclasses.fields(getattr(config, section.name)) if f.name not in attributes]
    assert not unread, f"documented but never read: {unread}"
