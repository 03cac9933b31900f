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
