"""Step 4 of the package doc, the uncertainty of the smoothed track: the diagonal (and first upper)
3 × 3 blocks of Σ = (JᵀJ)⁻¹ without forming Σ."""
from __future__ import annotations

import numpy as np

from localization.eval.reference.constants import NP


def _marginal_covariances(jac, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks of Σ = (JᵀJ)⁻¹: Σ_kk (K, 3, 3) of the poses, Σ_k,k+1 (K − 1, 3, 3) and the NP × NP block of
    the odometry unknowns. With H = JᵀJ = [[A, B], [Bᵀ, C]] (A block-tridiagonal: a factor touches
    at most two consecutive poses), S = C − Bᵀ A⁻¹ B and U = A⁻¹ B (a banded solve)::

        Σ_params = S⁻¹,   Σ_kl = (A⁻¹)_kl + U_k S⁻¹ U_lᵀ

    and the blocks of A⁻¹ by the block-tridiagonal recursion (``block_tridiagonal_inverse``)."""
    from scipy.linalg import solveh_banded
    from scipy.sparse import csr_matrix
    J = csr_matrix(jac)
    H = (J.T @ J).tocoo()
    n = 3 * K
    r, c, v = H.row, H.col, H.data
    pose = (r < n) & (c < n)
    rb, cb = r // 3, c // 3
    diag = np.zeros((K, 3, 3))
    up = np.zeros((max(K - 1, 0), 3, 3))
    d = pose & (rb == cb)
    np.add.at(diag, (rb[d], r[d] % 3, c[d] % 3), v[d])
    u = pose & (cb == rb + 1)
    np.add.at(up, (rb[u], r[u] % 3, c[u] % 3), v[u])
    diag += np.eye(3) * 1e-12
    Bm = np.zeros((n, NP))
    b = (r < n) & (c >= n)
    np.add.at(Bm, (r[b], c[b] - n), v[b])
    Cm = np.zeros((NP, NP))
    cc = (r >= n) & (c >= n)
    np.add.at(Cm, (r[cc] - n, c[cc] - n), v[cc])
    # A in upper banded form (bandwidth 5: a 3 × 3 block and its right neighbour)
    ab = np.zeros((6, n))
    dense_rows = np.arange(n)
    for off in range(6):
        i = dense_rows[:n - off]
        j = i + off
        same = (i // 3) == (j // 3)
        val = np.where(same, diag[i // 3, i % 3, j % 3], 0.0)
        nb = ~same & ((j // 3) == (i // 3) + 1)
        val = np.where(nb, up[np.minimum(i // 3, max(K - 2, 0)), i % 3, j % 3] if K > 1 else 0.0, val)
        ab[5 - off, off:] = val
    U = solveh_banded(ab, Bm)
    S = Cm - Bm.T @ U
    Sinv = np.linalg.inv(S)
    Ainv_diag, Ainv_next = block_tridiagonal_inverse(diag, up)
    Uk = U.reshape(K, 3, NP)
    cov = Ainv_diag + np.einsum("kia,ab,kjb->kij", Uk, Sinv, Uk)
    nxt = Ainv_next + np.einsum("kia,ab,kjb->kij", Uk[:-1], Sinv, Uk[1:])
    return cov, nxt, Sinv


def block_tridiagonal_inverse(diag, up) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal blocks (K, b, b) and first upper blocks (K − 1, b, b) of A⁻¹ for a symmetric positive
    definite block-tridiagonal A (diagonal blocks ``diag``, upper blocks ``up``: A_k,k+1)::

        D_0 = A_00,  D_k = A_kk − A_k,k−1 D_k−1⁻¹ A_k−1,k                      (forward)
        Σ_K−1 = D_K−1⁻¹,  Σ_k,k+1 = −D_k⁻¹ A_k,k+1 Σ_k+1,k+1,
        Σ_kk = D_k⁻¹ − Σ_k,k+1 A_k+1,k D_k⁻¹                                  (backward)

    One pass each way over the K blocks (3 × 3 matrices: a loop over scans, not beams)."""
    K = len(diag)
    Dinv = np.zeros_like(diag)
    D = diag[0]
    Dinv[0] = np.linalg.inv(D)
    for k in range(1, K):
        D = diag[k] - up[k - 1].T @ Dinv[k - 1] @ up[k - 1]
        Dinv[k] = np.linalg.inv(D)
    cov = np.zeros_like(diag)
    nxt = np.zeros_like(up)
    cov[K - 1] = Dinv[K - 1]
    for k in range(K - 2, -1, -1):
        nxt[k] = -Dinv[k] @ up[k] @ cov[k + 1]
        cov[k] = Dinv[k] - nxt[k] @ up[k].T @ Dinv[k]
    return 0.5 * (cov + np.transpose(cov, (0, 2, 1))), nxt
