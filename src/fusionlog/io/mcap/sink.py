"""The file object as the Rust MCAP writer sees it: nothing raised into Rust is lost.

The Foxglove SDK's writer calls the file object's ``write``/``seek``/``flush`` from Rust and
turns any Python exception they raise into a logged line — one per message from then on,
thousands on a full disk — and carries on. Two kinds of exception would be lost that way:

- **Write errors** (an OutputError from a CheckedFile, an OSError): :class:`Sink` keeps the
  first in ``error`` and drops later bytes (still tracking the position, as the Rust writer
  seeks back to patch chunk headers); the writer raises ``error`` after the message that met
  it, so the first failed write stops the stage with one line and the Rust side prints nothing.
- **Signals** (Ctrl-C, or SIGTERM/SIGHUP where a Python handler raises): CPython runs a signal's
  Python handler at the next bytecode of the main thread, which may be the first bytecode of
  ``Sink.write`` called from Rust, before any ``try`` — the KeyboardInterrupt would then go to
  Rust and vanish. While a writer is open, :class:`SignalGuard` puts a handler in front of
  each Python handler of SIGINT, SIGTERM and SIGHUP: outside the sink it calls the original
  at once, as if it were not there; inside a sink call it records the signal (``pending``)
  and the writer calls the original handler as soon as Rust has returned.

Rust calls ``write`` with ~8 kB buffers, not per message, so this layer costs nothing
measurable; the writer's per-message check is one attribute (``alert``).
"""

from __future__ import annotations

import signal
import threading
from types import FrameType
from typing import Any

from fusionlog.errors import OutputError

__all__ = ["SignalGuard", "Sink"]


class Sink:
    """Wraps ``file`` for the Rust writer; see the module docstring."""

    __slots__ = ("file", "name", "error", "pending", "alert", "pos", "end")

    def __init__(self, file: Any, name: str) -> None:
        self.file, self.name = file, name
        self.error: BaseException | None = None
        self.pending: list[tuple[Any, int]] = []  # (original handler, signal number)
        self.alert = False  # error or pending: the writer's one check per message
        try:
            self.pos = self.end = int(file.tell())
        except Exception:
            self.pos = self.end = 0

    def _fail(self, e: BaseException) -> None:
        if self.error is None:
            if isinstance(e, OSError):
                e = OutputError(f"{self.name}: cannot write: {e.strerror or e}")
            self.error = e
            self.alert = True

    def write(self, data: Any) -> int:
        n = len(data)
        if self.error is None:
            try:
                self.file.write(data)
            except BaseException as e:
                self._fail(e)
        self.pos += n
        if self.pos > self.end:
            self.end = self.pos
        return n

    def seek(self, offset: int, whence: int = 0) -> int:
        self.pos = (0, self.pos, self.end)[whence] + offset
        if self.error is None:
            try:
                self.file.seek(offset, whence)
            except BaseException as e:
                self._fail(e)
        return self.pos

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        if self.error is None:
            try:
                self.file.flush()
            except BaseException as e:
                self._fail(e)

    def deliver_signals(self) -> None:
        """Call the original handlers of the signals that came during a sink call (they
        usually raise: KeyboardInterrupt, or the CLI's SIGTERM exception)."""
        pending, self.pending = self.pending, []
        self.alert = self.error is not None
        for handler, signum in pending:
            handler(signum, None)


_SINK_CODES = frozenset(
    f.__code__ for f in (Sink.write, Sink.seek, Sink.tell, Sink.flush, Sink._fail)
)
_GUARDED = ("SIGINT", "SIGTERM", "SIGHUP")


def _sink_of(frame: FrameType | None) -> Sink | None:
    """The Sink whose method is running in ``frame`` or below it, if any."""
    while frame is not None:
        if frame.f_code in _SINK_CODES:
            sink = frame.f_locals.get("self")
            return sink if isinstance(sink, Sink) else None
        frame = frame.f_back
    return None


class SignalGuard:
    """Installed while at least one writer is open (main thread only); see the module
    docstring."""

    _lock = threading.Lock()
    _users = 0
    _saved: dict[int, Any] = {}

    @classmethod
    def acquire(cls) -> bool:
        if threading.current_thread() is not threading.main_thread():
            return False  # signals are handled in the main thread, never inside this one
        with cls._lock:
            if cls._users == 0:
                for name in _GUARDED:
                    sig = getattr(signal, name, None)
                    handler = signal.getsignal(sig) if sig is not None else None
                    if callable(handler):
                        cls._saved[sig] = handler
                        signal.signal(sig, cls._handle)
            cls._users += 1
        return True

    @classmethod
    def release(cls) -> None:
        with cls._lock:
            cls._users -= 1
            if cls._users == 0:
                for sig, handler in cls._saved.items():
                    if signal.getsignal(sig) == cls._handle:  # not replaced meanwhile
                        signal.signal(sig, handler)
                cls._saved = {}

    @classmethod
    def _handle(cls, signum: int, frame: FrameType | None) -> None:
        handler = cls._saved.get(signum, signal.default_int_handler)
        sink = _sink_of(frame)
        if sink is None:
            handler(signum, frame)
            return
        sink.pending.append((handler, signum))
        sink.alert = True
