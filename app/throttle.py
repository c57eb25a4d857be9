"""Failed token checks per client address: checks spaced out, the right token never refused.

Every check of a presented API token (``POST /api/v1/session`` and ``Authorization: Bearer``)
goes through :class:`TokenThrottle`. An address may send ``free_failures`` wrong tokens within
``window_s`` without delay; after that its checks are spaced out, one at a time (concurrent
requests queue for their turn): 0.5 s apart, doubling with every further failure up to
``max_delay_s``. A wrong token beyond the free ones is answered 429 with ``Retry-After``.

The right token is always accepted, but a throttled address waits for its turn like any other
check: answering the right token at once would tell a guesser at full speed which guess was
right, whatever the wrong ones got. An address that sent the right token starts afresh. Other
addresses are never slowed (IPv6 clients are counted per /64, the block one host usually has).

The counts live in the web process's memory (they restart with it). Behind a reverse proxy, run
uvicorn with ``--proxy-headers --forwarded-allow-ips=<proxy>`` so that clients keep their own
address.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Literal, overload

#: Spacing after the first failure beyond the free ones, s (doubles with each further one).
FIRST_DELAY_S = 0.5
#: Most addresses remembered; beyond it those whose failures expired are forgotten, then the oldest.
MAX_CLIENTS = 10_000


def client_key(host: str | None) -> str:
    """The throttled unit of a peer address: the address itself, an IPv6 one's /64 block."""
    if not host:
        return "unknown"
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return str(address.ipv4_mapped)
        return str(ipaddress.ip_network(f"{address}/64", strict=False))
    return str(address)


@dataclass
class _Client:
    failures: deque[float] = field(default_factory=deque)
    #: Monotonic time before which this address's next check waits.
    next_check: float = 0.0


class TokenThrottle:
    """Failed token checks per client address (see the module's docstring).

    Parameters
    ----------
    free_failures : int, >= 1, wrong tokens an address may send within ``window_s`` unslowed.
    window_s : float, > 0, failures older than this are forgotten, s.
    max_delay_s : float, >= 0, longest spacing between two checks of one address, s.
    clock : callable returning monotonic seconds.
    sleep : coroutine function waiting that many seconds (``asyncio.sleep``; tests may step ``clock``).
    """

    def __init__(
        self,
        *,
        free_failures: int,
        window_s: float,
        max_delay_s: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ):
        if free_failures < 1:
            raise ValueError(f"free_failures: expected >= 1, got {free_failures}")
        if not window_s > 0:
            raise ValueError(f"window_s: expected > 0, got {window_s}")
        if not max_delay_s >= 0:
            raise ValueError(f"max_delay_s: expected >= 0, got {max_delay_s}")
        self.free_failures = free_failures
        self.window_s = window_s
        self.max_delay_s = max_delay_s
        self._clock = clock
        self._sleep = sleep
        self._lock = threading.Lock()
        self._clients: dict[str, _Client] = {}

    def failures(self, client: str) -> int:
        """Failed checks of ``client`` within the window."""
        with self._lock:
            state = self._state(client, self._clock(), create=False)
            return 0 if state is None else len(state.failures)

    async def wait_turn(self, client: str) -> float:
        """Wait until ``client`` may have its next token checked (at once unless it is throttled).

        Returns
        -------
        float
            The seconds waited.
        """
        with self._lock:
            now = self._clock()
            state = self._state(client, now, create=False)
            if state is None:
                return 0.0
            spacing = self._spacing(len(state.failures))
            if spacing == 0.0:
                return 0.0
            turn = max(now, state.next_check)
            state.next_check = turn + spacing
        if turn > now:
            await self._sleep(turn - now)
        return turn - now

    def failed(self, client: str) -> float | None:
        """Count a wrong token; the seconds until the next check if ``client`` is now throttled, else None."""
        with self._lock:
            now = self._clock()
            state = self._state(client, now, create=True)
            state.failures.append(now)
            state.next_check = max(state.next_check, now + self._spacing(len(state.failures)))
            if len(state.failures) <= self.free_failures:
                return None
            return max(state.next_check - now, 0.0)

    def succeeded(self, client: str) -> None:
        """The right token: ``client`` starts afresh."""
        with self._lock:
            self._clients.pop(client, None)

    @staticmethod
    def retry_after(seconds: float) -> str:
        """A ``Retry-After`` value: whole seconds, at least 1."""
        return str(max(1, math.ceil(seconds)))

    def _spacing(self, failures: int) -> float:
        beyond = failures - self.free_failures
        if beyond < 0:
            return 0.0
        return min(FIRST_DELAY_S * 2.0 ** min(beyond, 32), self.max_delay_s)

    @overload
    def _state(self, client: str, now: float, *, create: Literal[True]) -> _Client: ...

    @overload
    def _state(self, client: str, now: float, *, create: Literal[False]) -> _Client | None: ...

    def _state(self, client: str, now: float, *, create: bool) -> _Client | None:
        """The address's state with expired failures dropped (caller holds the lock)."""
        state = self._clients.get(client)
        if state is not None:
            while state.failures and state.failures[0] <= now - self.window_s:
                state.failures.popleft()
            if not state.failures and state.next_check <= now:
                del self._clients[client]
                state = None
        if state is None and create:
            self._forget_some(now)
            state = self._clients[client] = _Client()
        return state

    def _forget_some(self, now: float) -> None:
        """Keep at most :data:`MAX_CLIENTS` addresses: expired ones go first, then the oldest."""
        if len(self._clients) < MAX_CLIENTS:
            return
        for key in [
            k
            for k, s in self._clients.items()
            if not s.failures or s.failures[-1] <= now - self.window_s
        ]:
            del self._clients[key]
        while len(self._clients) >= MAX_CLIENTS:
            del self._clients[next(iter(self._clients))]
