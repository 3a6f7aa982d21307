"""Every codec survives garbage and damaged frames, and decodes the next valid frame (resync).
A smaller count than the full run (bench/fuzz_codecs.py: 10^5 inputs per codec)."""

from __future__ import annotations

import pytest

from tests.fuzz_targets import all_targets, fuzz

TARGETS = all_targets()


@pytest.mark.parametrize("target", TARGETS, ids=[t.name for t in TARGETS])
def test_codec_never_raises_and_resyncs_within_one_frame(target) -> None:
    count, failures = fuzz(target, 2000, seed=12345)
    assert count == 2000
    assert failures == 0, f"{target.name}: {failures} inputs left the decoder unable to decode the next frame"
