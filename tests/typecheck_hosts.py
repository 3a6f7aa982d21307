"""Checked by the type checker only (tests/test_types.py), never run: the manager fulfils every Protocol of
app/therapy/services.py that the consumers are typed with, and the script runner the exercises' ExerciseRunner.
A member renamed or retyped on one side and not the other fails the build here, with the member named."""

from __future__ import annotations

from app.manager import LinarmppManager
from app.scripting.runner import ScriptRunner
from app.therapy.services import EventHost, ExerciseRunner, LslHost, ScriptHost, SessionHost


def the_manager_hosts_the_recorder(manager: LinarmppManager) -> SessionHost:
    return manager


def the_manager_hosts_the_lsl_outlets(manager: LinarmppManager) -> LslHost:
    return manager


def the_manager_hosts_an_exercises_start(manager: LinarmppManager) -> EventHost:
    return manager


def the_manager_hosts_the_scripts(manager: LinarmppManager) -> ScriptHost:
    return manager


def the_runner_runs_exercises(runner: ScriptRunner) -> ExerciseRunner:
    return runner
