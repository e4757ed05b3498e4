"""One in-process run's per-UAV estimators spread over worker processes (``swarmnav evaluate``
with one algorithm × seed and ``--jobs`` > 1; ``make bench``).

Each worker is forked (the dataset and settings are inherited, not pickled) and holds a
:class:`swarmnav.evaluation.NodeGroup` of every W-th UAV; the parent runs the rounds
(:func:`swarmnav.evaluation.run_node_epoch`): it sends each worker the round's states of every
live node and collects their next states and finished estimates over a pipe (pickled NodeStates,
~1 % of a round's work at N = 1,000). The nodes compute exactly what they compute in one process —
the same states in the same id order — so the estimates are bit-identical (tests/test_node_workers.py).

A worker that raises sends the exception (its traceback attached as a note) and the parent raises it;
a worker that dies is reported with its exit code; workers exit when the parent's end of the pipe
closes (the parent killed) and are stopped by :meth:`WorkerGroup.close`.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import pickle
import time
import traceback

from swarmnav.evaluation import NodeGroup


def _serve(conn, ds, algo: str, settings: dict, inits: dict, uavs: list[int], inherited=()) -> None:
    # the parent's ends of the pipes (this worker's own and the earlier workers'), copied by the fork:
    # while this process held its own pipe's other end, the parent's death never reached it as EOF
    for c in inherited:
        c.close()
    # what the fork inherited (the dataset, the modules) out of the collector's sight: its passes
    # would write into every inherited object's header and so copy the parent's pages
    gc.freeze()
    try:
        group = NodeGroup(ds, algo, settings, inits, uavs, time.perf_counter)
        conn.send((True, None))
        while True:
            command, arg = conn.recv()
            if command == "stop":
                return
            if command == "step":  # the round's states, pickled once by the parent for every worker
                arg = pickle.loads(conn.recv_bytes())
            group.submit(command, arg)
            conn.send((True, group.result()))
    except (EOFError, KeyboardInterrupt, BrokenPipeError):  # the parent is gone or interrupted
        return
    except Exception as e:  # noqa: BLE001 - sent to the parent, which raises it
        e.add_note(f"in node worker (UAVs {uavs[0]}, {uavs[1] if len(uavs) > 1 else ''}…):\n{traceback.format_exc()}")
        try:
            pickle.loads(pickle.dumps(e))  # the parent must rebuild it too (not so if its __init__ takes other arguments)
            conn.send((False, e))
        except Exception:  # noqa: BLE001 - not picklable: its text
            conn.send((False, RuntimeError(f"{type(e).__name__}: {e}\n{traceback.format_exc()}")))


class WorkerGroup:
    """A :class:`~swarmnav.evaluation.NodeGroup` in a forked worker process, with the same
    ``submit``/``result`` (``submit`` returns at once: the workers compute side by side).
    ``inherited``: the connections of the workers started before this one (the child closes them)."""

    def __init__(self, ctx, ds, algo: str, settings: dict, inits: dict, uavs: list[int], inherited=()):
        self.uavs = list(uavs)
        parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, ds, algo, settings, inits, self.uavs, (parent, *inherited)),
                                name=f"node-worker-{self.uavs[0]}", daemon=True)
        self.proc.start()
        child.close()
        self.conn = parent
        self.result()  # the estimators are built (or their construction failed)

    def submit(self, command: str, arg) -> None:
        try:
            if command == "step":  # arg: the round's states, or their pickle (run_node_epoch's shared_payload)
                self.conn.send((command, None))
                self.conn.send_bytes(arg if isinstance(arg, bytes) else pickle.dumps(arg, pickle.HIGHEST_PROTOCOL))
            else:
                self.conn.send((command, arg))
        except (BrokenPipeError, OSError):
            self._died()

    @staticmethod
    def shared_payload(snapshot: dict) -> bytes:
        """The round's states pickled once for every worker (~35 ms at N = 1,000)."""
        return pickle.dumps(snapshot, pickle.HIGHEST_PROTOCOL)

    def result(self):
        try:
            ok, value = self.conn.recv()
        except (EOFError, OSError):
            self._died()
        if not ok:
            raise value
        return value

    def _died(self):
        self.proc.join(timeout=5.0)
        raise RuntimeError(f"node worker {self.proc.pid} (UAVs {self.uavs[:3]}…) died "
                           f"(exit code {self.proc.exitcode}): the run cannot go on without its nodes")

    def close(self) -> None:
        try:
            self.conn.send(("stop", None))
        except (BrokenPipeError, OSError):
            pass
        self.conn.close()
        self.proc.join(timeout=5.0)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout=5.0)


def worker_groups(workers: int):
    """A ``node_groups`` factory for :func:`swarmnav.evaluation.run_algorithm`: the UAVs dealt
    round-robin (by sorted id) over ``workers`` forked processes (one group in this process if
    ``workers`` <= 1 or there is one UAV)."""

    def make(ds, algo, settings, inits, uavs, clock):
        uavs = sorted(uavs)
        w = max(1, min(int(workers), len(uavs)))
        if w == 1:
            return [NodeGroup(ds, algo, settings, inits, uavs, clock)]
        ctx = mp.get_context("fork")
        groups: list[WorkerGroup] = []
        try:
            for i in range(w):
                groups.append(WorkerGroup(ctx, ds, algo, settings, inits, uavs[i::w], [g.conn for g in groups]))
        except BaseException:
            for g in groups:
                g.close()
            raise
        return groups

    return make
