"""Pre-imported fork server ("zygote") for the UAV node processes of one ``swarmnav launch``.

Why: a UAV process spends ~0.55 s of CPU importing numpy, pydantic, zenoh, gtsam and our modules
before it does any work; with 18-100 UAV processes on 2 cores that is a large share of a short
run, and every process holds its own copy of the modules' heap. The zygote imports all of it once
(``preload``); each UAV process is an ``os.fork()`` of it that runs ``services.uav_node`` as
``__main__``, sharing the imported modules' pages copy-on-write (``gc.freeze()`` keeps the cyclic
collector from touching, and so copying, them).

The zygote never opens a Zenoh session and starts no thread: a fork copies only the calling thread,
so a runtime thread (Zenoh's, OpenBLAS's) would be missing, with its locks possibly held, in every
child. The launcher sets OMP/BLAS threads to 1; ``serve`` refuses to start if the process has more
than one thread.

Protocol, on one AF_UNIX SOCK_SEQPACKET socket the launcher passes as ``--fd`` (JSON messages):

  launcher -> zygote  {"argv": [python, "-m", module, *args], "log": path}
  zygote -> launcher  {"spawned": pid} with a pidfd of the child attached (SCM_RIGHTS), or {"error": why}
                      {"exit": pid, "rc": rc} when a child ends (Popen's convention: -N = killed by signal N)

The child gets what ``subprocess.Popen`` gave a UAV: stdin /dev/null, stdout+stderr appended to
its log, the signal dispositions of a fresh interpreter, PR_SET_PDEATHSIG=SIGTERM (it dies with the
zygote) and the command line of ``<python> -m services.uav_node ...`` in /proc/<pid>/cmdline
(``ps``, psutil and the chaos tools find UAVs by it). It always leaves with ``os._exit``.

The zygote ends when the launcher closes the socket (stopping any child still there: SIGTERM,
SIGKILL after a grace) and dies with the launcher (PR_SET_PDEATHSIG=SIGTERM, set by the launcher).

The launcher's side is :class:`Zygote` (start, ask for processes, collect exits) and
:class:`ZygoteProc`, a ``subprocess.Popen`` look-alike per UAV process (pid, poll, wait,
send_signal, terminate, kill, returncode) so the supervision code is the same for both. Signals go
through the pidfd, so a pid whose process has already ended (and may be reused) is never signalled.
"""

from __future__ import annotations

import argparse
import atexit
import ctypes
import gc
import json
import os
import runpy
import select
import signal
import socket
import subprocess
import sys
import time
import traceback
from pathlib import Path

STOP_GRACE_S = 2.5  # children still there when the launcher goes: SIGTERM, SIGKILL after this
SPAWN_TIMEOUT_S = 120.0  # the first answer waits for the zygote's imports (a few s on a loaded machine)
EXIT_UNKNOWN = -1000  # returncode of a child that ended after its zygote died: no one could wait for it
MAX_MSG = 1 << 16


def _send(sock: socket.socket, msg: dict, fds: list[int] | None = None) -> None:
    data = json.dumps(msg).encode()
    if fds:
        socket.send_fds(sock, [data], fds)
    else:
        sock.send(data)


def _pdeathsig(sig: int = signal.SIGTERM) -> None:
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(sig))  # PR_SET_PDEATHSIG


def cmdline_bytes(argv: list[str]) -> int:
    """Bytes ``argv`` takes in /proc/<pid>/cmdline (NUL-terminated strings)."""
    return sum(len(os.fsencode(a)) + 1 for a in argv)


def set_cmdline(argv: list[str]) -> None:
    """Make /proc/self/cmdline read ``argv``, NUL-separated as for an exec'd process.

    The kernel shows the process's original argument strings, [arg_start, arg_end) of its memory
    (/proc/self/stat fields 48-49), as long as that area ends with a NUL; CPython keeps its own
    copies of its arguments and never reads that memory after start-up. The area cannot grow:
    ``argv`` must fit (the launcher starts the zygote with a command line long enough, see
    :class:`Zygote`); what is left is NUL-padded and shows as trailing empty arguments.
    (setproctitle cannot do this: it writes one string, which /proc then shows as a single argument.)"""
    with open("/proc/self/stat", "rb") as f:
        fields = f.read().rsplit(b")", 1)[1].split()
    start, end = int(fields[45]), int(fields[46])
    raw = b"".join(os.fsencode(a) + b"\0" for a in argv)
    if len(raw) > end - start:
        raise ValueError(f"command line of {len(raw)} bytes does not fit the zygote's {end - start}")
    ctypes.memmove(start, raw.ljust(end - start, b"\0"), end - start)


