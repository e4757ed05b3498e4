"""The monitor's append-only journal: everything it receives, durable every record.

``<run>/journal/monitor.jnl`` is a sequence of records ``kind (1 byte) | length (uint32 LE) |
payload``: ``H`` the run header (JSON: run id, dataset, seed, algo, schedule, security), ``E`` an
estimate message as received (JSON bytes, already validated), ``C`` a clock message, ``V`` an event
(JSON). Each record is written with one ``write`` and flushed, so a SIGKILLed monitor loses nothing
it had accepted (the kernel holds the bytes); a record cut short by a crash mid-write is detected by
its length and ignored. ``swarmnav report RUN_DIR`` replays the journal to rebuild report.json,
report.md, estimates.npz and the recording.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path

HEADER, ESTIMATE, CLOCK, EVENT = b"H", b"E", b"C", b"V"
_REC = struct.Struct("<cI")
MAX_RECORD = 16 << 20


def journal_path(run_dir: Path) -> Path:
    return Path(run_dir) / "journal" / "monitor.jnl"


class JournalWriter:
    def __init__(self, path: Path, header: dict):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.f = open(path, "xb")  # never append to another run's journal
        self.write(HEADER, json.dumps(header).encode())

    def write(self, kind: bytes, payload: bytes) -> None:
        self.f.write(_REC.pack(kind, len(payload)) + payload)
        self.f.flush()

    def event(self, ev: dict) -> None:
        self.write(EVENT, json.dumps(ev).encode())

    def close(self) -> None:
        self.f.close()


def read_journal(path: Path) -> Iterator[tuple[bytes, bytes]]:
    """(kind, payload) of every complete record; a truncated tail (crash mid-write) ends the stream."""
    data = Path(path).read_bytes()
    o = 0
    while o + _REC.size <= len(data):
        kind, n = _REC.unpack_from(data, o)
        if kind not in (HEADER, ESTIMATE, CLOCK, EVENT) or n > MAX_RECORD or o + _REC.size + n > len(data):
            return
        yield kind, data[o + _REC.size:o + _REC.size + n]
        o += _REC.size + n
