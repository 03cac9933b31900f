"""Leases that follow the client. The server destroys an environment that no call has touched
for its --idle_timeout_s (Env.idle_timeout_s). While an environment object of this package
lives, one daemon thread per process renews its environments' leases with the server's
KeepAlive call, one call per connection every third of the idle timeout carrying all of that
connection's names, so a trainer may pause (evaluation, checkpointing, a debugger) for any
time. When the process dies the renewals stop and the server reclaims the environments after
the idle timeout, as before. A connection is dropped from the renewals once it is closed or
garbage collected; names the server no longer knows are dropped too."""

from __future__ import annotations

import os
import threading
import time
import weakref

from ._errors import MLLError
from ._stubs import pb

# Renewals per idle timeout: a lease is renewed twice more before it could expire.
RENEWALS_PER_TIMEOUT = 3
# Never renew more often than this (a server with a tiny idle timeout must not make us spin).
MIN_PERIOD_S = 0.05
# KeepAlive takes at most this many names per call.
MAX_NAMES_PER_CALL = 10000


class _Lease:
    """The names one connection keeps alive and when they are next due."""

    __slots__ = ("names", "period_s", "due")

    def __init__(self, period_s: float):
        self.names: dict[str, None] = {}  # Ordered set.
        self.period_s = period_s
        self.due = time.monotonic() + period_s


class _Keeper:
    """The process's renewal thread, started with the first lease."""

    def __init__(self):
        self._wake = threading.Condition()
        self._leases: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()  # Connection -> _Lease.
        self._thread: threading.Thread | None = None

    def hold(self, connection, name: str, idle_timeout_s: float) -> None:
        if not idle_timeout_s > 0:  # A server that predates KeepAlive reports no timeout.
            return
        period_s = max(idle_timeout_s / RENEWALS_PER_TIMEOUT, MIN_PERIOD_S)
        with self._wake:
            lease = self._leases.get(connection)
            if lease is None:
                lease = self._leases[connection] = _Lease(period_s)
            lease.period_s = min(lease.period_s, period_s)
            lease.due = min(lease.due, time.monotonic() + lease.period_s)
            lease.names[name] = None
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="mll-keepalive", daemon=True)
                self._thread.start()
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                now = time.monotonic()
                due, next_due = [], None
                for connection, lease in list(self._leases.items()):
                    if connection.closed:
                        del self._leases[connection]
                    elif lease.due <= now:
                        lease.due = now + lease.period_s
                        due.append((connection, list(lease.names)))
                    else:
                        next_due = lease.due if next_due is None else min(next_due, lease.due)
                if not due:
                    self._wake.wait(None if next_due is None else next_due - now)
                    continue
            for connection, names in due:  # Outside the lock: calls take a round trip.
                self._renew(connection, names)
            del due

    def _renew(self, connection, names: list[str]) -> None:
        gone: list[str] = []
        for start in range(0, len(names), MAX_NAMES_PER_CALL):
            request = pb.KeepAliveRequest(names=names[start : start + MAX_NAMES_PER_CALL])
            try:
                gone += connection.call("KeepAlive", request, timeout=10.0).not_found
            except (MLLError, ValueError):  # Unreachable for now (retried next period), or closed meanwhile.
                return
        if gone:
            with self._wake:
                lease = self._leases.get(connection)
                for name in gone:
                    if lease is not None:
                        lease.names.pop(name, None)


_KEEPER = _Keeper()


def hold(connection, name: str, idle_timeout_s: float) -> None:
    """Keeps the environment `name` on `connection`'s server alive for as long as `connection`
    is open (idle_timeout_s: the server's, from Env.idle_timeout_s; 0 does nothing)."""
    _KEEPER.hold(connection, name, idle_timeout_s)


def _forget_leases_after_fork() -> None:
    """A forked child renews none of its parent's leases (their connections are the parent's),
    and must not wait on a lock the parent's renewal thread may have held at the fork."""
    global _KEEPER
    _KEEPER = _Keeper()


os.register_at_fork(after_in_child=_forget_leases_after_fork)
