"""The house's structure, read from the source with ``ast`` (issue #29): no third-party tool.

* no import circle anywhere in ``app/`` (every import counts: module level, inside functions, and under
  ``TYPE_CHECKING`` — a circle for the type checker is still two modules that cannot be understood apart);
* nothing under ``app/devices/sim/``, no codec, and neither the bus nor the command queue imports Qt, directly
  or through another module of ``app/`` (the simulator process must not load PySide6);
* no device module imports the manager, directly or through another module;
* **the floors** (issue #40): every module sits on a floor (:data:`FLOORS`, ground first: the wire, the core,
  safety, the devices, the therapy, the session's record, the worker, the archive and the research export, the
  manager, the scripting, the window, the application and its command line) and imports only from its own floor
  or those below — also under ``TYPE_CHECKING``: no arrow runs back up;
* **Qt only where it belongs** (issue #40): PySide6/pyqtgraph are imported only by the window (``app/ui/``), the
  drivers (``app/devices/*.py``, their threads emit Qt signals), the composition root and the programs that run
  it (``app.manager``, ``app.application``, ``app.cli``, ``app.scripting.headless``) and the reports' PDF drawing
  (``app.session.reports``); the wire, the core, safety, the therapy and the session's record do not reach Qt
  through any import;
* **the links' facts once** (issue #40): no ``"<device>.tty"`` and no loopback address spelled outside
  ``app/core/links.py`` (the one function that names a simulated device's link, the one socket URL), and each
  serial rate (the default, the configured range, the LINarm's, ScienceMode's) typed in its one place
  (:data:`BAUD_FACTS`);
* **the journal heard on the bus only** (issue #40): no ``add_event_subscriber`` / ``set_event_sink`` wrapper
  defined or called anywhere (app, tests, benches, tools); the run log keeps no listener list of its own (no
  ``subscribe`` / ``_listeners`` / ``_notify`` in ``RunLog``) and nothing subscribes to a run log: its changes are
  journal records (origin ``run``), heard on the bus;
* outside ``app/ui/``, no parameter or attribute called manager / app / context is typed ``Any`` (or left
  untyped): a device or a consumer says what it really uses.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
APP = ROOT / "app"
QT_MODULES = ("PySide6", "shiboken6", "pyqtgraph", "qasync", "OpenGL")
CODECS = ("app.wire.cmdmessenger", "app.wire.sciencemode", "app.wire.physio_codec",
          "app.wire.udp_frames", "app.wire.linarm_protocol")
QT_FREE_CORE = ("app.core.bus", "app.core.streams", "app.devices.command_queue", "app.devices.realtime")
MANAGER_NAMES = frozenset({"manager", "mgr", "app", "ctx", "context"})

# The floors, ground first: a module imports only from its floor or lower ones. The longest prefix places a module.
FLOORS: tuple[tuple[str, ...], ...] = (
    ("app",),  # the package itself: its version
    ("app.wire",),  # each device's protocol tables, codecs, constants
    ("app.core",),  # the bus, the journal, stream names and ids, runs, configuration, files
    ("app.safety",),  # the supervisor, the FES limiter, the assistance map, the fault policy
    ("app.devices",),  # drivers, transports, command queues, simulators
    ("app.therapy",),  # patients, plans, exercises, the electrode set-up
    ("app.session",),  # the record: recording, replay, metrics, reports, exports, LSL
    ("app.worker",),  # the heavy work's process
    ("app.research_export", "app.archive"),
    ("app.manager", "app.gui_watch", "app.main_thread_gc"),  # the composition root
    ("app.scripting",),
    ("app.ui",),
    ("app.application", "app.desktop_entry"),
    ("app.cli",),
)
# Where Qt may be imported (prefixes), and the floors that must not reach it through any import.
QT_PLACES = ("app.ui", "app.devices", "app.manager", "app.main_thread_gc", "app.application", "app.cli",
             "app.scripting.headless", "app.session.reports")
QT_FREE_FLOORS = ("app.wire", "app.core", "app.safety", "app.therapy", "app.session")


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@cache
def app_modules(root: Path = ROOT) -> dict[str, Path]:
    return {module_name(p, root): p for p in sorted((root / "app").rglob("*.py"))}


def _imports(path: Path, name: str) -> Iterator[str]:
    """Every module name an ``import`` statement of ``path`` names (absolute; relative ones resolved)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*base_parts, node.module] if node.module else base_parts)
            else:
                base = node.module or ""
            yield base
            for alias in node.names:
                yield f"{base}.{alias.name}"