# -- the zygote process ------------------------------------------------------------------------------


def preload(algo: str) -> None:
    """Import everything a UAV node process runs (its sys.modules, measured on a launch): the node
    service, zenoh, gtsam, numpy, pydantic and the estimator module of ``algo``; compute the code
    digest once (cached: a forked UAV logs the digest of the code it has loaded)."""
    import gtsam  # noqa: F401
    import numpy  # noqa: F401
    import numpy.ma  # noqa: F401  (numpy imports it lazily, in a node's first np.unique: ~10 ms per process)
    import pydantic  # noqa: F401
    import zenoh  # noqa: F401

    import services.uav_node.node  # noqa: F401
    from services.runtime.service import code_digest
    from swarmnav.estimators import registry

    if algo in registry.known() and registry.kind(algo) == "node":
        try:
            registry.estimator_class(algo)
        except registry.UnknownAlgorithmError:
            pass  # the node process says so itself, as without a zygote
    code_digest()


def _exit_code(code) -> int:
    """The process exit status for ``SystemExit(code)``, as the interpreter computes it."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    print(code, file=sys.stderr)
    return 1


def _child(req: dict, zygote_pid: int, close: list[int]) -> None:
    """In the forked child: become ``req["argv"]`` and run its module as ``__main__``; never returns."""
    code = 1
    try:
        try:
            _pdeathsig()
            if os.getppid() != zygote_pid:  # the zygote died between fork and prctl
                os._exit(1)
            signal.set_wakeup_fd(-1)
            for fd in close:
                os.close(fd)
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            signal.signal(signal.SIGINT, signal.default_int_handler)
            null = os.open(os.devnull, os.O_RDONLY)
            log = os.open(req["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            os.dup2(null, 0)
            os.dup2(log, 1)
            os.dup2(log, 2)
            os.close(null)
            os.close(log)
            argv = req["argv"]
            set_cmdline(argv)
            sys.argv = argv[2:]  # [module, *args]; run_module puts the module's file in argv[0]
            runpy.run_module(argv[2], run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as e:
            code = _exit_code(e.code)
        except BaseException:  # noqa: BLE001 - whatever it is, it goes to the log and the process ends
            traceback.print_exc()
            code = 1
        try:
            atexit._run_exitfuncs()  # what interpreter exit would run (logging.shutdown, ...)
            sys.stdout.flush()
            sys.stderr.flush()
        except BaseException:  # noqa: BLE001
            pass
    finally:
        os._exit(code)


def _spawn(req: dict, ctrl: socket.socket, wake: tuple[int, int]) -> int:
    argv = req.get("argv")
    if not (isinstance(argv, list) and len(argv) >= 3 and argv[1] == "-m" and isinstance(req.get("log"), str)):
        raise ValueError(f"bad request {req!r}: expected argv [python, '-m', module, ...] and a log path")
    sys.stdout.flush()
    sys.stderr.flush()
    zygote_pid = os.getpid()
    pid = os.fork()
    if pid == 0:
        _child(req, zygote_pid, [ctrl.fileno(), *wake])
    return pid


def _reap(ctrl: socket.socket | None, live: set[int]) -> None:
    """waitpid every ended child; report each to the launcher (if it is still there)."""
    while live:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        live.discard(pid)
        if ctrl is not None:
            _send(ctrl, {"exit": pid, "rc": os.waitstatus_to_exitcode(status)})


def _stop_children(live: set[int]) -> None:
    """The launcher went away: SIGTERM every child still there, SIGKILL after ``STOP_GRACE_S``."""
    for sig, grace in ((signal.SIGTERM, STOP_GRACE_S), (signal.SIGKILL, 5.0)):
        for pid in live:
            try:
                os.kill(pid, sig)  # not reaped yet: the pid is still this child's
            except ProcessLookupError:
                pass
        end = time.monotonic() + grace
        while live and time.monotonic() < end:
            _reap(None, live)
            time.sleep(0.02)
        if not live:
            return


def serve(ctrl: socket.socket) -> int:
    """Fork a child per request, report every child's exit, until the launcher closes the socket."""
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    signal.set_wakeup_fd(wake_w)  # SIGCHLD wakes the select below
    signal.signal(signal.SIGCHLD, lambda *_: None)
    live: set[int] = set()
    try:
        while True:
            ready, _, _ = select.select([ctrl, wake_r], [], [])
            if wake_r in ready:
                while True:
                    try:
                        if not os.read(wake_r, 512):
                            break
                    except BlockingIOError:
                        break
            _reap(ctrl, live)
            if ctrl not in ready:
                continue
            data = ctrl.recv(MAX_MSG)
            if not data:
                break  # the launcher closed the channel: the launch is over
            try:
                pid = _spawn(json.loads(data), ctrl, (wake_r, wake_w))
            except (ValueError, OSError) as e:
                _send(ctrl, {"error": f"{type(e).__name__}: {e}"})
                continue
            live.add(pid)
            pidfd = os.pidfd_open(pid)  # the child cannot be reaped before: only we reap it
            try:
                _send(ctrl, {"spawned": pid}, [pidfd])
            finally:
                os.close(pidfd)
    except (BrokenPipeError, ConnectionResetError):
        pass  # the launcher is gone
    _stop_children(live)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="deploy.zygote", description="fork server for one launch's UAV node processes")
    p.add_argument("--fd", type=int, required=True, help="the launcher's control socket (AF_UNIX SOCK_SEQPACKET)")
    p.add_argument("--algo", required=True, help="the run's estimator: its module is imported before forking")
    p.add_argument("--run-dir", required=True, help="the run this zygote serves (shown by ps; leftover checks look for it)")
    p.add_argument("--room", default="", help="filler that makes the command line long enough for a UAV's")
    a = p.parse_args(argv)
    ctrl = socket.socket(fileno=a.fd)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C reaches the whole group: the launcher stops us
    c0, t0 = time.process_time(), time.monotonic()
    preload(a.algo)
    from services.runtime.service import code_digest

    set_cmdline([sys.executable, "-m", "deploy.zygote", "--fd", str(a.fd), "--algo", a.algo, "--run-dir", a.run_dir])
    threads = len(os.listdir("/proc/self/task"))
    if threads != 1:
        print(f"zygote: ERROR {threads} threads after the imports: forking would lose them; refusing to serve",
              file=sys.stderr)
        return 2
    print(f"zygote: pid {os.getpid()}, imports {time.process_time() - c0:.2f} CPU-s ({time.monotonic() - t0:.2f} s wall), "
          f"code {code_digest()}, {len(sys.modules)} modules; serving", file=sys.stderr)
    gc.freeze()  # the imported objects go to a permanent generation: collections in a child do not write to them
    return serve(ctrl)


