"""Say once on stderr when numba starts compiling a kernel, so a first run's silent ~30 s has a reason.

Numba fires its ``numba:compile`` event only on a real compile, after its disk cache had no entry for the
kernel (first run after an install or a kernel change, see ``parksim.kernel_cache``): a cached run says nothing.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from numba.core import event
from tqdm import tqdm

__all__ = ["compile_notice", "NOTICE"]

NOTICE = "compiling render kernels (first run after install or a kernel change, ~30 s)..."


def _to_stderr(message: str) -> None:
    """Write a line to stderr without breaking a tqdm bar there."""
    tqdm.write(message, file=sys.stderr)


class _FirstCompile(event.Listener):
    """Calls ``say(NOTICE)`` at the start of the first compile it hears of (numba compiles under one lock)."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say, self.said = say, False

    def on_start(self, e: event.Event) -> None:
        """A compile starts."""
        if not self.said:
            self.said = True
            self.say(NOTICE)

    def on_end(self, e: event.Event) -> None:
        """A compile ended: nothing more to say."""


@contextmanager
def compile_notice(say: Callable[[str], None] = _to_stderr) -> Iterator[None]:
    """Within the block, the first numba compile (a cache miss) is announced once through ``say``."""
    with event.install_listener("numba:compile", _FirstCompile(say)):
        yield
