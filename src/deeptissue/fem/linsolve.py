"""Sparse symmetric solves (upper-triangle CSR) by MKL PARDISO (the library pypardiso ships, called through ctypes).

The FE solver's Newton systems are symmetric saddle-point matrices (tangent and contact constraints):
:meth:`PardisoSymmetric.solve_indefinite` factorises them in symmetric indefinite mode (mtype -2, Bunch-Kaufman
pivoting, double precision) and refines the solution while its residual halves.

:meth:`PardisoSymmetric.solve` solves a positive definite matrix (the linear-elastic reference of the
convergence study) in SPD mode (mtype 2), with the symbolic analysis (fill-in reducing ordering) done once per
sparsity pattern; it falls back to indefinite mode if the matrix is not positive definite. precision 'mixed'
(default): the Cholesky factor in single precision, refined in double precision until the normwise backward
error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf) is below refine_eta (1e-14); a matrix whose refinement does
not halve that error at every step is factorised again in double. The single-precision factorisation takes
55-60 % of the time of the double one on a rat's limb (41.6 k free dofs, one core). reuse_iterations > 0: a
matrix of the same pattern as the last one factorised is first solved by conjugate gradients preconditioned by
that factor to a relative residual reuse_rtol, and factorised when they fall behind a geometric decrease.

With more than one thread, PARDISO's numerical factorisation schedules its work dynamically and its
reductions follow the threads' timing, so repeated factorisations of one matrix differ in the last bits
and a Newton path that thresholds on them can differ by a few iterations; one thread, or
:func:`pin_reproducible` before the first PARDISO call, gives bitwise identical solves and, with the
assembly's sums in a fixed order (numpy, scipy, OpenBLAS), identical Newton paths.
"""

from __future__ import annotations

import ctypes
import logging

import numpy as np
import scipy.sparse as sp

_log = logging.getLogger(__name__)

__all__ = ["PRECISIONS", "NotPositiveDefinite", "PardisoSymmetric", "pin_reproducible"]


PRECISIONS = ("mixed", "double")  # of PardisoSymmetric


class NotPositiveDefinite(np.linalg.LinAlgError):
    """The Cholesky (SPD) factorisation failed."""


_P = ctypes.POINTER
_I32 = ctypes.c_int32


def _mkl_pardiso():
    """MKL's ``pardiso`` entry point, from the mkl_rt that pypardiso locates."""
    import pypardiso

    f = pypardiso.PyPardisoSolver().libmkl.pardiso
    f.argtypes = [_P(ctypes.c_int64), _P(_I32), _P(_I32), _P(_I32), _P(_I32), _P(_I32), ctypes.c_void_p,
                  _P(_I32), _P(_I32), _P(_I32), _P(_I32), _P(_I32), _P(_I32), ctypes.c_void_p, ctypes.c_void_p,
                  _P(_I32)]
    f.restype = None
    return f


_MKL_CBWR_COMPATIBLE = 3  # mkl_cbwr.h: SSE2 code path without approximation instructions


def pin_reproducible() -> None:
    """Put MKL in conditional numerical reproducibility mode (code branch COMPATIBLE: deterministic
    reductions and static scheduling) with a fixed number of threads, so that PARDISO solves are bitwise
    identical from run to run with the same thread count, on any x86-64 CPU. COMPATIBLE rather than AUTO
    because a cluster's nodes may differ in instruction set. MKL allows this only before its first
    computation in the process: RuntimeError after that."""
    import pypardiso

    lib = pypardiso.PyPardisoSolver().libmkl
    lib.MKL_CBWR_Set.argtypes = lib.MKL_Set_Dynamic.argtypes = [ctypes.c_int]
    status = lib.MKL_CBWR_Set(_MKL_CBWR_COMPATIBLE)
    if status != 0:
        raise RuntimeError(f"MKL refused the reproducible mode (MKL_CBWR_Set status {status}): it must be "
                           "set before the first MKL computation of the process")
    lib.MKL_Set_Dynamic(0)
    _log.info("MKL in reproducible mode: code branch COMPATIBLE, %d threads", lib.MKL_Get_Max_Threads())


