"""Solver pieces of the bundle adjustment: Levenberg-Marquardt with exact Schur-complement steps (points
eliminated block by block) and the statistics at a solution (reduced normal matrix, camera covariances, noise
variances of features and clicks)."""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import threading
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

_BLAS_LOCK = threading.Lock()


def _openblas() -> ctypes.CDLL | None:
    libs = glob.glob(os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs", "*openblas*"))
    for lib in libs:
        try:
            dll = ctypes.CDLL(lib)
        except OSError:
            continue
        if hasattr(dll, "scipy_openblas_set_num_threads64_") and hasattr(dll, "scipy_openblas_get_num_threads64_"):
            return dll
    return None


_OPENBLAS = _openblas()


@contextlib.contextmanager
def single_thread_blas() -> Iterator[None]:
    """Run numpy's OpenBLAS on one thread inside the block (best effort; no-op when not found).

    The sparse solver (LSMR) calls BLAS on vectors of ~1e4-1e5 entries thousands of times; OpenBLAS threads them
    and on a busy 2-core machine each call then costs milliseconds instead of microseconds.
    """
    if _OPENBLAS is None:
        yield
        return
    with _BLAS_LOCK:
        before = int(_OPENBLAS.scipy_openblas_get_num_threads64_())
        _OPENBLAS.scipy_openblas_set_num_threads64_(1)
        try:
            yield
        finally:
            _OPENBLAS.scipy_openblas_set_num_threads64_(before)


def skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def point_blocks(Jp: sp.csr_matrix, starts: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Diagonal blocks (P, 3, 3) of Jp^T Jp for point columns in blocks at ``starts`` of size 1 or 3 (every row of
    Jp touches one block; size-1 blocks padded with an identity)."""
    P = len(starts)
    coo = Jp.tocoo()
    blk = np.searchsorted(starts, coo.col, side="right") - 1
    off = coo.col - starts[blk]
    R3 = np.zeros((Jp.shape[0], 3))
    row_blk = np.zeros(Jp.shape[0], dtype=np.int64)
    R3[coo.row, off] = coo.data
    row_blk[coo.row] = blk
    used = np.zeros(Jp.shape[0], bool)
    used[coo.row] = True
    B = np.zeros((P, 3, 3))
    np.add.at(B, row_blk[used], np.einsum("ri,rj->rij", R3[used], R3[used]))
    one = sizes == 1
    B[one, 1, 1] = B[one, 2, 2] = 1.0
    return B


def reduced_system(J: sp.spmatrix, w: np.ndarray, n_cam: int, starts: np.ndarray, sizes: np.ndarray):
    """Pieces of the normal matrix J^T diag(w) J with the point blocks eliminated: the weighted Jacobian's camera
    and point columns (sqrt(w) J), A_cp, the inverse point blocks V^-1 (sparse) and the reduced (Schur-complement)
    matrix (n_cam, n_cam) of the first ``n_cam`` unknowns."""
    sw = np.sqrt(w)
    Jw = (sp.diags(sw) @ J).tocsc()
    Jc, Jp = Jw[:, :n_cam].tocsr(), Jw[:, n_cam:].tocsr()
    A_cc = (Jc.T @ Jc).toarray()
    if Jp.shape[1] == 0:
        return Jc, Jp, None, None, A_cc
    A_cp = (Jc.T @ Jp).tocsr()
    V = point_blocks(Jp, starts, sizes)
    P = len(starts)
    valid = np.ones((P, 3), bool)
    valid[sizes == 1, 1:] = False
    vmask = valid[:, :, None] & valid[:, None, :]
    cols3 = starts[:, None] + np.arange(3)[None, :]
    idx_r = np.repeat(cols3, 3, axis=1).reshape(P, 3, 3)
    idx_c = np.tile(cols3, (1, 3)).reshape(P, 3, 3)
    V[:, np.arange(3), np.arange(3)] += 1e-12
    Vinv = np.linalg.inv(V)
    Vi = sp.csr_matrix((Vinv[vmask], (idx_r[vmask], idx_c[vmask])), shape=(Jp.shape[1],) * 2)
    return Jc, Jp, A_cp, Vi, A_cc - ((A_cp @ Vi) @ A_cp.T).toarray()


def camera_covariance(system: tuple, w: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(n_cam, n_cam) covariance of the camera unknowns of the estimate that minimises sum w r^2 (IRLS weights
    ``w`` (M,); ``system`` = :func:`reduced_system` for those weights) when the residuals have variances ``var``
    (M,): the sandwich S^-1 K diag(w var) K^T S^-1 with S the reduced normal matrix and K^T = J_c - J_p V^-1 A_cp^T
    (weighted columns). Equal to S^-1 when w * var = 1 (weights that are the inverse noise variances); larger
    otherwise (e.g. 1 px clicks weighted like 0.5 px features)."""
    Jc, Jp, A_cp, Vi, S = system
    Kt = Jc if A_cp is None else (Jc - Jp @ (Vi @ A_cp.T)).tocsr()  # sparse: a row touches its point's cameras
    middle = (Kt.T @ sp.diags(w * var) @ Kt).toarray()
    S_inv = np.linalg.pinv(S)
    return S_inv @ middle @ S_inv


def noise_variances(
    r: np.ndarray, w: np.ndarray, n_obs: int, n_clk: int, n_params: int, click_weight: np.ndarray | float
) -> tuple[float, float]:
    """Noise variances (px^2) of the feature observations and of the clicks from the final residuals ``r`` and
    their robust-loss weights ``w`` (the feature rows first, 2 per observation, then 2 per click, scaled by
    ``click_weight``).

    Features: weighted squared residuals over their count less the parameters (a median-based estimate was
    tried: on the real sets it is smaller and the predicted deviations overconfident, temple error / sigma RMS
    1.77 against 1.50). Clicks: squared residuals over their count less 7 (the similarity of the model frame
    they fix; at least half the count), never below the features' variance (a click is not sharper than a
    detected corner). One variance for both would overstate what a dozen clicks say about the frame: on
    fountain-P11 the features' is 0.34 px^2 for clicks simulated with 1 px noise."""
    m_obs, m_clk = 2 * n_obs, 2 * n_clk
    s2_obs = float(np.sum(w[:m_obs] * r[:m_obs] ** 2)) / max(m_obs - n_params, 1)
    if not m_clk:
        return s2_obs, s2_obs
    cw = np.asarray(click_weight, np.float64)
    r_clk = r[m_obs : m_obs + m_clk] / np.where(cw > 0, cw, 1.0)
    s2_clk = float(np.sum(r_clk**2)) / max(m_clk - 7, m_clk / 2)
    return s2_obs, max(s2_clk, s2_obs)


def centre_jacobian(rvec: np.ndarray, R0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3, 6) derivative of the camera centre -R^T t, R = rodrigues(rvec) @ R0, with respect to (rvec, t)
    (central differences on the rotation, exact on t)."""
    J = np.zeros((3, 6))
    h = 1e-7
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        Rp, Rm = rodrigues_batch(np.stack([rvec + e, rvec - e])) @ R0
        J[:, k] = (-(Rp.T @ t) + Rm.T @ t) / (2 * h)
    J[:, 3:] = -(rodrigues_batch(rvec)[0] @ R0).T
    return J


def schur_lm(residuals, jacobian, x0, n_cam, starts, sizes, loss, f_scale, max_nfev, ftol):
    """Levenberg-Marquardt on sum rho(r^2 / s^2) (soft_l1 or linear) by iteratively reweighted Gauss-Newton steps;
    each step solves the damped normal equations by the Schur complement on the first ``n_cam`` unknowns (the
    rest: per-point blocks at ``starts`` / ``sizes``, columns relative to ``n_cam``). Returns (x, evaluations)."""

    def cost_weights(r):
        if loss == "linear":
            return 0.5 * float(r @ r), np.ones_like(r)
        z = (r / f_scale) ** 2
        return float(f_scale**2 * np.sum(np.sqrt(1 + z) - 1)), 1 / np.sqrt(1 + z)

    x = x0.copy()
    r = residuals(x)
    cost, w = cost_weights(r)
    nfev, lam = 1, 1e-6  # Marquardt damping relative to diag(J^T W J): starts near Gauss-Newton
    P = len(starts)
    cols3 = starts[:, None] + np.arange(3)[None, :]
    valid = np.ones((P, 3), bool)
    valid[sizes == 1, 1:] = False
    idx_r = np.repeat(cols3, 3, axis=1).reshape(P, 3, 3)
    idx_c = np.tile(cols3, (1, 3)).reshape(P, 3, 3)
    vmask = valid[:, :, None] & valid[:, None, :]
    while nfev < max_nfev:
        J = jacobian(x).tocsr()
        sw = np.sqrt(w)
        Jw = (sp.diags(sw) @ J).tocsc()
        Jc, Jp = Jw[:, :n_cam].tocsr(), Jw[:, n_cam:].tocsr()
        g = Jw.T @ (sw * r)
        A_cc = (Jc.T @ Jc).toarray()
        A_cp = (Jc.T @ Jp).tocsr()
        V = point_blocks(Jp, starts, sizes)
        n_pcols = Jp.shape[1]
        g_c, g_p = g[:n_cam], g[n_cam:]
        diag_c = np.maximum(np.diag(A_cc), 1e-12)
        diag_p = np.maximum(np.einsum("pii->pi", V), 1e-12)
        improved = False
        while nfev < max_nfev:
            Vd = V.copy()
            Vd[:, np.arange(3), np.arange(3)] += lam * diag_p
            Vinv = np.linalg.inv(Vd)
            Vinv[~vmask] = 0.0
            Vi = sp.csr_matrix((Vinv[vmask], (idx_r[vmask], idx_c[vmask])), shape=(n_pcols, n_pcols))
            WVi = A_cp @ Vi
            S = A_cc + np.diag(lam * diag_c) - (WVi @ A_cp.T).toarray()
            rhs = -(g_c - WVi @ g_p)
            try:
                dc = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dp = Vi @ (-g_p - A_cp.T @ dc)
            x_new = x + np.r_[dc, dp]
            r_new = residuals(x_new)
            nfev += 1
            cost_new, w_new = cost_weights(r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                rel = (cost - cost_new) / max(cost, 1e-300)
                x, r, cost, w = x_new, r_new, cost_new, w_new
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or rel < ftol:
            break
    return x, nfev


def rodrigues_batch(rvecs: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of (N, 3) axis-angle vectors (radians)."""
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-12
    k = r / np.where(small, 1.0, theta)[:, None]
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.sin(theta)[:, None, None]
    c = (1 - np.cos(theta))[:, None, None]
    R = np.eye(3)[None] + s * K + c * (K @ K)
    R[small] = np.eye(3)
    return R
