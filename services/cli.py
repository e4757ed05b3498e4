"""`swarmnav` command line: thin entry point (parser -> config -> run), one module per command.

Each command lives in ``services/commands/<name>.py`` and exposes ``HELP``, ``add_arguments(parser)``
and ``run(args) -> int``. User errors (:class:`swarmnav.errors.SwarmnavError`) are printed as one
clear message without a traceback and exit with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS thread (before numpy loads): the estimators solve many small systems one after another,
# where OpenBLAS's threads only add overhead (in-process scale N = 100: 314 -> 142 CPU-s, 161 -> 142 s
# wall), and the UAV processes of a launch run single-threaded too (deploy/launcher.py), so evaluate
# computes as they do. A value the user set is kept.
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

COMMANDS = {
    "simulate": "services.commands.simulate",
    "evaluate": "services.commands.evaluate",
    "launch": "services.commands.launch",
    "calibrate": "services.commands.calibrate",
    "import-miluv": "services.commands.import_miluv",
    "report": "services.commands.report",
    "keys": "services.commands.keys",
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="swarmnav",
        description="Cooperative navigation for UAV swarms (adaptive time-varying factor graph) — "
        "simulate scenarios, evaluate estimators in-process, or launch the Zenoh swarm.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, modname in COMMANDS.items():
        mod = importlib.import_module(modname)
        sp = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP),
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(sp)
        sp.set_defaults(_run=mod.run)
    return p


class Terminated(KeyboardInterrupt):
    """SIGTERM in the command's own process: unwinds like Ctrl-C, so that worker pools are
    terminated on the way out (``with Pool``) instead of being orphaned and computing on."""


def _on_sigterm(main_pid: int):
    import signal

    def handler(signum, frame):
        if os.getpid() != main_pid:  # a forked worker inherited this handler: die as by default
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise Terminated()

    return handler


def install_sigterm() -> None:
    """SIGTERM unwinds this process like Ctrl-C (:class:`Terminated`); a forked child (evaluate's
    pool and node workers, the zygote) gets the default SIGTERM back at once: with a Python handler,
    a SIGTERM the kernel hands to one of the child's other threads (a queue's feeder thread) waits
    for its main thread, which may be blocked in a read, so Pool.terminate() waited forever on that
    worker (a rare hang at the end of evaluate, under load)."""
    import signal

    signal.signal(signal.SIGTERM, _on_sigterm(os.getpid()))
    os.register_at_fork(after_in_child=_default_sigterm)


def _default_sigterm() -> None:
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def main(argv: list[str] | None = None) -> int:
    import signal

    from swarmnav.errors import SwarmnavError

    args = build_parser().parse_args(argv)
    install_sigterm()  # launch installs its own SIGTERM/SIGINT handling for the swarm while it runs
    try:
        rc = int(args._run(args) or 0)
        sys.stdout.flush()  # here, so that a closed pipe is caught below rather than at interpreter exit
        return rc
    except SwarmnavError as e:
        print(f"swarmnav {args.command}: error: {e}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"\nswarmnav {args.command}: error: out of memory: the run is too large for this machine; reduce "
              "swarm.n_uavs, scenario.duration_s or scenario.imu_rate_hz (e.g. --set scenario.duration_s=60)",
              file=sys.stderr)
        return 1
    except Terminated:
        print(f"\nswarmnav {args.command}: terminated (SIGTERM): stopped before the end, its output is incomplete "
              "(no report.json is written)", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        # on a line of its own (a progress bar may be half drawn); launch reports its own stop
        print(f"\nswarmnav {args.command}: interrupted: stopped before the end, its output is incomplete (no report.json is written)", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into a reader that stopped (`| head`): no traceback, exit as SIGPIPE would
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115  (the interpreter flushes stdout at exit)
        return 141


if __name__ == "__main__":
    sys.exit(main())
