"""The alignment energy assembled with scipy.sparse from m360's exported problem terms.

Shared by ``benches/bench_align.py`` (scipy L-BFGS-B baseline) and the tests (an independent
evaluation of the energy). Unknowns are node-interleaved: x[2·node] = s, x[2·node + 1] = o.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.sparse as sp


def energy_function(problem: dict[str, Any]) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """f(x) -> (energy, gradient) of the problem, with sparse matrices: J (samples × unknowns)
    for the data term and D (2·edges × unknowns) for the smoothness."""
    nodes = problem["nodes"].astype(np.int64)
    k = len(nodes)
    n = int(problem["unknowns"])
    cols = np.stack([2 * nodes, 2 * nodes + 1], axis=-1).reshape(k, 16)
    vals = np.stack([problem["coef_s"], problem["coef_o"]], axis=-1).reshape(k, 16)
    jac = sp.csr_matrix((vals.ravel(), (np.repeat(np.arange(k), 16), cols.ravel())), shape=(k, n))
    p, q, w = problem["edges"].T
    p, q = p.astype(np.int64), q.astype(np.int64)
    e = len(p)
    root = np.sqrt(w)
    d_rows = np.repeat(np.arange(2 * e), 2)
    d_cols = np.stack([2 * p, 2 * q, 2 * p + 1, 2 * q + 1], axis=1).reshape(e, 2, 2).reshape(-1)
    d_vals = np.stack([root, -root, root, -root], axis=1).reshape(-1)
    diff = sp.csr_matrix((d_vals, (d_rows, d_cols)), shape=(2 * e, n))
    c, eps = float(problem["scale_weight"]), float(problem["gauge_weight"])

    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        r = jac @ x
        d = diff @ x
        s, o = x[0::2], x[1::2]
        energy = float(r @ r / k + d @ d + c * np.sum(1.0 / s) + eps * np.sum(o * o))
        grad = 2.0 * (jac.T @ r) / k + 2.0 * (diff.T @ d)
        grad[0::2] -= c / (s * s)
        grad[1::2] += 2.0 * eps * o
        return energy, grad

    return f


def identity(problem: dict[str, Any]) -> np.ndarray:
    x = np.zeros(int(problem["unknowns"]))
    x[0::2] = 1.0
    return x
