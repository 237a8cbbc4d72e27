"""Checks of a Dask cluster the executor relies on (:mod:`.distributed`): the address of a
running scheduler, that what answers there is a Dask scheduler, and that a cluster still has
workers while tasks wait on it.

Every failure is one line (a FusionlogError) within a bounded time:

* ``--scheduler`` takes ``tcp://HOST:PORT`` or ``tls://HOST:PORT``; an address without a scheme
  is refused with the one it probably means, other schemes (``ucx://``, ``inproc://``, ``ws://``)
  are refused;
* before a Client is made, one connection asks the service for its identity, within the
  timeout: a closed port, a socket that accepts and stays silent, an HTTP server or a Dask
  worker are each reported in one line (a Client that fails to connect would later print
  Dask's ``Client.__del__`` traceback after our line);
* while results are awaited, the scheduler is asked for its workers once a second: none for
  `timeout` seconds ends the wait (all workers killed: never a silent hang), and a scheduler
  that stops answering ends it too.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from fusionlog.errors import FusionlogError

__all__ = ["SCHEMES", "WorkerWatch", "check_address", "probe_scheduler"]

#: The transports a --scheduler address may use.
SCHEMES = ("tcp", "tls")


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def check_address(address: str) -> str:
    """The address if its scheme is tcp:// or tls://, else a one-line FusionlogError."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        raise FusionlogError(
            f"--scheduler {address}: give the scheme, e.g. tcp://{address} (tcp:// or tls://)"
        )
    if scheme not in SCHEMES:
        raise FusionlogError(
            f"--scheduler {address}: scheme {scheme}:// is not supported (tcp:// or tls://)"
        )
    if not rest or rest.startswith(":") or rest.endswith(":"):
        raise FusionlogError(f"--scheduler {address}: expected {scheme}://HOST:PORT")
    return address


async def _identity(address: str, timeout: float) -> Any:
    from distributed.comm import connect
    from distributed.security import Security

    args = Security().get_connection_args("client")
    comm = await connect(address, timeout=timeout, **args)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def _refused(address: str, timeout: float) -> bool:
    """Whether the host refuses a TCP connection to the port (nothing listens there): an answer
    that needs no waiting, where Dask's connect would retry it for the whole timeout."""
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        host, port = parse_host_port(parse_address(address)[1])
        socket.create_connection((host, port), timeout=min(timeout, 2.0)).close()
    except ConnectionRefusedError:
        return True
    except (OSError, ValueError):  # unreachable, silent, unparsable: Dask's connect says
        pass
    return False


def probe_scheduler(address: str, timeout: float) -> None:
    """A Dask scheduler answers at `address` within `timeout` seconds, else one line (at once
    when the connection is refused)."""
    if _refused(address, timeout):
        raise FusionlogError(
            f"--scheduler {address}: cannot connect to a Dask scheduler (connection refused: "
            "nothing listens on that port)"
        )
    try:
        # Dask's connect gives up at `timeout` with its reason; this bound is for the rest
        ident = asyncio.run(asyncio.wait_for(_identity(address, timeout), timeout + 2))
    except TimeoutError:
        raise FusionlogError(
            f"--scheduler {address}: nothing answered as a Dask scheduler within {timeout:g} s "
            "(a silent or another service there? --scheduler-timeout SECONDS)"
        ) from None
    except Exception as e:  # refused, reset, a service that speaks another protocol
        raise FusionlogError(
            f"--scheduler {address}: cannot connect to a Dask scheduler ({_reason(e)})"
        ) from None
    kind = ident.get("type") if isinstance(ident, dict) else None
    if kind != "Scheduler":
        what = f"a Dask {kind}" if isinstance(kind, str) else "not a Dask scheduler"
        raise FusionlogError(f"--scheduler {address}: {what} answers there, not a scheduler")


class WorkerWatch:
    """Asked by a waiting loop (`check`, as often as it likes): at most once a second asks the
    scheduler for its workers; none for `timeout` seconds, or no answer, is one line."""

    def __init__(self, client: Any, where: str, timeout: float) -> None:
        self._client, self.where, self._timeout = client, where, timeout
        self._asked = self._seen = time.monotonic()

    def check(self) -> None:
        now = time.monotonic()
        if now - self._asked < 1.0:
            return
        self._asked = now
        try:
            workers = self._client.scheduler_info(n_workers=-1)["workers"]
        except Exception as e:
            raise FusionlogError(
                f"{self.where}: lost the connection to the Dask scheduler ({_reason(e)}); "
                "nothing was written"
            ) from None
        if workers:
            self._seen = now
        elif now - self._seen >= self._timeout:
            raise FusionlogError(
                f"{self.where}: no Dask worker for {self._timeout:g} s (all workers gone?); "
                "nothing was written"
            )
