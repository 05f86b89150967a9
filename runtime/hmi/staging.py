"""Who may write the curve staging area: one client at a time, for a limited time.

A client (one TCP connection) takes the staging area with its first staging write (header or
data) or with ``STAGING_CONTROL`` = TAKE while nobody holds it. Its hold lasts
``timeout_s`` after its last staging write, and ends earlier when it aborts
(``STAGING_CONTROL`` = ABORT), when its commit is accepted, or when its connection closes. While
the hold lasts, other clients' staging writes answer exception 2 and their commits from the
staging area are refused with STAGING_LOCKED; the holder's address and the time left are shown
in the status.

Threading: the server's event loop thread only. Time comes from the caller (monotonic seconds).
"""

from __future__ import annotations

import ipaddress
import logging
from dataclasses import dataclass

from runtime.hmi.registers import StagingState, StagingView

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Peer:
    """One client connection (compared by identity: a reconnect is another client)."""

    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


class StagingHold:
    """The staging area's holder.

    :param timeout_s: how long a hold lasts after the holder's last staging write.
    """

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._holder: Peer | None = None
        self._last_s = 0.0

    def holder(self, now_s: float) -> Peer | None:
        """The client holding the area now (a hold that timed out ends here)."""
        if self._holder is not None and now_s - self._last_s > self.timeout_s:
            log.info("modbus: staging hold of %s lapsed after %.1f s", self._holder, self.timeout_s)
            self._holder = None
        return self._holder

    def may_write(self, peer: Peer, now_s: float) -> bool:
        """Whether ``peer`` may write the staging area now."""
        holder = self.holder(now_s)
        return holder is None or holder is peer

    def touch(self, peer: Peer, now_s: float) -> None:
        """``peer`` wrote the staging area: take the hold or restart its timeout.

        :raises ValueError: if another client holds it (check :meth:`may_write` first).
        """
        if not self.may_write(peer, now_s):
            raise ValueError(f"staging area held by {self._holder}, not {peer}")
        if self._holder is None:
            log.info("modbus: %s holds the staging area", peer)
        self._holder = peer
        self._last_s = now_s

    def release(self, peer: Peer) -> bool:
        """End ``peer``'s hold (abort, accepted commit, closed connection); whether it held."""
        if self._holder is not peer:
            return False
        self._holder = None
        return True

    def view(self, now_s: float) -> StagingView:
        """The staging registers' view of the hold."""
        holder = self.holder(now_s)
        if holder is None:
            return StagingView()
        left_ms = max(0, round(1000.0 * (self.timeout_s - (now_s - self._last_s))))
        return StagingView(StagingState.HELD, _ipv4(holder.host), holder.port, left_ms)


def _ipv4(host: str) -> int:
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return 0
    if isinstance(address, ipaddress.IPv6Address):
        address = address.ipv4_mapped  # type: ignore[assignment]
    return int(address) if address is not None else 0
