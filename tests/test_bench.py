"""deploy/bench.py: the report it writes (tables with a size column, the load average beside the figures)
and one tiny in-process measurement. The benchmark itself is `make bench`, not a test."""

import re

import pytest

from deploy import bench


def _inproc_row(n):
    return {"n": n, "duration_s": 5.0, "load1_before": 1.0, "load1_after": 1.5, "simulate_s": 0.1 * n / 18,
            "links_per_uav_epoch": 17.0, "step_ms_p50": 4.0 + n / 100, "step_ms_p99": 9.0, "wall_per_uav_epoch_ms": 5.0 + n / 100,
            "cpu_per_uav_epoch_ms": 5.0, "outside_estimator_per_uav_epoch_ms": 0.2, "epoch_wall_ms_p50": 5.0 * n,
            "realtime_factor": 2.0, "rounds_mean": 10.0, "peak_rss_mb": 100.0}


def test_render_md_has_sizes_and_load():
    res = {"started": "x", "commit": "abc", "density_per_km3": 400.0, "host": {"cpus": 2, "mem_gb": 8, "python": "3.11"},
           "load1_start": 1.0, "load1_end": 2.0, "bench_wall_s": 10.0,
           "inproc": [_inproc_row(n) for n in (18, 50, 100, 300, 1000)] + [{"n": 2000, "duration_s": 1.0, "error": "timeout"}],
           "dist": [{"n": 18, "duration_s": 60.0, "inproc_command_wall_s": 10.0, "dist_command_wall_s": 20.0,
                     "wall_ratio_dist_over_inproc": 2.0, "dist_command_rtf": 3.0, "dist_exit": 0, "dist_complete": True,
                     "memory": {"uav": {"processes": 18, "peak_rss_mb_max": 150.0, "peak_rss_mb_median": 140.0,
                                        "peak_pss_mb_max": None, "peak_pss_mb_median": None}}},
                    {"n": 100, "duration_s": 20.0, "skipped": "time budget"}],
           "profile": {"n": 300, "duration_s": 4.0, "total_s": 10.0, "load1": 1.0,
                       "by_tottime": [{"function": "f", "calls": 1, "tottime_s": 1.0, "cumtime_s": 2.0}],
                       "by_cumtime": [{"function": "g", "calls": 1, "tottime_s": 1.0, "cumtime_s": 2.0}]},
           "notes": ["n"]}
    md = bench.render_md(res)
    assert "load" in md.lower()
    # the table parse of ../shared/checks/perf-scale part c: a size column under a |---| separator
    lines = md.splitlines()
    sizes = set()
    for i, ln in enumerate(lines):
        if i and re.match(r"^\s*\|?\s*:?-{3,}", ln) and "|" in lines[i - 1]:
            head = [c.strip().lower() for c in lines[i - 1].strip().strip("|").split("|")]
            col = next((j for j, h in enumerate(head) if re.match(r"^(n|n_uavs|uavs|swarm size|size)\b", h)), 0)
            for row in lines[i + 1:]:
                if not row.strip().startswith("|"):
                    break
                m = re.fullmatch(r"\**\s*(\d[\d,]*)\s*\**", row.strip().strip("|").split("|")[col].strip())
                if m:
                    sizes.add(int(m.group(1).replace(",", "")))
    assert {18, 50, 100, 300, 1000} <= sizes


@pytest.mark.slow
def test_inproc_one_tiny():
    r = bench.inproc_one(4, 3.0)
    assert r["n"] == 4 and r["epochs"] == 3 and r["step_ms_p50"] > 0 and r["peak_rss_mb"] > 0
    assert r["wall_per_uav_epoch_ms"] > 0 and r["load1_after"] >= 0
