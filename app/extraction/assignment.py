"""The optimal one-to-one assignment of a small cost matrix, as a compiled kernel.

Association (:mod:`app.extraction.linking`, step 5) needs it where two of a
snapshot's sources claim the same track; it runs inside the compiled
association loop, where ``scipy.optimize.linear_sum_assignment`` cannot be
called.  The method is scipy's: the shortest augmenting path of Crouse
(2016, "On implementing 2D rectangular assignment algorithms", IEEE TAES
52(4), pp. 1685-1686), the Jonker-Volgenant family.  Rows are added one at
a time; each finds, by a Dijkstra search on the reduced costs
``c[i, j] - u[i] - v[j]`` (never negative), the cheapest path to a free
column, and the dual prices ``u``, ``v`` are raised so that the reduced
costs of the matched pairs stay zero.  With at most as many rows as
columns every row is matched; a tall matrix is solved transposed.  Ties
are broken as scipy breaks them (columns scanned from the last, a free
column preferred at equal cost), so the two give the same pairs, which
tests/test_extraction_kernels.py checks on random and tied matrices.
"""

from __future__ import annotations

import numpy as np

from app.compiled import njit, warm_up_with


@njit
def min_cost_assignment(cost):
    """(rows, cols) of the assignment of least total ``cost`` (n_rows, n_cols), rows ascending.

    ``min(n_rows, n_cols)`` pairs, each row and column at most once, as
    ``scipy.optimize.linear_sum_assignment`` returns them.  Costs must be
    finite.  (Plain loops, no numpy calls: each numpy function in a kernel
    adds a second or more to the first run's compilation.)
    """
    transposed = cost.shape[1] < cost.shape[0]
    n_rows, n_cols = min(cost.shape), max(cost.shape)
    c = np.empty((n_rows, n_cols))
    for i in range(n_rows):
        for j in range(n_cols):
            c[i, j] = cost[j, i] if transposed else cost[i, j]
    u = np.zeros(n_rows)
    v = np.zeros(n_cols)
    path_cost = np.empty(n_cols)
    previous_row = np.empty(n_cols, dtype=np.int64)
    col_of_row = np.full(n_rows, -1)
    row_of_col = np.full(n_cols, -1)
    row_seen = np.zeros(n_rows, dtype=np.bool_)
    col_seen = np.zeros(n_cols, dtype=np.bool_)
    remaining = np.empty(n_cols, dtype=np.int64)
    for new_row in range(n_rows):
        # Dijkstra from new_row over the reduced costs, until a free column is reached
        for k in range(n_cols):
            remaining[k] = n_cols - 1 - k
            path_cost[k] = np.inf
            col_seen[k] = False
        for i in range(n_rows):
            row_seen[i] = False
        n_remaining = n_cols
        shortest = 0.0
        i = new_row
        sink = -1
        while sink == -1:
            row_seen[i] = True
            lowest = np.inf
            at = -1
            for k in range(n_remaining):
                j = remaining[k]
                r = shortest + c[i, j] - u[i] - v[j]
                if r < path_cost[j]:
                    previous_row[j] = i
                    path_cost[j] = r
                if path_cost[j] < lowest or (path_cost[j] == lowest and row_of_col[j] == -1):
                    lowest = path_cost[j]
                    at = k
            shortest = lowest
            j = remaining[at]
            if row_of_col[j] == -1:
                sink = j
            else:
                i = row_of_col[j]
            col_seen[j] = True
            n_remaining -= 1
            remaining[at] = remaining[n_remaining]
        # new prices keep the matched pairs' reduced costs at zero
        u[new_row] += shortest
        for i in range(n_rows):
            if row_seen[i] and i != new_row:
                u[i] += shortest - path_cost[col_of_row[i]]
        for j in range(n_cols):
            if col_seen[j]:
                v[j] -= shortest - path_cost[j]
        # flip the path's pairs
        j = sink
        while True:
            i = previous_row[j]
            row_of_col[j] = i
            col_of_row[i], j = j, col_of_row[i]
            if i == new_row:
                break
    rows = np.empty(n_rows, dtype=np.int64)
    cols = np.empty(n_rows, dtype=np.int64)
    if not transposed:
        for i in range(n_rows):
            rows[i], cols[i] = i, col_of_row[i]
        return rows, cols
    # the transposed problem's rows are the columns: list the pairs by the original rows
    k = 0
    for j in range(n_cols):
        if row_of_col[j] >= 0:
            rows[k], cols[k] = j, row_of_col[j]
            k += 1
    return rows, cols


@warm_up_with
def _warm_up_assignment() -> None:
    """Compile :func:`min_cost_assignment` for the float matrices association passes."""
    min_cost_assignment(np.array([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]]))
