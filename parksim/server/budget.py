"""Reply byte budget: a render reply is counted from before it is rendered until its body has been sent.

A request's reply size is known before rendering (``LocalSim.reply_bytes``): over ``max_reply_bytes`` it is
refused at once (``ReplyTooLarge``, 413); otherwise its bytes are reserved here, and while the replies in flight
(queued, rendering, encoded or still being sent to a client that reads slowly or not at all) would exceed the
budget, a new request gets ``BudgetFull`` (503, Retry-After). So clients that never read hold at most the budget.
"""

from __future__ import annotations

import threading

__all__ = ["ReplyBudget", "Reservation", "BudgetFull", "ReplyTooLarge"]


class ReplyTooLarge(ValueError):
    """One request asks for a reply larger than the per-request limit; the message names both sizes."""


class BudgetFull(RuntimeError):
    """The replies in flight use up the budget: retry after ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class Reservation:
    """``nbytes`` taken from a budget; ``release`` gives them back once (later calls do nothing)."""

    def __init__(self, budget: ReplyBudget, nbytes: int) -> None:
        self.budget, self.nbytes = budget, nbytes
        self._released = False

    def release(self) -> None:
        with self.budget._lock:
            if not self._released:
                self._released = True
                self.budget.in_flight -= self.nbytes


class ReplyBudget:
    """At most ``limit_bytes`` of replies reserved at once (thread-safe)."""

    def __init__(self, limit_bytes: int, retry_after_s: int) -> None:
        self.limit_bytes, self.retry_after_s = limit_bytes, retry_after_s
        self._lock = threading.Lock()
        self.in_flight = 0
        self.rejected = 0

    def stats(self) -> dict[str, int]:
        return {"budget_bytes": self.limit_bytes, "in_flight_bytes": self.in_flight, "rejected": self.rejected}

    def reserve(self, nbytes: int) -> Reservation:
        """Take ``nbytes`` of the budget, or raise ``BudgetFull`` when they do not fit beside the replies in flight."""
        with self._lock:
            if self.in_flight + nbytes > self.limit_bytes:
                self.rejected += 1
                raise BudgetFull(f"reply budget full: {self.in_flight} of {self.limit_bytes} bytes are held by replies "
                                 f"being rendered or sent, and this one needs {nbytes}; retry after "
                                 f"{self.retry_after_s} s", self.retry_after_s)
            self.in_flight += nbytes
        return Reservation(self, nbytes)
