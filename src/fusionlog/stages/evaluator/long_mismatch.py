"""The exact values of a long one-run log in blocks of time when the truth is not the filters'
model (issue 34; `core.exact_mismatch`): `LongReplayExact`'s blocks, bound check and spool,
FBS's backward pass spooling, per instant, the backward information filter's S and, under the
truth, B and cov(eta) of y_b = B x + eta (3 n^2 doubles, on disk: an unnamed temporary file,
`driver.long_log.Spool`), read back block by block by the forward pass."""

from __future__ import annotations

from fusionlog.core.exact_mismatch import MismatchBlocks

from .long_exact import LongReplayExact

__all__ = ["LongMismatchExact"]


class LongMismatchExact(LongReplayExact):
    """`LongReplayExact` of a `MismatchBlocks` (the truth not the model)."""

    exact: MismatchBlocks

    def prepare(self) -> None:
        """FBS's backward recursion over the whole log from its end, spooled (nothing without
        FBS)."""
        from fusionlog.driver.long_log import Spool, edges

        if not self.exact.smoother or self.spool is not None:
            return
        spool, after = Spool(self.exact.width), None
        try:
            for k0, k1 in reversed(edges(self.exact.steps + 1, self.block)):
                rows, after = self.exact.backward(k0, k1, self._present(k0, k1), after)
                spool.write(k0, rows)
        except BaseException:
            spool.close()
            raise
        self.spool = spool

    def _backward(self, k0: int, k1: int):
        return self.spool.read(k0, k1) if self.spool is not None else None