def _pattern_key(U: sp.csr_matrix) -> tuple:
    return U.shape[0], U.nnz, hash(U.indptr.tobytes()), hash(U.indices.tobytes())


def _symmetric_matvec(U: sp.csr_matrix, diag: np.ndarray, v: np.ndarray) -> np.ndarray:
    """K v for K = U + triu(U, 1)^T given by its upper triangle U and diag = U.diagonal()."""
    return U @ v + U.T @ v - diag * v


class _Factor:
    """One PARDISO handle for a sparsity pattern (upper triangle, 0-based CSR), matrix type and precision."""

    def __init__(self, call, U: sp.csr_matrix, mtype: int, single: bool, key: tuple):
        self._call = call
        self.mtype, self.dtype = mtype, (np.float32 if single else np.float64)
        self.pt = np.zeros(64, np.int64)
        ip = self.iparm = np.zeros(64, np.int32)
        ip[0] = 1  # the settings below, not PARDISO's defaults
        ip[1] = 2  # METIS nested dissection
        ip[9] = 8 if mtype == -2 else 13  # pivot perturbation 1e-8 (symmetric indefinite)
        ip[20] = 1  # Bunch-Kaufman pivoting (symmetric indefinite)
        ip[27] = 1 if single else 0
        ip[34] = 1  # 0-based indices
        self.n = U.shape[0]
        self.ia, self.ja = U.indptr.astype(np.int32), U.indices.astype(np.int32)
        self.key = key  # _pattern_key(U)
        self.a = None
        self._pardiso(11, U.data.astype(self.dtype), np.zeros(self.n, self.dtype))

    def _pardiso(self, phase: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        x = np.zeros_like(b)
        err = _I32(0)
        self._call(self.pt.ctypes.data_as(_P(ctypes.c_int64)), ctypes.byref(_I32(1)), ctypes.byref(_I32(1)),
                   ctypes.byref(_I32(self.mtype)), ctypes.byref(_I32(phase)), ctypes.byref(_I32(self.n)), a.ctypes.data,
                   self.ia.ctypes.data_as(_P(_I32)), self.ja.ctypes.data_as(_P(_I32)), np.zeros(1, np.int32).ctypes.data_as(_P(_I32)),
                   ctypes.byref(_I32(1)), self.iparm.ctypes.data_as(_P(_I32)), ctypes.byref(_I32(0)), b.ctypes.data,
                   x.ctypes.data, ctypes.byref(err))
        if err.value != 0:
            raise np.linalg.LinAlgError(f"PARDISO error {err.value} (phase {phase}, mtype {self.mtype})")
        return x

    def factor(self, U: sp.csr_matrix) -> bool:
        """Numerical factorisation; False if it failed (mtype 2: not positive definite)."""
        self.a = np.ascontiguousarray(U.data, dtype=self.dtype)
        try:
            self._pardiso(22, self.a, np.zeros(self.n, self.dtype))
        except np.linalg.LinAlgError:
            self.a = None
            return False
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x (n,) float64 from the current factor (phase 33)."""
        return self._pardiso(33, self.a, np.ascontiguousarray(b, dtype=self.dtype)).astype(np.float64)

    def free(self):
        """Release PARDISO's memory of this handle (phase -1)."""
        if self.a is not None or np.any(self.pt):
            self._pardiso(-1, np.zeros(1, self.dtype), np.zeros(1, self.dtype))
        self.a = None


class PardisoSymmetric:
    """K x = b by MKL PARDISO; precision 'mixed' (single-precision Cholesky + refinement in double,
    and with reuse_iterations > 0 conjugate gradients preconditioned by the last factor first) or
    'double'. Counters: factorisations, double_fallbacks (mixed: refinement too slow, factorised again
    in double), refinements (solve steps after the first), reused (solved by conjugate gradients
    without a factorisation), reuse_failed (not converged: factorised), reuse_indefinite (non-positive
    curvature found), cg_iterations."""

    def __init__(self, precision: str = "mixed", *, refine_eta: float = 1e-14, max_refinements: int = 8,
                 reuse_iterations: int = 0, reuse_rtol: float = 1e-10):
        if precision not in PRECISIONS:
            raise ValueError(f"linear solver precision {precision!r}: expected one of {PRECISIONS}")
        if reuse_iterations < 0 or not 0 < reuse_rtol < 1:
            raise ValueError(f"linear solver: reuse_iterations {reuse_iterations} must be >= 0 and reuse_rtol "
                             f"{reuse_rtol} in (0, 1)")
        self._call = _mkl_pardiso()
        self.precision, self.refine_eta, self.max_refinements = precision, refine_eta, max_refinements
        self.reuse_iterations, self.reuse_rtol = reuse_iterations, reuse_rtol
        self._factors: dict = {}
        self.last_mode = None
        self.factorisations = self.double_fallbacks = self.refinements = 0
        self.reused = self.reuse_failed = self.reuse_indefinite = self.cg_iterations = 0

    @property
    def counters(self) -> dict:
        """The counters of the class docstring, by name."""
        return {k: getattr(self, k) for k in ("factorisations", "double_fallbacks", "refinements", "reused",
                                              "reuse_failed", "reuse_indefinite", "cg_iterations")}

    def _factor(self, name: str, U: sp.csr_matrix, mtype: int, single: bool, key: tuple) -> _Factor:
        """The handle of this name, analysed again (and the old one freed) if U's pattern (key) changed."""
        f = self._factors.get(name)
        if f is None or f.key != key:
            if f is not None:
                f.free()
            f = self._factors[name] = _Factor(self._call, U, mtype, single, key)
        return f

    def _refined(self, f: _Factor, U: sp.csr_matrix, b: np.ndarray) -> np.ndarray | None:
        """Iterative refinement with K = U + triu(U, 1)^T applied in double, until the normwise backward
        error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf) is below refine_eta; None if it stalls."""
        x = f.solve(b)
        diag = U.diagonal()
        a = abs(U)
        k_inf = float(np.max(a @ np.ones(U.shape[0]) + a.T @ np.ones(U.shape[0]) - np.abs(diag)))
        b_inf = float(np.max(np.abs(b)))
        eta_prev = np.inf
        for _ in range(self.max_refinements + 1):
            if not np.all(np.isfinite(x)):
                return None
            r = b - _symmetric_matvec(U, diag, x)
            eta = float(np.max(np.abs(r))) / (k_inf * float(np.max(np.abs(x))) + b_inf or 1.0)
            if eta <= self.refine_eta:
                return x
            if eta > 0.5 * eta_prev:
                return None
            eta_prev = eta
            self.refinements += 1
            x = x + f.solve(r)
        return None

    def _preconditioned_cg(self, f: _Factor, U: sp.csr_matrix, b: np.ndarray):
        """Conjugate gradients on K x = b (K = U + triu(U, 1)^T) preconditioned by the factor f of an
        earlier matrix: x, or 'indefinite' (p^T K p <= 0 for a search direction p), or None (no
        convergence to reuse_rtol, given up from the third iteration on as soon as the residual lags
        behind a geometric decrease from |b| to reuse_rtol |b| over reuse_iterations)."""
        diag = U.diagonal()
        b_2 = float(np.linalg.norm(b)) or 1.0
        x = np.zeros_like(b)
        r = b.copy()
        z = f.solve(r)
        p = z.copy()
        rz = float(r @ z)
        for k in range(1, self.reuse_iterations + 1):
            q = _symmetric_matvec(U, diag, p)
            pq = float(p @ q)
            self.cg_iterations += 1
            if not pq > 0:
                return "indefinite"
            alpha = rz / pq
            x += alpha * p
            r -= alpha * q
            eta = float(np.linalg.norm(r)) / b_2
            if eta <= self.reuse_rtol:
                _log.debug("    conjugate gradients on the last factor: %d iterations", k)
                return x
            if k >= 3 and eta > self.reuse_rtol ** (k / self.reuse_iterations):
                return None  # slower than geometric progress to reuse_rtol in reuse_iterations: factorise
            z = f.solve(r)
            rz_new = float(r @ z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        return None

    def solve(self, U: sp.csr_matrix, b: np.ndarray, spd_only: bool = False) -> np.ndarray:
        """Solve K x = b with K given by its upper triangle U (CSR, sorted, full diagonal).

        spd_only: raise NotPositiveDefinite instead of falling back to the indefinite factorisation.
        (With reuse, conjugate gradients that converge without meeting non-positive curvature return x
        even if K is indefinite; x is then still a descent direction: b^T x = x^T K x = sum of
        alpha_j^2 p_j^T K p_j > 0 over the K-conjugate search directions.)"""
        b = np.asarray(b, dtype=np.float64).ravel()
        mtypes = (2,) if spd_only else (2, -2)
        key = _pattern_key(U)
        if self.precision == "mixed" and self.reuse_iterations:
            f = self._factors.get("spd32")
            if f is not None and f.a is not None and f.key == key:
                x = self._preconditioned_cg(f, U, b)
                if isinstance(x, np.ndarray):
                    self.reused += 1
                    self.last_mode = "cg"
                    return x
                if isinstance(x, str):  # 'indefinite': the Cholesky factorisation would fail
                    self.reuse_indefinite += 1
                    if spd_only:
                        raise NotPositiveDefinite("the matrix is not positive definite (conjugate gradients)")
                    mtypes = (-2,)
                else:
                    self.reuse_failed += 1
        if self.precision == "mixed" and 2 in mtypes:
            f = self._factor("spd32", U, 2, True, key)
            self.factorisations += 1
            if f.factor(U):
                x = self._refined(f, U, b)
                if x is not None:
                    self.last_mode = 2
                    return x
                self.double_fallbacks += 1
            else:  # not positive definite: not retried as SPD in double (that would cost a second
                mtypes = mtypes[1:]  # factorisation that fails the same way): indefinite mode next
        for mtype in mtypes:
            f = self._factor(f"{mtype}", U, mtype, False, key)
            self.factorisations += 1
            if not f.factor(U):
                continue
            x = f.solve(b)
            if np.all(np.isfinite(x)):
                self.last_mode = mtype
                return x
        if spd_only:
            raise NotPositiveDefinite("PARDISO: the matrix is not positive definite")
        raise np.linalg.LinAlgError("PARDISO failed in SPD and symmetric-indefinite mode")

    def solve_indefinite(self, U: sp.csr_matrix, b: np.ndarray, *, max_refinements: int = 4) -> np.ndarray:
        """Solve K x = b for a symmetric indefinite K (a saddle-point matrix) given by its upper triangle U:
        Bunch-Kaufman factorisation in double precision (mtype -2, the analysis kept while the pattern is
        unchanged), refined while the relative residual |b - K x|_2 / |b|_2 at least halves and is above
        1e-13. LinAlgError if the factorisation fails or the solution is not finite."""
        b = np.asarray(b, dtype=np.float64).ravel()
        f = self._factor("-2", U, -2, False, _pattern_key(U))
        self.factorisations += 1
        if not f.factor(U):
            raise np.linalg.LinAlgError("PARDISO: symmetric indefinite factorisation failed")
        diag = U.diagonal()
        x = f.solve(b)
        err = np.inf
        for _ in range(max_refinements):
            r = b - _symmetric_matvec(U, diag, x)
            e = np.linalg.norm(r) / max(np.linalg.norm(b), 1e-300)
            if not e < 0.5 * err or e < 1e-13:
                break
            err = e
            self.refinements += 1
            x = x + f.solve(r)
        if not np.all(np.isfinite(x)):
            raise np.linalg.LinAlgError("PARDISO: non-finite solution")
        self.last_mode = -2
        return x

    def close(self):
        """Free every factor."""
        for f in self._factors.values():
            f.free()
        self._factors = {}
