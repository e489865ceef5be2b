"""docs/protocol.md is the contract for clients in other languages: it must match the code."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from dhg import _bone_sim
from dhg.core import protocol
from support import schema_fields

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def _doc_layouts() -> dict[str, dict]:
    text = DOC.read_text()
    out: dict[str, dict] = {}
    for m in re.finditer(r"^### `(\w+)` \(kind (\d+), (\d+) bytes\)\n\n(.*?)(?:\n\n|\Z)", text, re.M | re.S):
        rows = []
        for line in m.group(4).splitlines()[2:]:
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows.append((cells[1].strip("`"), cells[2], int(cells[0]), int(cells[3]), cells[4]))
        out[m.group(1)] = {"kind": int(m.group(2)), "size": int(m.group(3)), "fields": rows}
    return out


def test_every_layout_in_the_doc_matches_the_code():
    code = _bone_sim.protocol_layouts()
    doc = _doc_layouts()
    assert set(doc) == set(code)
    for name, layout in code.items():
        assert doc[name]["kind"] == layout["kind"], name
        assert doc[name]["size"] == layout["size"], name
        assert doc[name]["fields"] == [tuple(f) for f in layout["fields"]], name


def test_the_flags_table_matches_the_code():
    rows = re.findall(r"^\| (\d+) \| (\d+) \| `(\w+)` \|", DOC.read_text(), re.M)
    assert {name: int(value) for _, value, name in rows} == protocol.FLAGS
    assert all(int(value) == 1 << int(bit) for bit, value, _ in rows)


def test_the_doc_example_pose_is_a_valid_pose():
    import struct

    fmt = re.search(r'pose = struct\.pack\("([^"]+)"', DOC.read_text()).group(1)
    payload = struct.pack(fmt, 1, 1, 0, 1, 123, 0.01, 0.02, 0.03, 1, 0, 0, 0, 0.0, 0)
    m = protocol.decode("pose", payload)
    assert m["position_m"] == pytest.approx((0.01, 0.02, 0.03))
    assert m["client_time_ns"] == 123


def test_python_encodes_what_the_layouts_say():
    b = protocol.encode_pose(7, 99, [1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0], True, 1000.0)
    assert len(b) == _bone_sim.protocol_layouts()["pose"]["size"]
    assert b[0] == 1 and b[1] == protocol.VERSION
    assert np.frombuffer(b, "<f8", 3, 16).tolist() == [1.0, 2.0, 3.0]
    assert protocol.decode("pose", b)["flags"] & protocol.FLAGS["drill_on"]
    with pytest.raises(ValueError):
        protocol.decode("pose", b[:-1])


def _doc_control_ops() -> list[tuple[str, set[str]]]:
    text = DOC.read_text()
    table = text[text.index("**control**") :].split("\n\n")[1]
    out = []
    for line in table.splitlines()[2:]:
        op, fields, _ = (c.strip() for c in line.strip("|").split("|"))
        while re.search(r"\([^()]*\)", fields):  # what is in parentheses describes a field's values
            fields = re.sub(r"\([^()]*\)", "", fields)
        names = {n for n in re.findall(r"`([a-z_]+)`", fields) if n != "null"}
        out.append((op.strip("`"), names))
    return out


def test_the_control_table_names_exactly_the_ops_and_fields_the_server_takes():
    """The JSON of control requests against the core's ``ControlRequest`` (serde): every op, in
    order, and for each the fields it accepts; a field the doc names that the server would
    refuse as unknown, or one it takes that the doc leaves out, fails here."""
    code = [(op, set(fields)) for op, fields in _bone_sim.control_ops()]
    assert _doc_control_ops() == code


def _doc_paragraph_fields(reply: str) -> set[str]:
    """The backticked names of the doc's ``**<reply>**:`` paragraph (up to the blank line)."""
    m = re.search(rf"^\*\*{reply}\*\*: (.*?)\n\n", DOC.read_text(), re.M | re.S)
    assert m, f"no **{reply}** paragraph in protocol.md"
    return set(re.findall(r"`([a-z_0-9]+)`", m.group(1)))


@pytest.mark.parametrize("reply", ["info", "closed", "metrics", "health", "error"])
def test_the_json_replies_in_the_doc_are_the_rust_types(reply):
    """Each field the Rust reply type (``transport/replies.rs``) serialises is named in the doc's
    paragraph on that reply, and the paragraph names no field the type lacks."""
    schema = _bone_sim.reply_schemas()[reply]
    code = schema_fields(schema)
    doc = _doc_paragraph_fields(reply)
    assert doc - code == set(), f"{reply}: the doc names fields the reply does not have"
    assert code - doc == set(), f"{reply}: the reply has fields the doc does not name"
    # Every field is always written: a client can rely on each being there (an optional one
    # as null, never left out).
    for node in [schema, *schema.get("$defs", {}).values()]:
        for name, field in node.get("properties", {}).items():
            nullable = "null" in field.get("type", []) or {"type": "null"} in field.get("anyOf", [])
            assert name in node.get("required", []) or nullable, (node.get("title"), name)


def test_the_documents_key_table_is_the_cores_key_space():
    """Every key ``docs/protocol.md``'s table lists is one the core builds, and the other way
    round: the session leaves and the server's keys (``protocol/keys.rs``), and the model keys."""
    table = [ln for ln in DOC.read_text().splitlines() if ln.startswith("| `<p>/")]
    listed = {k.split("?")[0] for ln in table for k in re.findall(r"`(<p>/[^`]*)`", ln.split("|")[1])}
    p, sid, w = "<p>", "<id>", "<w>"
    built = {protocol.session_key(p, sid, leaf) for leaf in protocol.SESSION_LEAVES if leaf != "xray"}
    built |= {protocol.session_key(p, sid, "xray/<view>")}
    built |= {protocol.server_key(p, leaf) for leaf in protocol.SERVER_LEAVES}
    built |= {protocol.worker_key(p, w), protocol.worker_predict_key(p, w), protocol.shared_predict_key(p)}
    assert listed == built


def test_a_session_key_gives_back_its_session_and_nothing_else_does():
    key = protocol.session_key("lab/a", "station-1", "xray/top")
    assert key == "lab/a/session/station-1/xray/top"
    assert protocol.session_of("lab/a", key) == "station-1"
    assert protocol.session_of("lab/a", protocol.server_key("lab/a", "health")) is None
    assert protocol.session_of("lab/b", key) is None, "another prefix"
    assert protocol.session_of("lab/a", protocol.session_key("lab/a", "station-1")) is None, "no leaf"