# -- the launcher's side -----------------------------------------------------------------------------


class ZygoteLost(RuntimeError):
    """The zygote died, stopped answering or refused a request: the launch cannot go on (message: why,
    e.g. "killed by SIGKILL")."""


class Zygote:
    """The launcher's handle on its zygote process: start it, ask it for processes, collect their exits.

    ``argvs``: every command line it will be asked for (the zygote's own is padded to fit the longest,
    see :func:`set_cmdline`); ``log``: its output, appended; ``popen_kw``: env/cwd/preexec_fn for
    ``subprocess.Popen``."""

    def __init__(self, run_dir: Path, algo: str, argvs: list[list[str]], log: Path, **popen_kw):
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        argv = [sys.executable, "-m", "deploy.zygote", "--fd", str(theirs.fileno()), "--algo", algo, "--run-dir", str(run_dir)]
        room = max(map(cmdline_bytes, argvs), default=0) - cmdline_bytes(argv) - len("--room") - 2
        self.argv = argv + (["--room", "x" * room] if room > 0 else [])
        self.log = log
        try:
            with open(log, "ab") as f:
                self.p = subprocess.Popen(self.argv, pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, stdout=f,
                                          stderr=subprocess.STDOUT, **popen_kw)
        finally:
            theirs.close()
        self.sock = ours
        self.exits: dict[int, int] = {}  # pid -> returncode, reported and not yet collected by its ZygoteProc
        self.lost: str | None = None  # why the zygote can no longer be used, e.g. "killed by SIGKILL"
        self.hung: str | None = None  # set by close() when the zygote had to be killed
        self._reply: tuple[dict, list[int]] | None = None

    def _fail(self, why: str) -> None:
        """Mark the zygote lost: by how its process ended if it did (within 1 s), else by ``why``."""
        if self.lost is None:
            try:
                rc = self.p.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                self.lost = why
                return
            self.lost = (f"exit {rc}" if rc >= 0 else f"killed by {signal.Signals(-rc).name}"
                         if -rc in signal.valid_signals() else f"killed by signal {-rc}")

    def pump(self, timeout: float) -> None:
        """Read every message that arrives within ``timeout`` s (0: only those already there)."""
        end = time.monotonic() + timeout
        while self.lost is None:
            left = max(0.0, end - time.monotonic())
            if not select.select([self.sock], [], [], left)[0]:
                return
            try:
                data, fds, _, _ = socket.recv_fds(self.sock, MAX_MSG, 1)
            except OSError as e:
                self._fail(f"its control channel failed: {e}")
                return
            if not data:
                self._fail("it closed its control channel")
                return
            msg = json.loads(data)
            if "exit" in msg:
                self.exits[msg["exit"]] = msg["rc"]
            else:
                self._reply = (msg, fds)
            end = time.monotonic()  # after a message: drain what is there, do not wait again

    def check(self) -> str | None:
        """Why the zygote is gone (None while it serves)."""
        self.pump(0.0)
        if self.lost is None and self.p.poll() is not None:
            self._fail("its process ended")
        return self.lost

    def spawn(self, argv: list[str], log: Path) -> ZygoteProc:
        """A new process running ``argv`` (``[python, "-m", module, ...]``), output appended to ``log``."""
        if self.lost:
            raise ZygoteLost(self.lost)
        try:
            _send(self.sock, {"argv": argv, "log": str(log)})
        except OSError as e:
            self._fail(f"its control channel failed: {e}")
            raise ZygoteLost(self.lost) from None
        end = time.monotonic() + SPAWN_TIMEOUT_S
        while self._reply is None:
            if self.check():
                raise ZygoteLost(self.lost)
            if time.monotonic() > end:
                raise ZygoteLost(f"no answer within {SPAWN_TIMEOUT_S:.0f} s")
            self.pump(0.5)
        (msg, fds), self._reply = self._reply, None
        if "error" in msg:
            raise ZygoteLost(f"it refused {argv[:3]}: {msg['error']}")
        if len(fds) != 1:
            raise ZygoteLost(f"its answer {msg} came without a pidfd")
        os.set_inheritable(fds[0], False)
        return ZygoteProc(self, msg["spawned"], fds[0], argv)

    def close(self) -> int | None:
        """End the zygote (call when every child is gone): close the channel, wait, SIGKILL if it hangs."""
        self.sock.close()
        try:
            return self.p.wait(timeout=STOP_GRACE_S + 5.0)
        except subprocess.TimeoutExpired:
            self.hung = f"it did not exit within {STOP_GRACE_S + 5.0:.1f} s of the run's end (stopped or hung): killed"
            self.p.kill()
            return self.p.wait()


