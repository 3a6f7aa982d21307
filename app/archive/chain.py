"""The archive's hash chains (docs/archive.md, "Integrity"): ``hash = SHA-256(prev_hash ␞ field ␞ field …)``
over the stored text of a row; the first row of a chain follows ``genesis(kind, key)``."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from typing import Any

SEP = "\x1e"


def canonical(value: Any) -> str:
    """The stored and hashed text of a JSON value: sorted keys, no spaces, UTF-8 as is."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)


def chain_hash(prev: str, parts: Sequence[Any]) -> str:
    text = SEP.join([prev, *("" if p is None else (repr(p) if isinstance(p, float) else str(p)) for p in parts)])
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def genesis(kind: str, key: str) -> str:
    return hashlib.sha256(f"linarmpp-archive{SEP}{kind}{SEP}{key}".encode()).hexdigest()


def journal_parts(uuid: str, seq: int, t_wall: str, t_mono: float | None, kind: str, who: str, origin: str,
                  data: str) -> list[Any]:
    return [uuid, seq, t_wall, t_mono, kind, who, origin, data]


def history_parts(h: Any) -> list[Any]:
    return [h.patient_id, h.version, h.fields, h.values, h.changed_by, h.changed_station, h.changed_at, h.reason]


def ledger_parts(r: Any) -> list[Any]:
    return [r.seq, r.kind, r.key, r.version, r.head, r.at, r.station]


def session_seal(content_digest: str, journal_head: str, journal_rows: int) -> str:
    """What the ledger seals of a session: its files' digest and its journal's head and length."""
    return hashlib.sha256(SEP.join([content_digest, journal_head, str(journal_rows)]).encode()).hexdigest()
