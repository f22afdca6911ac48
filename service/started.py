"""When this process started, on time.perf_counter()'s clock: a command bounded in wall time
(`elastreg train --minutes`) counts from there, its interpreter's start and imports included."""

from __future__ import annotations

import os
import time

#: the most a process can plausibly take from its exec to the command's entry (the interpreter
#: and the imports, 6 s on a loaded 2-core machine); a longer age is a clock that reads wrong
MAX_START_S = 60.0


def process_started(entered: float) -> float:
    """The perf_counter() reading at this process's start, not after `entered` (the command's
    own entry, a perf_counter() reading). Linux keeps the start in /proc/self/stat (field 22,
    clock ticks on the boot clock, which CLOCK_BOOTTIME reads here: no wall clock, so no NTP
    step or rounding of the boot time as psutil's create_time has); elsewhere, or where the
    record reads implausibly (older kernels counted it on another clock), `entered`."""
    try:
        with open("/proc/self/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()  # the name before ")" may hold spaces
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):  # not Linux: no file, no CLOCK_BOOTTIME
        return entered
    start = time.perf_counter() - age
    return start if entered - MAX_START_S <= start <= entered else entered
