"""What the archive keeps of a session besides its files, derived from the folder before the upload's
transaction: the session row, its exercise runs (app/core/runs.py), their repetitions with their metrics
(app/session/metrics.py) and the journal rows (events.jsonl, hash-chained). The files stay the record; these rows make
the lists and the progress report fast, and are what ``linarmpp archive verify`` checks the chain of."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.archive.chain import canonical, chain_hash, genesis, journal_parts

log = logging.getLogger(__name__)


@dataclass
class Derived:
    session: dict[str, Any]
    runs: list[dict[str, Any]] = field(default_factory=list)
    repetitions: list[dict[str, Any]] = field(default_factory=list)
    journal: list[dict[str, Any]] = field(default_factory=list)


def _float(value: Any) -> float | None:
    try:
        return None if value is None else float(value)
    except (TypeError, ValueError):
        return None


def _start_epoch(start: dict[str, Any]) -> float:
    """The start in epoch seconds (the browser's order): the manifest's, else from its ISO time."""
    epoch = _float(start.get("t_wall_epoch_s"))
    if epoch:
        return epoch
    try:
        import datetime as _dt

        return _dt.datetime.fromisoformat(str(start.get("t_wall", ""))).timestamp()
    except ValueError:
        return 0.0


def derive_session(folder: Path, manifest: dict[str, Any], uuid: str, digest: str, station: str) -> Derived:
    from app.session import metrics as m
    from app.session.recording import load_session

    session = load_session(folder)
    start = manifest.get("start") if isinstance(manifest.get("start"), dict) else {}
    end = manifest.get("end") if isinstance(manifest.get("end"), dict) else {}
    problems = list(session.problems)
    summary: dict[str, Any] = {}
    runs: list[dict[str, Any]] = []
    reps: list[dict[str, Any]] = []
    try:
        computed = m.metrics_of_session(session)
        summary = computed["summary"]
        by_id = {r["run_id"]: r for r in computed["runs"]}
        for position, run in enumerate(m._runs_of(session), start=1):
            got = by_id.get(run.run_id, {})
            runs.append({
                "session_uuid": uuid, "position": position, "run_id": run.run_id,
                "program": canonical(run.program.as_dict(with_text=False)), "title": run.title,
                "parameters": canonical([p.as_dict() for p in run.parameters]), "source": run.source,
                "operator": run.operator, "restart_of": run.restart_of,
                "started_s": run.started_mono - session.start_mono,
                "ended_s": None if run.ended_mono is None else run.ended_mono - session.start_mono,
                "end_reason": run.end_reason, "end_detail": run.end_detail,
                "summary": canonical(got.get("summary") or {}),
            })
            for k, rep in enumerate(got.get("repetitions") or [], start=1):
                reps.append({"session_uuid": uuid, "run_position": position, "idx": k,
                             "run_id": run.run_id, "metrics": canonical(rep)})
    except Exception as exc:  # the files are the record: a session the metrics cannot read is still archived
        log.exception("metrics of %s", folder)
        problems.append(f"the metrics could not be computed at upload: {type(exc).__name__}: {exc}")
    journal = []
    prev = genesis("journal", uuid)
    for seq, e in enumerate(session.events, start=1):
        t_wall, t_mono = str(e.get("t_wall", "")), _float(e.get("t_mono"))
        kind, who, origin = str(e.get("kind", "")), str(e.get("who", "")), str(e.get("origin", ""))
        data = canonical(e.get("data") if isinstance(e.get("data"), dict) else {})
        h = chain_hash(prev, journal_parts(uuid, seq, t_wall, t_mono, kind, who, origin, data))
        journal.append({"session_uuid": uuid, "seq": seq, "t_wall": t_wall, "t_mono": t_mono, "kind": kind,
                        "who": who, "origin": origin, "data": data, "prev_hash": prev, "hash": h})
        prev = h
    titles = [r["title"] for r in runs if r["title"] and r["run_id"] != "session"]
    if not titles:
        titles = [str((e.get("data") or {}).get("name") or "script") for e in session.events
                  if e.get("kind") == "script_start"]
    config = manifest.get("config") if isinstance(manifest.get("config"), dict) else {}
    row = {
        "uuid": uuid, "patient_id": str(manifest.get("patient_id") or folder.parent.name)[:64],
        "station": str(config.get("station") or "") or str((manifest.get("host") or {}).get("node") or "") or station,
        "operator": str(manifest.get("operator", "")), "note": str(manifest.get("note", "")),
        "start_iso": str(start.get("t_wall", "")), "start_epoch_s": _start_epoch(start),
        "end_iso": str(end.get("t_wall", "")) if end else "",
        "duration_s": float(manifest["duration_s"]) if isinstance(manifest.get("duration_s"), int | float)
        else session.duration_s,
        "status": session.status, "app_version": str(manifest.get("app_version", "")),
        "format_version": int(manifest.get("format_version") or 0),
        "folder_name": f"{folder.parent.name}/{folder.name}", "manifest": json.dumps(manifest, ensure_ascii=False),
        "exercises": canonical(titles), "alarms": sum(1 for e in session.events if e.get("kind") == "alarm"),
        "summary": canonical(summary), "problems": canonical(problems), "content_digest": digest,
        "journal_head": prev, "journal_rows": len(journal),
    }
    return Derived(row, runs, reps, journal)

