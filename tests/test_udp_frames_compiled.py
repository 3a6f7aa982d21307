"""The compiled UDP codecs (#16: generated packers, binascii CRC, pre-keyed HMAC) put the same bytes on the wire
as the table read field by field, for any values: checked against a plain reference written from the tables."""

from __future__ import annotations

import hashlib
import hmac
import math
import struct
from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from app.wire import udp_frames as uf
from app.wire.physio_codec import Field, Layout, crc16_ccitt


def reference_pack(layout: Layout, values: dict[str, Any]) -> bytes:
    """The layout table read one field at a time (the pre-#16 algorithm)."""
    raws: list[Any] = []
    for f in layout.fields:
        if f.name == "header":
            raws.append(layout.header)
        elif f.name in ("crc", "reserved"):
            raws.append(0 if f.name == "crc" else b"")
        elif f.fmt == "f":
            raws.append(float(values[f.name]))
        else:
            lo, hi, na = uf._INT_LIMITS[f.fmt]
            v = values[f.name]
            if f.scale is None:
                lo, hi = (-32768, 32767) if f.fmt == "h" else (0, 65535) if f.fmt == "H" else (lo, hi)
                raws.append(min(hi, max(lo, int(v))))
            elif math.isnan(v):
                raws.append(na)
            else:
                raws.append(min(hi, max(lo, round(v / f.scale))))
    body = struct.pack(layout.struct_format, *raws)[:-2]
    return body + struct.pack("<H", crc16_ccitt(body))


def field_values(layout: Layout) -> st.SearchStrategy[dict[str, Any]]:
    def one(f: Field) -> st.SearchStrategy[Any]:
        if f.fmt == "f":
            return st.floats(-1e6, 1e6, width=32)
        if f.scale is None:
            return st.integers(-100, 70000)
        nan_ok = uf._INT_LIMITS[f.fmt][2] is not None
        return st.floats(-1e9, 1e9) | (st.just(math.nan) if nan_ok else st.nothing())
    return st.fixed_dictionaries({f.name: one(f) for f in layout.fields if f.name not in ("header", "crc", "reserved")})


@given(st.data())
def test_the_generated_packers_match_the_table_read_field_by_field(data) -> None:
    for layout in uf.ALL_UDP_LAYOUTS:
        values = data.draw(field_values(layout))
        packed = uf._pack(layout, values)
        assert packed == reference_pack(layout, values)
        assert len(packed) == layout.size


@given(st.binary(max_size=64))
def test_the_crc_is_crc16_ccitt_false(data: bytes) -> None:
    assert uf.crc16(data) == crc16_ccitt(data)


@given(st.binary(max_size=64), st.binary(min_size=16, max_size=64))
def test_the_pre_keyed_mac_is_hmac_sha256(frame: bytes, key: bytes) -> None:
    assert uf.mac(key, frame) == hmac.new(key, frame, hashlib.sha256).digest()[:uf.MAC_SIZE]
