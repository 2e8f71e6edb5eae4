"""The Poisson blend's normal equations assembled independently with scipy.sparse.

Shared by ``benches/bench_blend.py`` (scipy Jacobi-CG baseline) and the tests (an independent
check of m360's solution).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def scipy_system(
    values: np.ndarray, weights: np.ndarray, target: np.ndarray, lam: float = 0.1
) -> tuple[sp.csr_matrix, np.ndarray]:
    """The normal equations of Σ_a Σ_e ω̄_a(e)((B_q - B_p) - (D_a(q) - D_a(p)))² + λ‖B - T‖²,
    forward differences, wrap in longitude, no vertical edge past the last row; ω̄ is the mean
    of the weights at the edge's two ends."""
    k, h, w = values.shape
    n = h * w
    idx = np.arange(n).reshape(h, w)
    tails = [idx.ravel(), idx[:-1].ravel()]
    heads = [np.roll(idx, -1, axis=1).ravel(), idx[1:].ravel()]
    p = np.concatenate(tails)
    q = np.concatenate(heads)
    m = len(p)
    diff = sp.csr_matrix(
        (np.r_[-np.ones(m), np.ones(m)], (np.r_[np.arange(m), np.arange(m)], np.r_[p, q])),
        shape=(m, n),
    )
    edge_w = np.zeros(m)
    edge_g = np.zeros(m)
    for a in range(k):
        v = values[a].ravel().astype(np.float64)
        wt = weights[a].ravel().astype(np.float64)
        ok = np.isfinite(v[p]) & np.isfinite(v[q])
        wa = np.where(ok, 0.5 * (wt[p] + wt[q]), 0.0)
        edge_w += wa
        edge_g += np.where(ok, wa * (v[q] - v[p]), 0.0)
    a_mat = (diff.T @ sp.diags(edge_w) @ diff + lam * sp.identity(n)).tocsr()
    b = diff.T @ edge_g + lam * target.ravel().astype(np.float64)
    return a_mat, b
