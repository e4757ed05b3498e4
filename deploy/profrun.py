"""Dev hook behind ``SWARMNAV_PROFILE=1 swarmnav launch``: run a service module under cProfile with
a CPU-time clock (``time.process_time``; wall-clock profiles of 20 processes sharing 2 cores mostly
measure waiting). Usage: ``python -m deploy.profrun OUT.prof -m services.uav_node ARGS...``."""

import cProfile
import os
import runpy
import sys
import time


def main() -> int:
    out, dash_m, mod = sys.argv[1:4]
    if dash_m != "-m":
        raise SystemExit("usage: python -m deploy.profrun OUT.prof -m MODULE ARGS...")
    sys.argv = [mod, *sys.argv[4:]]
    # SWARMNAV_PROFILE_CLOCK=thread: the main thread's CPU only (process_time also counts Zenoh's threads)
    clock = time.thread_time if os.environ.get("SWARMNAV_PROFILE_CLOCK") == "thread" else time.process_time
    pr = cProfile.Profile(clock)
    code = 0
    pr.enable()
    try:
        runpy.run_module(mod, run_name="__main__", alter_sys=True)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 0
    finally:
        pr.disable()
        pr.dump_stats(out)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
