"""The script API is defined once (issue #40): its errors, its callback plumbing and ``linarmppManager`` in
app/scripting/api_spec.py, which the application imports and the isolated kernel loads by its path; the kernel's
proxies and the application's objects show a script the same names; bridge.py serves the API and
kernel_process.py runs the process (one job each, no circle); the runner uses its typed host without probing.

Read from the source with ``ast`` where the question is "where is it written", run where it is "what does a
script see" (the kernel's module in a ``python -I`` child, as the application starts it).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
APP = ROOT / "app"
SCRIPTING = APP / "scripting"
SPEC = SCRIPTING / "api_spec.py"
KERNEL = SCRIPTING / "kernel.py"
ERRORS = ("ScriptStopped", "ScriptError", "DeviceUnavailable", "CommandError", "CommandRefused")
ISOLATED_FROM = ("app", "PySide6", "shiboken6", "serial")
CALLBACK_SENTENCE = "expects a function taking one argument"
LOOKED_FOR = (*(f"class {name}" for name in ("LinarmppManager", *ERRORS, "KernelProcess", "ApiBridge")),
              "def set_callbacks", "def _set_callbacks", CALLBACK_SENTENCE)


@cache
def _definitions() -> tuple[tuple[str, ast.AST], ...]:
    """(file, node) for every class, function and text constant of ``app/`` (parsed once per process)."""
    kinds = (ast.ClassDef, ast.FunctionDef, ast.Constant)
    texts = {path: path.read_text(encoding="utf-8") for path in sorted(APP.rglob("*.py"))}
    return tuple((str(path.relative_to(ROOT)), node) for path, text in texts.items()
                 if any(word in text for word in LOOKED_FOR)  # only these files can hold what is looked for
                 for node in ast.walk(ast.parse(text, str(path))) if isinstance(node, kinds))


def _nodes() -> Iterator[tuple[str, ast.AST]]:
    yield from _definitions()


def _classes_named(name: str) -> list[str]:
    return [path for path, node in _nodes() if isinstance(node, ast.ClassDef) and node.name == name]


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


# ---------------------------------------------------------------------------------------------- written once
def test_one_linarmpp_manager_per_role() -> None:
    """The application's composition root (app/manager.py) and the script's ``linarmppManager`` (the API's
    definition, shared by the kernel and the application): one class each, not one per process."""
    assert sorted(_classes_named("LinarmppManager")) == ["app/manager.py", "app/scripting/api_spec.py"]


@pytest.mark.parametrize("name", ERRORS)
def test_each_script_error_is_defined_once_in_the_api_definition(name: str) -> None:
    assert _classes_named(name) == ["app/scripting/api_spec.py"]


def test_the_callback_plumbing_is_written_once() -> None:
    """``set…CallbackFun``'s rule (a function is added, a list replaces, None clears) and its sentence."""
    where = [path for path, node in _nodes()
             if isinstance(node, ast.Constant) and isinstance(node.value, str) and CALLBACK_SENTENCE in node.value]
    assert where == ["app/scripting/api_spec.py"]
    defined = [path for path, node in _nodes()
               if isinstance(node, ast.FunctionDef) and node.name.lstrip("_") == "set_callbacks"]
    assert defined == ["app/scripting/api_spec.py"]


def test_the_api_definition_is_standard_library_only() -> None:
    """The kernel loads it by path: it may import nothing of the application, nor anything not in the stdlib."""
    imported = {name.split(".")[0] for name in _imports(SPEC)}
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported
    assert not imported & set(ISOLATED_FROM)


def test_the_kernel_imports_nothing_of_the_application() -> None:
    imported = {name.split(".")[0] for name in _imports(KERNEL)}
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported


# ---------------------------------------------------------------------------------------------- one job each
def test_the_bridge_serves_the_api_and_kernel_process_runs_the_process() -> None:
    """Two modules, one job each: the process (spawn, pipes, selectors) is not the bridge's, and the process's
    module knows nothing of the API (the arrow runs bridge → kernel_process only: no circle)."""
    process, bridge = SCRIPTING / "kernel_process.py", SCRIPTING / "bridge.py"
    assert process.exists(), "app/scripting/kernel_process.py (the kernel's process and link) is missing"
    assert not {"subprocess", "selectors", "signal"} & _imports(bridge)
    assert not any(name.startswith("app.scripting") for name in _imports(process))
    assert "app.scripting.kernel_process" in _imports(bridge)
    assert _classes_named("KernelProcess") == ["app/scripting/kernel_process.py"]
    assert _classes_named("ApiBridge") == ["app/scripting/bridge.py"]


def test_the_runner_does_not_probe_its_host() -> None:
    """The runner is typed end to end (app.therapy.services.ScriptHost): no getattr / hasattr on what it was handed."""
    runner = SCRIPTING / "runner.py"
    probes = [f"line {node.lineno}: {ast.unparse(node)[:60]}"
              for node in ast.walk(ast.parse(runner.read_text(encoding="utf-8")))
              if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
              and node.func.id in ("getattr", "hasattr")]
    assert probes == [], "\n".join(probes)


# ---------------------------------------------------------------------------------------------- what a script sees
KERNEL_PROBE = r'''
import importlib.util, json, sys
spec = importlib.util.spec_from_file_location("kernel_under_test", sys.argv[1])
kernel = importlib.util.module_from_spec(spec)
spec.loader.exec_module(kernel)

class Link:
    hello = json.loads(sys.stdin.read())

namespace = kernel.build_api(Link())
names = {name: sorted(n for n in dir(obj) if not n.startswith("_")) for name, obj in namespace.items()
         if name in kernel._api.API_NAMES}
errors = {name: [c.__name__ for c in cls.__mro__] for name, cls in kernel._api.SCRIPT_ERRORS.items()}
print(json.dumps({
    "names": names, "errors": errors,
    "shared": all(namespace[n] is c for n, c in kernel._api.SCRIPT_ERRORS.items()),
    "manager": type(namespace["linarmppManager"]) is kernel._api.LinarmppManager,
    "spec_file": kernel._api.__file__,
    "modules": sorted(m for m in sys.modules if m.split(".")[0] in ISOLATED_FROM),
}))
'''.replace("ISOLATED_FROM", repr(ISOLATED_FROM))


def _kernel_view() -> dict[str, Any]:
    from app.scripting.bridge import hello_message

    done = subprocess.run([sys.executable, "-I", "-c", KERNEL_PROBE, str(KERNEL)], input=json.dumps(hello_message()),
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_the_kernel_and_the_application_show_a_script_the_same_api() -> None:
    from app.scripting import api, api_spec
    from tests.test_script_api import Manager

    seen = _kernel_view()
    assert seen["modules"] == [], "the kernel loaded the application's modules"
    assert Path(seen["spec_file"]) == SPEC  # the application's own definition, loaded by its path
    assert seen["shared"] and seen["manager"]
    assert seen["errors"] == {name: [c.__name__ for c in cls.__mro__] for name, cls in api_spec.SCRIPT_ERRORS.items()}
    context = api.ScriptContext(Manager())
    try:
        in_app = api.build_api(context)
        names = {name: sorted(n for n in dir(in_app[name]) if not n.startswith("_")) for name in api_spec.API_NAMES}
    finally:
        context.close()
    assert seen["names"] == names
    assert type(in_app["linarmppManager"]) is api_spec.LinarmppManager
    assert all(in_app[name] is cls for name, cls in api_spec.SCRIPT_ERRORS.items())
