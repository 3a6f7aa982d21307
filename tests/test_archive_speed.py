"""What makes the archive's listing and a long session's upload fast (issue #39, acceptance 5; the figures are
bench/bench_archive.py's) gives the same results as before: the listing's records are SessionInfo's own, the stream
files parsed by pandas are bit for bit Python's float() (and anything else is parsed as before), a window of a
signal by binary search holds the samples the comparison held, and on PostgreSQL an upload's chunks are stored
compressed with lz4 and read back byte for byte."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import text

from app.archive.api import SessionInfo
from app.archive.store import open_archive
from app.session.metrics import Series
from app.session.recording import _PANDAS_MIN_BYTES, csv_values, read_stream_csv
from tests.postgres import APP, PostgresServer
from tests.run_sessions import RunSpec, write_run_session
from tests.test_archive_postgres import pg_server  # noqa: F401  (the session's server, shared with that file)


def test_the_listing_makes_the_records_sessioninfo_makes(tmp_path: Path) -> None:
    with open_archive(url=f"sqlite:///{tmp_path / 'a.sqlite3'}", station="room-A") as a:
        for k, titles in enumerate((["Trigger reaching"], ["Trigger reaching", "Temperature follow"], [])):
            folder = write_run_session(tmp_path / "s" / "PZ-017" / f"2026030{k + 1}-100000",
                                       [RunSpec(t, "trigger_reaching", reps=1) for t in titles],
                                       start_iso=f"2026-03-0{k + 1}T10:00:00+01:00")
            a.upload_session(folder)
        listed = a.list_sessions()
        assert len(listed) == 3 and [s.start[:10] for s in listed] == ["2026-03-03", "2026-03-02", "2026-03-01"]
        for info in listed:
            again = SessionInfo(**{f.name: getattr(info, f.name) for f in dataclasses.fields(SessionInfo)})
            assert info == again and repr(info) == repr(again) and hash(info) == hash(again)
            assert isinstance(info.exercises, tuple)
            with pytest.raises(dataclasses.FrozenInstanceError):
                info.station = "x"  # type: ignore[misc]
        assert listed[1].exercises == ("Trigger reaching", "Temperature follow")
        assert listed[0].exercises == () and listed[2].exercises == ("Trigger reaching",)


def _body(rows: int, seed: int = 1) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(seed)
    values = rng.standard_normal((rows, 5)) * 10.0 ** rng.integers(-12, 12, (rows, 5))
    values[5, 1], values[7, 2], values[9, 3], values[11, 0] = np.nan, np.inf, -np.inf, -0.0
    values[13, 4], values[15, 1] = 5e-324, 1.7976931348623157e308
    body = "".join(",".join(repr(float(x)) for x in row) + "\n" for row in values).encode()
    return body, values


def test_pandas_reads_the_recorders_numbers_bit_for_bit_and_leaves_anything_else_to_float(tmp_path: Path) -> None:
    body, values = _body(12_000)
    assert len(body) > _PANDAS_MIN_BYTES
    fast = csv_values(body, 5)
    assert fast is not None and fast.shape == values.shape
    assert np.array_equal(fast.view(np.int64), values.view(np.int64))  # nan, ±inf, -0.0, subnormal, max included
    # not plain numbers: None (the caller's parse decides, line by line as before)
    for bad in (body.replace(b"\n", b",,\n", 1), body.replace(b"0", b'"0"', 1), body.replace(b",", b", ", 1),
                body.replace(b"\n", b"\r\n"), body.replace(b"1", b"x", 1), body[:5000]):
        assert csv_values(bad, 5) is None
    # read_stream_csv through it: the same table as Python's float() of each field, a damaged line dropped as before
    path = tmp_path / "s.csv"
    path.write_bytes(b"t,a,b,c,d\n" + body)
    header, table, dropped = read_stream_csv(path)
    assert (header, dropped) == (["t", "a", "b", "c", "d"], 0)
    assert np.array_equal(table.view(np.int64), values.view(np.int64))
    lines = body.split(b"\n")
    lines[100] = b"1.0,2.0,oops,4.0,5.0"
    path.write_bytes(b"t,a,b,c,d\n" + b"\n".join(lines))
    _header, table, dropped = read_stream_csv(path)
    assert dropped == 1 and len(table) == len(values) - 1
    assert np.array_equal(table[100].view(np.int64), values[101].view(np.int64))


def test_a_window_by_binary_search_holds_the_samples_the_comparison_held() -> None:
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.choice([0.0, 0.005, 0.01], 5000))  # in order, with repeated times
    ordered = Series(t, rng.standard_normal(5000))
    shuffled = Series(rng.permutation(t), ordered.v)
    with_nan = Series(np.where(np.arange(5000) == 70, np.nan, t), ordered.v)
    bounds = [(1.0, 2.0), (t[10], t[10]), (t[20], t[10]), (-np.inf, np.inf), (np.nan, 3.0), (1.0, np.nan),
              (t[-1] + 1, t[-1] + 2), (t[0] - 2, t[0] - 1), (t[100], t[200])]
    for series in (ordered, shuffled, with_nan):
        for t0, t1 in bounds:
            sel = (series.t >= t0) & (series.t <= t1)
            got_t, got_v = series.between(t0, t1)
            assert np.array_equal(got_t, series.t[sel], equal_nan=True) and np.array_equal(got_v, series.v[sel])
            assert np.array_equal(series.window(t0, t1), series.v[sel])


def test_on_postgresql_the_uploaded_chunks_are_lz4_and_read_back_byte_for_byte(
        pg_server: PostgresServer, tmp_path: Path) -> None:  # noqa: F811
    db = pg_server.new_database()
    folder = write_run_session(tmp_path / "s" / "PZ-017" / "20260302-100000",
                               [RunSpec("Trigger reaching", "trigger_reaching", reps=3)])
    with open_archive(url=db.url(APP), password_file=db.password_file(APP), station="room-A") as a:
        with a.engine.connect() as conn:
            offered = conn.execute(text("SELECT 'lz4' = ANY(enumvals) FROM pg_settings "
                                        "WHERE name = 'default_toast_compression'")).scalar()
        if not offered:
            pytest.skip("this PostgreSQL server has no lz4 (older than 14, or built without it)")
        uuid = a.upload_session(folder).uuid
        with a.engine.connect() as conn:
            methods = {r[0] for r in conn.execute(text("SELECT DISTINCT pg_column_compression(data) FROM blob_chunks"))}
            default = conn.execute(text("SHOW default_toast_compression")).scalar()
        assert methods <= {"lz4", None} and "lz4" in methods  # (a chunk too small to compress: None)
        assert default == "pglz"  # SET LOCAL: the upload's transaction only
        files = a.session_files(uuid)
        for info in files.files():
            assert files.read_bytes(info.name) == (folder / info.name).read_bytes()
        assert a.verify().ok
        assert json.loads(files.read_bytes("manifest.json"))["patient_id"] == "PZ-017"
