"""CPU seconds of processes, for the benchmarks (standard library only, so that a script that
imports it runs on a host with nothing installed)."""

from __future__ import annotations

import os
import pathlib
import resource


def process_cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process so far, all its threads (/proc/<pid>/stat)."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children_cpu_s() -> float:
    """user + system CPU seconds of this process's children that have ended."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def threads_cpu_ns(pid: int) -> dict[int, int]:
    """CPU nanoseconds (user + system) of each live thread of a process, by thread id
    (/proc/<pid>/task/<tid>/schedstat: the scheduler's own count, not rounded to clock ticks as
    /proc/<pid>/stat is, whose 10 ms steps are a tenth of a second-long window of a light client)."""
    threads = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            threads[int(tid)] = int(pathlib.Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
        except (FileNotFoundError, ProcessLookupError):  # The thread ended meanwhile.
            pass
    return threads


def threads_cpu_delta_s(before: dict[int, int], after: dict[int, int]) -> float:
    """CPU seconds between two threads_cpu_ns samples of one process: each thread alive at the end
    from its count at the start (0 if it started since); a thread that ended in between is not
    counted."""
    return sum(ns - before.get(tid, 0) for tid, ns in after.items()) / 1e9
