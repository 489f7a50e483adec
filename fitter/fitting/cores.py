"""The cores this process may run on (:func:`usable_cores`): the one count by which the fit
sizes its threads and batches, and the collection its fits at once. stdlib only, so the
server imports it cheaply.

``os.cpu_count()`` counts the machine's CPUs, not those the process may use: in a container
limited by a cpuset, or under ``taskset``, a fit given 2 of 64 cores would split the
atlas detail's level 0 into 64 batches of one or two patches (``atlas.detail``) and start
64 threads for work 2 cores run. ``os.process_cpu_count()`` (Python 3.13) is this rule.
"""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The CPUs in this process's affinity mask (``os.sched_getaffinity``, Linux and some
    BSDs), else ``os.cpu_count()`` where it has none (macOS, Windows); at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # no affinity on this platform
        return max(1, os.cpu_count() or 1)
