"""The monitor's journal: every record durable, a record cut short by a crash ignored, and the
replay (`swarmnav report`) fed the same messages as the live monitor."""

import json

import pytest

from services.monitor import journal as J


def test_round_trip_and_torn_tail(tmp_path):
    p = J.journal_path(tmp_path)
    w = J.JournalWriter(p, {"run": "r1"})
    w.write(J.ESTIMATE, b'{"a": 1}')
    w.event({"t": 1.0, "kind": "dropout", "uav": 3})
    # no close(): each record is flushed as written (a SIGKILLed writer loses nothing it accepted)
    data = p.read_bytes()
    recs = list(J.read_journal(p))
    assert [k for k, _ in recs] == [J.HEADER, J.ESTIMATE, J.EVENT]
    assert json.loads(recs[0][1]) == {"run": "r1"} and json.loads(recs[2][1])["kind"] == "dropout"
    p.write_bytes(data + J._REC.pack(J.ESTIMATE, 100) + b'{"cut short')  # a crash mid-write
    assert [k for k, _ in J.read_journal(p)] == [J.HEADER, J.ESTIMATE, J.EVENT]
    p.write_bytes(data + b"\xff\x00")  # garbage tail
    assert len(list(J.read_journal(p))) == 3


def test_never_appends_to_another_runs_journal(tmp_path):
    J.JournalWriter(J.journal_path(tmp_path), {"run": "a"}).close()
    with pytest.raises(FileExistsError):
        J.JournalWriter(J.journal_path(tmp_path), {"run": "b"})
