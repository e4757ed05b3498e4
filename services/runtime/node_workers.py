"""One in-process run's per-UAV estimators spread over worker processes (``swarmnav evaluate``
with one algorithm × seed and ``--jobs`` > 1; ``make bench``).

Each worker is forked (the dataset and settings are inherited, not pickled) and holds a
:class:`swarmnav.evaluation.NodeGroup` of every W-th UAV; the parent runs the rounds
(:func:`swarmnav.evaluation.run_node_epoch`): it sends each worker the round's states of every
live node and collects their next states and finished estimates over a pipe (the states pickled,
the estimates packed into arrays: :func:`pack_estimates`). The nodes compute exactly what they compute in one process —
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

import numpy as np

from swarmnav.estimators.base import LinkClass, LinkInfo, NodeEstimate
from swarmnav.evaluation import NodeGroup


def pack_estimates(done: dict[int, NodeEstimate]) -> tuple:
    """A round's finished estimates as a few arrays for the pipe, exact (float64 and int64, every bit
    kept): pickled as objects, 1,000 estimates with their ~24 LinkInfo each (a dataclass and an enum
    apiece) took ~140 ms each way at N = 1,000 — serial work in the parent every epoch. ``unsent``
    (the Zenoh node's history) is not carried: run_algorithm does not read it."""
    es = list(done.values())
    ints = np.array([(e.uav, e.k, e.rounds, len(e.links), e.quat is not None, e.delta_h_m is not None,
                      e.delta_l_m is not None) for e in es], np.int64).reshape(-1, 7)
    floats = np.array([(e.t, e.step_ms, e.delta_h_m if e.delta_h_m is not None else 0.0,
                        e.delta_l_m if e.delta_l_m is not None else 0.0) for e in es], np.float64).reshape(-1, 4)
    z4 = np.zeros(4)
    vecs = np.array([np.concatenate([np.asarray(e.pos, np.float64), np.asarray(e.vel, np.float64),
                                     np.asarray(e.pos_cov, np.float64).ravel(),
                                     z4 if e.quat is None else np.asarray(e.quat, np.float64)]) for e in es],
                    np.float64).reshape(len(es), 19)  # not -1: rows of another length raise, never re-chunk
    links = [li for e in es for li in e.links]
    link_ids = np.array([(li.other, int(li.cls)) for li in links], np.int64).reshape(-1, 2)
    link_vals = np.array([(li.residual_m, li.weight) for li in links], np.float64).reshape(-1, 2)
    return ints, floats, vecs, link_ids, link_vals


def unpack_estimates(packed: tuple) -> dict[int, NodeEstimate]:
    """:func:`pack_estimates`'s estimates again (the same numbers; ``unsent`` None)."""
    ints, floats, vecs, link_ids, link_vals = packed
    cls = {int(c): c for c in LinkClass}  # LinkClass(c) is ~10x slower than a look-up
    links_all = [LinkInfo(o, cls[c], r, w) for (o, c), (r, w) in zip(link_ids.tolist(), link_vals.tolist())]
    out, j = {}, 0
    for (uav, k, rounds, n_links, has_q, has_dh, has_dl), (t, step_ms, dh, dl), v in zip(
            ints.tolist(), floats.tolist(), vecs):
        links = links_all[j:j + n_links]
        j += n_links
        out[uav] = NodeEstimate(uav, k, t, v[0:3].copy(), v[3:6].copy(), v[6:15].reshape(3, 3).copy(),
                                v[15:19].copy() if has_q else None, links, rounds, step_ms,
                                dh if has_dh else None, dl if has_dl else None)
    return out


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
            out = group.result()
            if command == "step":  # (next states, finished estimates): the estimates as arrays
                out = (out[0], pack_estimates(out[1]))
            conn.send((True, out))
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
        self.conn, self._stepped = parent, False
        self.result()  # the estimators are built (or their construction failed)

    def submit(self, command: str, arg) -> None:
        self._stepped = command == "step"  # its result carries packed estimates
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
        if self._stepped:
            value = (value[0], unpack_estimates(value[1]))
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
