"""Sparse symmetric solvers for the Newton tangent (upper-triangle CSR of the free dofs).

Default: MKL PARDISO through pypardiso in SPD mode (mtype 2) with the symbolic analysis (fill-in
reducing ordering) done once per sparsity pattern and only numerical factorisation + solve per
Newton iteration; falls back to symmetric indefinite mode (mtype -2) if the matrix is not positive
definite. 'amg': pyamg smoothed aggregation with rigid-body modes + CG (low memory).
'superlu': scipy (slow, reference).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class NotPositiveDefinite(np.linalg.LinAlgError):
    """The Cholesky (SPD) factorisation failed."""


class PardisoSymmetric:
    def __init__(self):
        import pypardiso

        self._pp = pypardiso
        self._solvers = {}
        self._pattern = None
        self.last_mode = None

    def _solver(self, mtype, A):
        s = self._solvers.get(mtype)
        key = (A.shape[0], A.nnz, hash(A.indptr.tobytes()), hash(A.indices.tobytes()))
        if s is None or s[1] != key:
            if s is not None:
                s[0].free_memory(everything=True)
            ps = self._pp.PyPardisoSolver(mtype=mtype)
            ps._check_A(A)
            ps.set_phase(11)  # analysis only, once per pattern
            ps._call_pardiso(A, np.zeros((A.shape[0], 1)))
            s = (ps, key)
            self._solvers[mtype] = s
        return s[0]

    def solve(self, U: sp.csr_matrix, b: np.ndarray, spd_only: bool = False) -> np.ndarray:
        """Solve K x = b with K given by its upper triangle U (CSR, sorted, full diagonal).

        spd_only: raise NotPositiveDefinite instead of falling back to the indefinite factorisation."""
        for mtype in ((2,) if spd_only else (2, -2)):
            ps = self._solver(mtype, U)
            ps._check_A(U)
            ps.set_phase(23)  # numerical factorisation + solve
            try:
                x = ps._call_pardiso(U, np.asfortranarray(b.reshape(-1, 1)))
            except self._pp.pardiso_wrapper.PyPardisoError:
                continue
            x = x.ravel()
            if np.all(np.isfinite(x)):
                self.last_mode = mtype
                return x
        if spd_only:
            raise NotPositiveDefinite("PARDISO: the matrix is not positive definite")
        raise np.linalg.LinAlgError("PARDISO failed in SPD and symmetric-indefinite mode")

    def close(self):
        for s, _ in self._solvers.values():
            s.free_memory(everything=True)
        self._solvers = {}


class AMGSolver:
    def __init__(self, coords_mm: np.ndarray | None = None, free: np.ndarray | None = None, rtol: float = 1e-8):
        self.coords = coords_mm
        self.free = free
        self.rtol = rtol
        self.last_mode = "amg"

    def solve(self, U, b, spd_only: bool = False):
        import pyamg
        from scipy.sparse.linalg import cg

        K = (U + sp.triu(U, 1).T).tocsr()
        B = None
        if self.coords is not None:
            c = self.coords - self.coords.mean(axis=0)
            n = len(c)
            B = np.zeros((3 * n, 6))
            for i in range(3):
                B[i::3, i] = 1.0
            B[0::3, 3], B[1::3, 3] = -c[:, 1], c[:, 0]
            B[1::3, 4], B[2::3, 4] = -c[:, 2], c[:, 1]
            B[0::3, 5], B[2::3, 5] = c[:, 2], -c[:, 0]
            if self.free is not None:
                B = B[self.free]
        ml = pyamg.smoothed_aggregation_solver(K, B=B, max_coarse=500)
        x, info = cg(K, b, rtol=self.rtol, maxiter=500, M=ml.aspreconditioner())
        if info != 0:
            raise np.linalg.LinAlgError(f"AMG-CG did not converge (info {info})")
        return x

    def close(self):
        pass


class SuperLUSolver:
    last_mode = "superlu"

    def solve(self, U, b, spd_only: bool = False):
        from scipy.sparse.linalg import spsolve

        K = (U + sp.triu(U, 1).T).tocsc()
        return spsolve(K, b)

    def close(self):
        pass


def make_solver(name: str, *, coords_mm: np.ndarray | None = None, free: np.ndarray | None = None):
    """'pardiso' (default), 'amg' (coords_mm (n_nodes, 3) and free dof indices for the rigid-body
    modes), 'superlu'."""
    if name == "pardiso":
        return PardisoSymmetric()
    if name == "amg":
        return AMGSolver(coords_mm, free)
    if name == "superlu":
        return SuperLUSolver()
    raise ValueError(f"linear solver {name!r}: expected 'pardiso', 'amg' or 'superlu'")