class ZygoteProc:
    """A process forked by the zygote, with the part of ``subprocess.Popen``'s interface the launcher uses.

    The exit status comes from the zygote's report. If the zygote dies first, the process (which
    PR_SET_PDEATHSIG stops then) is followed through its pidfd, and its status is ``EXIT_UNKNOWN``."""

    def __init__(self, zygote: Zygote, pid: int, pidfd: int, args: list[str]):
        self.zygote, self.pid, self.args = zygote, pid, args
        self._pidfd: int | None = pidfd
        self.returncode: int | None = None

    def _ended(self, rc: int) -> None:
        self.returncode = rc
        os.close(self._pidfd)
        self._pidfd = None

    def _collect(self) -> None:
        if self.pid in self.zygote.exits:
            self._ended(self.zygote.exits.pop(self.pid))
        elif self.zygote.lost is not None and select.select([self._pidfd], [], [], 0)[0]:
            self._ended(EXIT_UNKNOWN)

    def poll(self) -> int | None:
        if self.returncode is None:
            self.zygote.pump(0.0)
            self._collect()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        end = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = 0.5 if end is None else min(0.5, end - time.monotonic())
            if left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            if self.zygote.lost is None:
                self.zygote.pump(left)
                self.zygote.check()
            else:
                select.select([self._pidfd], [], [], left)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                signal.pidfd_send_signal(self._pidfd, sig)
            except ProcessLookupError:  # ended, not yet reported
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


if __name__ == "__main__":
    raise SystemExit(main())
