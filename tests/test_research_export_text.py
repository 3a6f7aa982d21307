"""BIDS text written with numpy over a whole block (issue #41, acceptance 3's speed): the same bytes as the line by
line form, the times read from the lines' first fields as load_session reads them, and a damaged block read line by
line as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.research_export.bids import seconds_text, tsv_block
from app.research_export.source import FolderSource, _line_layout, _parse_lines, open_session
from app.session import recording

LINES = (b"20000.01,0.08107513668150916,nan,-2.4453260180334215e-05,20000.012\n"
         b"20000.015000149997,1e-300,-0.0,900.0,20000.017000149997\n"
         b"19999.9999999996,-nan,NaN,5,20000.02\n"
         b"20000.0200003,0.1,0.2,0.3,20000.0220003\n")


def _session(tmp_path, text: bytes, arrival: bool = True):
    folder = tmp_path / "s"
    (folder / recording.STREAMS_DIR).mkdir(parents=True)
    header = "t_mono_s,a,b,c" + (f",{recording.ARRIVAL_COLUMN}" if arrival else "") + "\n"
    (folder / recording.STREAMS_DIR / "dev.main.csv").write_bytes(header.encode() + text)
    (folder / recording.MANIFEST_FILE).write_text('{"start": {"t_mono_s": 19999.5}, "streams": {"dev.main": '
                                                  '{"file": "streams/dev.main.csv", "device": "dev", '
                                                  '"nominal_rate_hz": 100.0, "channels": null}}}')
    (folder / recording.EVENTS_FILE).write_text("")
    return open_session(FolderSource(folder))


@pytest.mark.parametrize("arrival", [True, False])
def test_the_numpy_text_is_the_line_by_line_text(tmp_path, arrival: bool) -> None:
    text = LINES if arrival else b"".join(ln.rsplit(b",", 1)[0] + b"\n" for ln in LINES.splitlines())
    session = _session(tmp_path, text * 50, arrival)
    (chunk,) = session.chunks("dev.main", raw=True, columns=[])
    assert chunk.layout is not None and chunk.values.shape == (200, 0)
    expected, dropped = _parse_lines(text * 50, 5 if arrival else 4, [0])
    assert dropped == 0 and np.array_equal(chunk.t, expected[:, 0])
    fast = tsv_block(chunk, session.start_mono)
    assert fast == tsv_block(dataclasses.replace(chunk, layout=None), session.start_mono)
    first = fast.split(b"\n")[0].split(b"\t")
    assert first == [b"0.510000000", b"0.08107513668150916", b"n/a", b"-2.4453260180334215e-05"]
    assert fast.split(b"\n")[2].startswith(b"0.500000000\t-n/a\tNaN\t5")  # as the line by line form writes them


def test_a_damaged_block_is_read_line_by_line_as_before(tmp_path) -> None:
    damaged = LINES + b"20000.03,0.1,0.2\n" + b"\n" + LINES  # a line short of fields, a blank line
    assert _line_layout(damaged, 5) is None
    session = _session(tmp_path, damaged)
    (chunk,) = session.chunks("dev.main", raw=True, columns=[])
    assert chunk.layout is None and chunk.raw is None and len(chunk.t) == 8
    assert session.tallies["dev.main"].dropped_lines == 2
    assert tsv_block(chunk, session.start_mono).count(b"\n") == 8


def test_times_to_the_nanosecond_read_back_within_half_a_nanosecond() -> None:
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-10.0, 10_000.0, 100_000), [0.0, 1e-10, -1e-10, 0.9999999996, 9.9999999995,
                                                                  123.0, 99_999.25]])
    chars, lengths = seconds_text(x, ord("\n"))
    lines = chars.tobytes().split(b"\n")[:-1]
    assert len(lines) == len(x) and np.array_equal(lengths, [len(ln) + 1 for ln in lines])
    back = np.array([float(ln) for ln in lines])
    assert np.max(np.abs(back - x)) <= 0.5e-9 + 1e-15 * np.max(np.abs(x)) + 1e-18
    agree = sum(ln == (b"%.9f" % v) for ln, v in zip(lines, x.tolist(), strict=True))
    assert agree >= len(x) - len(x) // 1000  # as %.9f but where x·1e9 rounds across a half nanosecond
    assert seconds_text(np.array([np.nan, 2e9]), ord("\t"))[0].tobytes() == b"nan\t2000000000.000000000\t"