def _owner(target: str, modules: dict[str, Path]) -> str | None:
    """The ``app`` module an imported name lives in (``app.devices.driver.Channel`` → ``app.devices.driver``)."""
    while target:
        if target in modules:
            return target
        target = target.rpartition(".")[0]
    return None


@cache
def import_graph(root: Path = ROOT) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(app module → app modules it imports, app module → third-party top-level packages it imports)."""
    modules = app_modules(root)
    internal: dict[str, set[str]] = {}
    external: dict[str, set[str]] = {}
    for name, path in modules.items():
        ins, outs = set(), set()
        for target in _imports(path, name):
            owner = _owner(target, modules)
            if owner is not None:
                if owner != name and not (name.startswith(owner + ".") and modules[owner].name == "__init__.py"):
                    ins.add(owner)
            elif not target.startswith("app"):
                outs.add(target.partition(".")[0])
        internal[name], external[name] = ins, outs
    return internal, external


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = 0
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in graph:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        cycles.append(sorted(component))
    return cycles


def reachable(graph: dict[str, set[str]], start: str) -> dict[str, str]:
    """Every module ``start`` imports, directly or not, with the module that imports it (for the message)."""
    seen: dict[str, str] = {}
    todo = [start]
    while todo:
        node = todo.pop()
        for child in graph.get(node, ()):
            if child not in seen and child != start:
                seen[child] = node
                todo.append(child)
    return seen


def _chain(parents: dict[str, str], start: str, end: str) -> str:
    chain = [end]
    while chain[-1] != start and chain[-1] in parents:
        chain.append(parents[chain[-1]])
    return " → ".join(reversed(chain))


def qt_reach(root: Path, module: str) -> list[str]:
    """How ``module`` reaches Qt, if it does: the import chains, one per offending module."""
    internal, external = import_graph(root)
    parents = reachable(internal, module)
    found = []
    for candidate in [module, *parents]:
        qt = sorted(external.get(candidate, set()) & set(QT_MODULES))
        if qt:
            found.append(f"{_chain(parents, module, candidate)} imports {', '.join(qt)}")
    return found


def untyped_manager_parameters(root: Path = ROOT) -> list[str]:
    """Parameters and annotated attributes named like the manager or a context, typed ``Any`` or untyped,
    outside ``app/ui/``."""
    problems = []
    for name, path in app_modules(root).items():
        if name.startswith("app.ui"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                args = node.args
                for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs]:
                    if arg.arg in MANAGER_NAMES and (isinstance(node, ast.Lambda) or _is_any(arg.annotation)):
                        where = getattr(node, "name", "lambda")
                        problems.append(f"{path.relative_to(root)}:{arg.lineno} {where}({arg.arg}: "
                                        f"{ast.unparse(arg.annotation) if arg.annotation else 'untyped'})")
            elif isinstance(node, ast.AnnAssign):
                target = node.target
                attr = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
                if attr in MANAGER_NAMES and _is_any(node.annotation):
                    problems.append(f"{path.relative_to(root)}:{node.lineno} {ast.unparse(target)}: "
                                    f"{ast.unparse(node.annotation)}")
    return problems


def _is_any(annotation: ast.expr | None) -> bool:
    if annotation is None:
        return True
    text = ast.unparse(annotation).replace("typing.", "").replace(" ", "")
    return text in ("Any", "Any|None", "None|Any", "Optional[Any]", "'Any'", '"Any"', "object")


def floor_of(module: str) -> int:
    best = (-1, -1)
    for level, prefixes in enumerate(FLOORS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best[1]:
                best = (level, len(prefix))
    return best[0]


def arrows_back_up(root: Path = ROOT) -> list[str]:
    internal, _ = import_graph(root)
    return [f"{a} (floor {floor_of(a)}) → {b} (floor {floor_of(b)})"
            for a in sorted(internal) for b in sorted(internal[a]) if floor_of(b) > floor_of(a)]


def _qt_place(module: str) -> bool:
    if module.startswith("app.devices.sim"):
        return False  # the simulators' process never loads Qt
    return any(module == p or module.startswith(p + ".") for p in QT_PLACES)


def qt_outside_its_places(root: Path = ROOT) -> list[str]:
    """Modules that import Qt themselves but are not among :data:`QT_PLACES`, and modules of the Qt-free floors
    that reach Qt through another module (with the chain)."""
    _, external = import_graph(root)
    found = [f"{m} imports {', '.join(sorted(external[m] & set(QT_MODULES)))}"
             for m in sorted(external) if external[m] & set(QT_MODULES) and not _qt_place(m)]
    for m in sorted(app_modules(root)):
        if any(m == f or m.startswith(f + ".") for f in QT_FREE_FLOORS) and not _qt_place(m):
            found += [line for line in qt_reach(root, m) if not line.startswith(f"{m} imports")]
    return found


# ---------------------------------------------------------------------------------------------- the rules
def test_every_module_has_a_floor() -> None:
    homeless = [m for m in app_modules(ROOT) if floor_of(m) <= 0 and m != "app"]
    assert not homeless, f"modules on no floor (put them in a folder of FLOORS): {homeless}"


def test_no_arrow_runs_back_up() -> None:
    up = arrows_back_up(ROOT)
    assert not up, "imports that run back up a floor (move the fact down, or pass it in):\n" + "\n".join(up)


# The one publishing call of each driver (app/devices/driver.py, rehastim.py): a device event goes on the bus and
# out as its Qt signal from there, never from a second path.
PUBLISHING_CALLS = frozenset({"_fire_event", "_record"})


def driver_emits_outside_the_publishing_call(root: Path = ROOT) -> list[str]:
    """``….emit(…)`` calls in the drivers (``app/devices/*.py``) outside their one publishing call."""
    found = []
    for name, path in app_modules(root).items():
        if not name.startswith("app.devices.") or name.startswith("app.devices.sim"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for func in ast.walk(tree):
            if isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)) and func.name not in PUBLISHING_CALLS:
                for node in ast.walk(func):
                    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                            and node.func.attr == "emit"):
                        found.append(f"{path.relative_to(root)}:{node.lineno} {func.name}: {ast.unparse(node)}")
    return sorted(set(found))


def test_every_driver_event_leaves_by_the_one_publishing_call() -> None:
    found = driver_emits_outside_the_publishing_call(ROOT)
    assert not found, "a driver emits a Qt signal beside its publishing call (publish it there):\n" + "\n".join(found)


# ---------------------------------------------------------------------------------------------- the links' facts
# A simulated device's serial link is a file in the runtime folder whose name the driver, the simulator host and
# the registry must agree on: one function names it (app/core/links.py); nobody spells "<device>.tty" again.
LINK_DEFINITION = "app/core/links.py"
LINK_SUFFIX = ".tty"
# The serial rates a link can be opened at (and the range a configured rate must lie in): each number is one fact,
# written in the one place listed here (file, the number, the line's text contains) -> which fact.
BAUD_NUMBERS = frozenset({1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600, 4_000_000})
BAUD_FACTS: dict[tuple[str, int, str], str] = {
    ("app/core/links.py", 115200, "DEFAULT_BAUDRATE: Final = 115200"): "a serial link's rate unless its device says",
    ("app/core/links.py", 1200, "BAUDRATE_RANGE: Final = (1200, 4_000_000)"): "the lowest rate a configuration gives",
    ("app/core/links.py", 4_000_000, "BAUDRATE_RANGE: Final = (1200, 4_000_000)"): "the highest one",
    ("app/core/config.py", 460800, "default=460800"): "the LINarm's rate (the firmware's LINARM_BAUDRATE on its side)",
    ("app/devices/rehastim.py", 115200, '"sm1": SerialSettings(115200'): "ScienceMode 1's fixed link settings",
    ("app/devices/rehastim.py", 460800, '"sm2": SerialSettings(460800'): "ScienceMode 2's fixed link settings",
}
LINK_FACT_FLOORS = ("app/wire/", "app/core/", "app/devices/")


@cache
def _source_tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), str(path))


def link_names_typed(root: Path = ROOT) -> list[str]:
    """String literals (or an f-string's last text) ending in ``.tty`` anywhere in ``app/`` outside
    :data:`LINK_DEFINITION`: a simulated device's link named again."""
    found = []
    for path in sorted((root / "app").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel == LINK_DEFINITION or LINK_SUFFIX not in path.read_text(encoding="utf-8"):
            continue  # (only files that spell it are parsed: the suite pays for every second)
        tree = _source_tree(path)
        parts = {id(v) for node in ast.walk(tree) if isinstance(node, ast.JoinedStr) for v in node.values}
        for node in ast.walk(tree):
            text = node.values[-1] if isinstance(node, ast.JoinedStr) and node.values else node
            if (isinstance(text, ast.Constant) and isinstance(text.value, str) and text.value.endswith(LINK_SUFFIX)
                    and id(node) not in parts):
                found.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")  # type: ignore[attr-defined]
    return sorted(found)


LOOPBACK = "127.0.0.1"  # the simulators' links and the UDP peers' default host: app.core.links.LOOPBACK


def loopback_typed(root: Path = ROOT) -> list[str]:
    """String literals (or an f-string's text) holding the loopback address in ``app/`` outside
    :data:`LINK_DEFINITION`: the driver and the simulator host must agree on it (a socket link's URL)."""
    found = []
    for path in sorted((root / "app").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel == LINK_DEFINITION or LOOPBACK not in path.read_text(encoding="utf-8"):
            continue
        for node in ast.walk(_source_tree(path)):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and LOOPBACK in node.value:
                found.append(f"{rel}:{node.lineno}: {node.value!r}")
    return found


def baud_rates_typed(root: Path = ROOT) -> tuple[list[str], set[tuple[str, int, str]]]:
    """Baud-rate numbers in the wire, the core and the devices outside :data:`BAUD_FACTS` (and the entries used)."""
    found, used = [], set()
    for path in sorted((root / "app").rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if not rel.startswith(LINK_FACT_FLOORS):
            continue
        lines = path.read_text(encoding="utf-8").splitlines()
        for node in ast.walk(_source_tree(path)):
            if (isinstance(node, ast.Constant) and type(node.value) is int and node.value in BAUD_NUMBERS):
                line = lines[node.lineno - 1]
                keys = [key for key in BAUD_FACTS if (key[0], key[1]) == (rel, node.value) and key[2] in line]
                if keys:
                    used.update(keys)
                else:
                    found.append(f"{rel}:{node.lineno}: {node.value} in {line.strip()}")
    return found, used


def test_the_links_facts_are_written_once() -> None:
    """Issue #40: the simulated devices' link names, the serial rates and the loopback address the simulators'
    links use have one definition that everything imports (the code before typed "linarm.tty", "physio.tty",
    "fes.tty" and f"{name}.tty" in five places, the default rate 115200 and the rate range twice, and "127.0.0.1"
    in ten places of config, transport, the patient model and the simulator host)."""
    names = link_names_typed(ROOT)
    rates, used = baud_rates_typed(ROOT)
    hosts = loopback_typed(ROOT)
    assert not names and not rates and not hosts, (
        "a simulated device's link named again (use app.core.links.simulator_link):\n" + "\n".join(names)
        + "\na serial rate typed again (read app.core.links or the device's own settings):\n" + "\n".join(rates)
        + "\nthe loopback address typed again (app.core.links.LOOPBACK, socket_link_url):\n" + "\n".join(hosts))
    assert used == set(BAUD_FACTS), f"stale entries in BAUD_FACTS: {set(BAUD_FACTS) - used}"


# The supervisor's (kind, data) wrappers around the bus's listeners (issue #40): a second way to hear the journal,
# with a subscriber list of its own. Whoever wants the records asks the bus (subscribe(records=True) or listen).
JOURNAL_WRAPPERS = frozenset({"add_event_subscriber", "remove_event_subscriber", "set_event_sink", "event_sink"})


def journal_wrappers_used(root: Path = ROOT) -> list[str]:
    """Definitions, calls and keyword arguments named like the old wrappers, in ``app/``, ``tests/``, ``bench/``
    and ``tools/``."""
    found = []
    for folder in ("app", "tests", "bench", "tools"):
        for path in sorted((root / folder).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            if not any(name in text for name in JOURNAL_WRAPPERS):
                continue  # (only files that spell one are parsed)
            for node in ast.walk(_source_tree(path)):
                name = (node.name if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                        else node.attr if isinstance(node, ast.Attribute)
                        else node.arg if isinstance(node, ast.keyword) else None)
                if name in JOURNAL_WRAPPERS and path.name != "test_architecture.py":
                    found.append(f"{path.relative_to(root).as_posix()}:{getattr(node, 'lineno', '?')}: {name}")
    return found


def test_the_journal_is_heard_on_the_bus_only() -> None:
    found = journal_wrappers_used(ROOT)
    assert not found, "the supervisor's (kind, data) wrappers (listen on the bus instead):\n" + "\n".join(found)


# The run log's own listener list (issue #40): a second way to hear the run changes beside their journal records.
RUN_LOG_LISTENING = frozenset({"subscribe", "_listeners", "_notify"})


def _names_a_run_log(node: ast.expr) -> bool:
    """``runs``, ``self.runs``, ``manager.runs``, ``self._run_log``, ``earlier``… — a run log by the name the code
    gives it (the manager's ``runs``, the runner's ``_run_log``)."""
    name = node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name) else ""
    return name in ("runs", "run_log", "_run_log", "_runs", "live_runs")


def run_log_listeners(root: Path = ROOT) -> list[str]:
    """``RunLog`` defining a listener mechanism (in ``app/core/runs.py``), and any ``<run log>.subscribe(...)`` or
    ``<run log>._listeners`` in ``app/``, ``tests/``, ``bench/`` and ``tools/``."""
    found: list = []
    runs = root / "app" / "core" / "runs.py"
    if runs.exists():
        for node in ast.walk(_source_tree(runs)):
            if isinstance(node, ast.ClassDef) and node.name == "RunLog":
                for inner in ast.walk(node):
                    name = (inner.name if isinstance(inner, (ast.FunctionDef, ast.AsyncFunctionDef))
                            else inner.attr if isinstance(inner, ast.Attribute) else None)
                    if name in RUN_LOG_LISTENING:
                        found.append((inner.lineno, f"app/core/runs.py:{inner.lineno}: RunLog.{name}"))
    found = [text for _line, text in sorted(set(found))]
    for folder in ("app", "tests", "bench", "tools"):
        for path in sorted((root / folder).rglob("*.py")):
            if path.name == "test_architecture.py" or path == runs:
                continue
            text = path.read_text(encoding="utf-8")
            if "subscribe" not in text and "_listeners" not in text:
                continue
            for node in ast.walk(_source_tree(path)):
                if (isinstance(node, ast.Attribute) and node.attr in RUN_LOG_LISTENING
                        and _names_a_run_log(node.value)):
                    found.append(f"{path.relative_to(root).as_posix()}:{node.lineno}: {ast.unparse(node)}")
    return found


def test_runs_are_heard_on_the_bus_only() -> None:
    """Issue #40: a run's start, state and end are journal records (origin ``run``) that the leases and the
    exercise's progress hear on the bus, not a listener list of the run log's own."""
    found = run_log_listeners(ROOT)
    assert not found, "a run log's own listeners (listen to its journal records on the bus):\n" + "\n".join(found)


def test_qt_only_where_it_belongs() -> None:
    found = qt_outside_its_places(ROOT)
    assert not found, "Qt outside the window, the drivers and the composition root:\n" + "\n".join(found)

def test_no_import_circle_in_app() -> None:
    internal, _ = import_graph(ROOT)
    cycles = import_cycles(internal)
    assert not cycles, "import circles in app/ (every import counts, TYPE_CHECKING too):\n" + "\n".join(
        " ↔ ".join(c) for c in cycles)


def test_simulators_codecs_bus_and_command_queue_are_qt_free() -> None:
    modules = app_modules(ROOT)
    checked = [m for m in modules if m.startswith("app.devices.sim")] + [*CODECS, *QT_FREE_CORE]
    missing = [m for m in [*CODECS, *QT_FREE_CORE] if m not in modules]
    assert not missing, f"modules this rule names are gone: {missing} (update the rule)"
    offenders = [line for m in checked for line in qt_reach(ROOT, m)]
    assert not offenders, "Qt reached from simulators / codecs / bus:\n" + "\n".join(offenders)


def test_no_device_module_imports_the_manager() -> None:
    internal, _ = import_graph(ROOT)
    offenders = []
    for name in app_modules(ROOT):
        if name.startswith("app.devices"):
            parents = reachable(internal, name)
            if "app.manager" in parents:
                offenders.append(_chain(parents, name, "app.manager"))
    assert not offenders, "device modules reaching the manager:\n" + "\n".join(offenders)


def test_no_untyped_manager_outside_the_ui() -> None:
    problems = untyped_manager_parameters(ROOT)
    assert not problems, "manager/context typed Any (say what is used instead):\n" + "\n".join(problems)


# ---------------------------------------------------------------------------------------------- the rules' own tests
@pytest.fixture
def toy(tmp_path: Path) -> Path:
    (tmp_path / "app" / "devices" / "sim").mkdir(parents=True)
    for init in ("app", "app/devices", "app/devices/sim"):
        (tmp_path / init / "__init__.py").write_text("")
    return tmp_path


def _write(root: Path, rel: str, text: str) -> None:
    (root / rel).write_text(text)
    app_modules.cache_clear()
    import_graph.cache_clear()


def test_rules_catch_a_circle_a_qt_import_a_manager_import_and_an_any(toy: Path) -> None:
    _write(toy, "app/a.py", "def f():\n    from app import b\n")
    _write(toy, "app/b.py", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from app.a import f\n")
    _write(toy, "app/manager.py", "from typing import Any\nclass M:\n    def __init__(self, app: Any): ...\n")
    _write(toy, "app/devices/helper.py", "from PySide6.QtCore import QObject\nfrom app.manager import M\n")
    _write(toy, "app/devices/sim/core.py", "from app.devices.helper import QObject\n")
    _write(toy, "app/devices/clean.py", "import numpy\nfrom . import helper as _h\n")
    internal, _ = import_graph(toy)
    assert import_cycles(internal) == [["app.a", "app.b"]]
    assert qt_reach(toy, "app.devices.sim.core") == [
        "app.devices.sim.core → app.devices.helper imports PySide6"]
    assert "app.manager" in reachable(internal, "app.devices.clean")  # relative import resolved
    assert untyped_manager_parameters(toy) == ["app/manager.py:3 __init__(app: Any)"]
    assert arrows_back_up(toy) == ["app.devices.helper (floor 4) → app.manager (floor 9)"]
    # app/a.py and app/b.py sit on no floor but the package's; helper is a driver, so its Qt is allowed
    assert qt_outside_its_places(toy) == []
    _write(toy, "app/devices/sim/core.py", "from PySide6.QtCore import QObject\n")
    assert qt_outside_its_places(toy) == ["app.devices.sim.core imports PySide6"]
    _write(toy, "app/devices/helper.py", "class D:\n    def _fire_event(self):\n        self.a.emit(1)\n"
                                         "    def other(self):\n        self.b.emit(2)\n")
    assert driver_emits_outside_the_publishing_call(toy) == ["app/devices/helper.py:5 other: self.b.emit(2)"]
    app_modules.cache_clear()
    import_graph.cache_clear()


def test_rules_catch_a_link_name_a_baud_rate_a_loopback_and_a_journal_wrapper(toy: Path) -> None:
    _write(toy, "app/devices/drv.py", 'from pathlib import Path\nLINK = Path("run") / "robot.tty"\n'
                                      'def sim(name):\n    return f"{name}.tty"\nRATE = 57600\n'
                                      'URL = f"socket://127.0.0.1:{RATE}"\n')
    _write(toy, "app/devices/sup.py", "class S:\n    def add_event_subscriber(self, fn): ...\n")
    assert link_names_typed(toy) == ["app/devices/drv.py:2: 'robot.tty'", "app/devices/drv.py:4: f'{name}.tty'"]
    assert baud_rates_typed(toy) == (["app/devices/drv.py:5: 57600 in RATE = 57600"], set())
    assert journal_wrappers_used(toy) == ["app/devices/sup.py:2: add_event_subscriber"]
    assert loopback_typed(toy) == ["app/devices/drv.py:6: 'socket://127.0.0.1:'"]
    app_modules.cache_clear()
    import_graph.cache_clear()


def test_rule_catches_a_run_log_listener(toy: Path) -> None:
    (toy / "app" / "core").mkdir()
    _write(toy, "app/core/runs.py", "class RunLog:\n    def subscribe(self, fn): ...\n")
    _write(toy, "app/devices/use.py", "def f(manager, bus):\n    manager.runs.subscribe(print)\n"
                                      "    bus.subscribe('x')\n")
    assert run_log_listeners(toy) == ["app/core/runs.py:2: RunLog.subscribe",
                                      "app/devices/use.py:2: manager.runs.subscribe"]
    app_modules.cache_clear()
    import_graph.cache_clear()
