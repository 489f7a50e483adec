"""The cores this process may run on (``fitter.fitting.cores.usable_cores``): its affinity
mask, not the machine's CPU count; where it has none, the CPU count."""

from __future__ import annotations

import os

from fitter.fitting import cores
from fitter.fitting.atlas import threads


def test_the_affinity_mask_not_the_machines_cpus(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3, 17}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)  # the machine's: not what counts
    assert cores.usable_cores() == 2


def test_without_an_affinity_the_cpu_count_at_least_one(monkeypatch):
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)  # macOS, Windows
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert cores.usable_cores() == 6
    monkeypatch.setattr(os, "cpu_count", lambda: None)  # undeterminable
    assert cores.usable_cores() == 1


def test_on_threads_starts_one_thread_per_usable_core(monkeypatch):
    """``atlas.threads.on_threads`` sizes its pool by the usable cores (1 of a machine's 64:
    one thread), and the chunks come back in order either way."""
    started = []

    class Recording(threads.ThreadPoolExecutor):
        def __init__(self, workers):
            started.append(workers)
            super().__init__(workers)

    monkeypatch.setattr(threads, "ThreadPoolExecutor", Recording)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    for mask, expected in (({0}, 1), ({0, 1, 2}, 3)):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, mask=mask: mask,
                            raising=False)
        assert threads.on_threads(lambda lo: lo, 80, 10) == list(range(0, 80, 10))
        assert started[-1] == expected
