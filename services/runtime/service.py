"""Runtime shared by the Zenoh services (uav_node, sensor_sim, monitor): inbox, signals, logging.

Heavy work never runs in a Zenoh callback (gtsam holds the GIL; starving callbacks lose samples,
docs/deployment.md). Every subscriber/queryable gets a ``FifoChannel`` handler and one small pump thread
of ours that blocks in ``recv()`` (GIL released) and appends the sample to a deque; the service
loop drains the deque. The loop is woken through an Event only while it waits, and a pump may take
a ``direct`` function that consumes the item in the pump thread (light work only: e.g. decode and
store a peer state) and says whether the loop must wake, so that a node waiting for 17 peer states
is woken once per round instead of once per state (every wake-up costs ~30-40 us of CPU on a
2-core VM shared by 20 processes; polling the channels with try_recv cost more, ~40 us a poll).
When the loop is busy the Rust channel buffers.

SIGTERM/SIGINT set a stop flag and wake the loop; the service then closes its session
explicitly (a declared subscriber left open hangs interpreter exit).
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import sys
import threading
import time
from collections import deque

CHANNEL_CAPACITY = 100_000


def _name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` in /proc (``top -H``, per-thread CPU): Python 3.11 names
    its threads for Python only. Best effort (Linux prctl PR_SET_NAME, 15 bytes)."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        pass


class Inbox:
    """(tag, item) pairs fed by pump threads, one per Zenoh channel handler."""

    def __init__(self):
        self.items: deque = deque()
        self.ev = threading.Event()
        self._threads: list[threading.Thread] = []
        self.stop = threading.Event()
        self.counts: dict[str, int] = {}  # items received per tag (logged at exit: where a process's messages came from)

    def channel(self):
        import zenoh

        return zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)

    def attach(self, tag: str, source, direct=None) -> None:
        """Pump ``source.recv()`` (Subscriber/Queryable/reply handler) into the inbox as (tag, item),
        or, with ``direct``, call ``direct(item)`` in the pump thread and wake the loop if it returns True."""

        def pump():
            _name_os_thread(f"pump-{tag}")
            while not self.stop.is_set():
                try:
                    item = source.recv()
                except Exception:  # channel closed (undeclared / session closed)
                    return
                self.counts[tag] = self.counts.get(tag, 0) + 1
                if direct is not None:
                    try:
                        if direct(item):
                            self.ev.set()
                    except Exception:  # never let a bad item end the pump
                        logging.getLogger(__name__).exception("pump %s", tag)
                    continue
                self.items.append((tag, item))
                self.ev.set()

        th = threading.Thread(target=pump, name=f"pump-{tag}", daemon=True)
        th.start()
        self._threads.append(th)

    def get(self, timeout: float | None, clear: bool = True):
        """The next (tag, item), waiting up to ``timeout`` s; None if nothing came (or woken).
        ``clear=False``: the caller cleared ``ev`` itself before checking its own wake condition."""
        if self.items:
            return self.items.popleft()
        if timeout == 0:
            return None
        if clear:
            self.ev.clear()
        if self.items:
            return self.items.popleft()
        self.ev.wait(timeout)
        return self.items.popleft() if self.items else None

    def wake(self) -> None:
        self.ev.set()

    def join(self, timeout: float = 5.0) -> list[str]:
        """Wait for the pump threads to end (call after the session is closed: closing drops the
        channels' senders, so every ``recv()`` returns). Returns the names of threads still alive.

        Needed because CPython <= 3.13 ends a daemon thread that is still inside ``recv()`` at
        interpreter exit with ``pthread_exit``; unwinding that through zenoh's Rust frames aborts
        the process ("FATAL: exception not rethrown", exit -6) after the work is done."""
        self.stop.set()
        end = time.monotonic() + timeout
        for th in self._threads:
            th.join(max(0.0, end - time.monotonic()))
        return [th.name for th in self._threads if th.is_alive()]


def finish_process(inbox: Inbox, log: logging.Logger, rc: int) -> int:
    """End a service after its session is closed: join the pump threads; if one is still stuck
    in a Zenoh call, leave with ``os._exit`` (files are closed by then) instead of letting the
    interpreter's finalisation abort the process."""
    stuck = inbox.join()
    if stuck:
        log.warning("pump threads still blocked after close: %s; exiting without finalisation", stuck)
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def undeclare_all(subs) -> None:
    """Undeclare every subscriber/queryable in ``subs`` before the session closes; one that is
    already gone (undeclared, or its channel closed with the session) is skipped."""
    for s in subs:
        try:
            s.undeclare()
        except Exception:  # already undeclared / session closing: nothing left to release
            pass


def parse_key(key_expr, rejects):
    """``keys.parse`` of a received sample's or query's key; a malformed key is counted in ``rejects``
    (``swarmnav.wire.messages.Rejects``) as ``bad_key`` and gives None."""
    try:
        return _keys().parse(str(key_expr))  # cached by key: ~0.3 µs for a key seen before
    except ValueError as e:
        from swarmnav.wire import messages as M

        rejects.add(str(key_expr), M.WireError("bad_key", str(e)))
        return None


@functools.cache
def _keys():
    """``swarmnav.wire.keys``, imported on first use (an import statement in parse_key cost ~1.5 µs
    per received sample: ~0.3 ms per epoch for a node of a 100-UAV swarm)."""
    from swarmnav.wire import keys

    return keys


def install_signals(inbox: Inbox) -> None:
    def handler(signum, frame):
        inbox.stop.set()
        inbox.wake()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


@functools.cache
def code_digest() -> str:
    """12 hex of the sha256 over the swarmnav core sources (path + bytes) this process runs.

    Logged by every node at start-up: an in-process and a distributed run only agree when both ran
    the same estimator code, and a source file edited between two process starts is otherwise
    invisible (``git describe`` only says "-dirty"). Computed once, right after the imports: a UAV
    process forked by the zygote (deploy/zygote.py) inherits the digest of the code it has loaded,
    not of the files on disk at its fork."""
    import hashlib
    from pathlib import Path

    import swarmnav

    root = Path(swarmnav.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def setup_logging(name: str) -> logging.Logger:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s.%(msecs)03d {name} %(levelname)s %(message)s", datefmt="%H:%M:%S")
    return logging.getLogger(name)


class Deadline:
    def __init__(self, seconds: float):
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return max(0.0, self.end - time.monotonic())

    def passed(self) -> bool:
        return time.monotonic() >= self.end
