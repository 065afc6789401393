"""``parksim.recon.heap.keep_freed_memory``: a block freed and allocated again reuses mapped pages (no page faults)."""

from __future__ import annotations

import subprocess
import sys

import pytest

CYCLE = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from parksim.recon.heap import keep_freed_memory
    assert keep_freed_memory()
np.ones(1 << 23)   # 64 MB: over glibc's largest mmap threshold
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    np.ones(1 << 23)   # allocated, every page written, freed
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
HUGE_PAGES = (1 << 26) // (2 << 20)
"""2 MB pages in a block: the fewest faults a fresh mapping of it can take (numpy asks for huge pages)."""


def _faults(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", CYCLE, mode], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return int(done.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_blocks_are_reused_without_page_faults() -> None:
    # by default each 64 MB block is a fresh mmap: at least a fault per page, five times
    assert _faults("default") >= 5 * HUGE_PAGES
    # kept in the heap, the same pages come back already mapped
    assert _faults("keep") < HUGE_PAGES
