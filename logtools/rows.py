"""Row-by-row arithmetic over long series, a block of rows at a time.

Every row of such an expression is computed on its own (elementwise ufuncs, per-row products and norms),
so the blocks give the same numbers as one whole-array expression, with temporaries bounded by the block:
4 h at 200 Hz is 2.9 M rows, and every (n, 3) temporary of a whole-array expression is 69 MB of it."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: rows computed at a time by every block-wise loop of row-by-row arithmetic (6 MB per (rows, 3) float
#: temporary); the numbers do not depend on it
BLOCK_ROWS = 1 << 18


def by_rows(fn: Callable[..., np.ndarray | tuple[np.ndarray, ...]], *arrays: np.ndarray,
            rows: int = BLOCK_ROWS) -> np.ndarray | tuple[np.ndarray, ...]:
    """``fn(*arrays)`` for ``fn`` computing each row of its output(s) from the same row of its inputs (all
    of one length), BLOCK_ROWS rows at a time. One output array or a tuple of them, as ``fn`` returns."""
    n = len(arrays[0])
    if n <= rows:
        return fn(*arrays)
    outs: list[np.ndarray] | None = None
    single = False
    for a in range(0, n, rows):
        r = fn(*(x[a:a + rows] for x in arrays))
        if outs is None:
            single = not isinstance(r, tuple)
            outs = [np.empty((n,) + np.shape(x)[1:], np.asarray(x).dtype) for x in ((r,) if single else r)]
        for o, x in zip(outs, (r,) if single else r):
            o[a:a + len(x)] = x
    return outs[0] if single else tuple(outs)
