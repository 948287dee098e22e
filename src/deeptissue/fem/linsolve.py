"""Sparse symmetric solves (upper-triangle CSR) by MKL PARDISO (the library pypardiso ships, called through ctypes).

:meth:`PardisoSymmetric.solve_constrained` solves the FE solver's Newton systems, symmetric saddle-point systems
of a tangent K and active contact constraints G, ``K x - G^T lam = r, G x = s``, without factorising the
indefinite saddle-point matrix: it factorises the augmented matrix ``A = K + G^T diag(rho) G`` of the size of K
(positive definite wherever K is on the constraints' kernel, so Cholesky in single precision) and iterates the
augmented-Lagrangian correction on the saddle-point residual, in double precision. With rho a thousand times
the stiffness a constraint meets, a correction gains about three digits: four to six triangular solves reach a
relative residual of 1e-12. On a rat's limb (41.5 k free dofs, one core) that is 0.35-0.46 s for the
single-precision Cholesky and 0.08 s of corrections; the tangent alone takes 0.57 s to factorise by Cholesky
in double precision and 0.84 s by Bunch-Kaufman (docs/solver.md).

:meth:`PardisoSymmetric.solve` solves a positive definite matrix (the linear-elastic reference of the
convergence study) in SPD mode (mtype 2), with the symbolic analysis (fill-in reducing ordering) done once per
sparsity pattern; it falls back to indefinite mode if the matrix is not positive definite. precision 'mixed'
(default): the Cholesky factor in single precision, refined in double precision until the normwise backward
error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf) is below refine_eta (1e-14); a matrix whose refinement does
not halve that error at every step is factorised again in double. The single-precision factorisation takes
55-60 % of the time of the double one on a rat's limb (41.6 k free dofs, one core).

With more than one thread, PARDISO's numerical factorisation schedules its work dynamically and its
reductions follow the threads' timing, so repeated factorisations of one matrix differ in the last bits
and a Newton path that thresholds on them can differ by a few iterations; one thread, or
:func:`pin_reproducible` before the first PARDISO call, gives bitwise identical solves and, with the
assembly's sums in a fixed order (numpy, scipy, OpenBLAS), identical Newton paths.
"""

from __future__ import annotations

import ctypes
import functools
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


@functools.cache
def _mkl_rt():
    """The mkl_rt library pypardiso locates (once per process: it searches the file system, 0.2-0.5 s)."""
    import pypardiso

    return pypardiso.PyPardisoSolver().libmkl


@functools.cache
def _mkl_pardiso():
    """MKL's ``pardiso`` entry point."""
    f = _mkl_rt().pardiso
    f.argtypes = [
        _P(ctypes.c_int64),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        ctypes.c_void_p,
        _P(_I32),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        _P(_I32),
        ctypes.c_void_p,
        ctypes.c_void_p,
        _P(_I32),
    ]
    f.restype = None
    return f


_MKL_CBWR_COMPATIBLE = 3  # mkl_cbwr.h: SSE2 code path without approximation instructions


def pin_reproducible() -> None:
    """Put MKL in conditional numerical reproducibility mode (code branch COMPATIBLE: deterministic
    reductions and static scheduling) with a fixed number of threads, so that PARDISO solves are bitwise
    identical from run to run with the same thread count, on any x86-64 CPU. COMPATIBLE rather than AUTO
    because a cluster's nodes may differ in instruction set. MKL allows this only before its first
    computation in the process: RuntimeError after that."""
    lib = _mkl_rt()
    lib.MKL_CBWR_Set.argtypes = lib.MKL_Set_Dynamic.argtypes = [ctypes.c_int]
    status = lib.MKL_CBWR_Set(_MKL_CBWR_COMPATIBLE)
    if status != 0:
        raise RuntimeError(
            f"MKL refused the reproducible mode (MKL_CBWR_Set status {status}): it must be "
            "set before the first MKL computation of the process"
        )
    lib.MKL_Set_Dynamic(0)
    _log.info(
        "MKL in reproducible mode: code branch COMPATIBLE, %d threads", lib.MKL_Get_Max_Threads()
    )


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
        self._call(
            self.pt.ctypes.data_as(_P(ctypes.c_int64)),
            ctypes.byref(_I32(1)),
            ctypes.byref(_I32(1)),
            ctypes.byref(_I32(self.mtype)),
            ctypes.byref(_I32(phase)),
            ctypes.byref(_I32(self.n)),
            a.ctypes.data,
            self.ia.ctypes.data_as(_P(_I32)),
            self.ja.ctypes.data_as(_P(_I32)),
            np.zeros(1, np.int32).ctypes.data_as(_P(_I32)),
            ctypes.byref(_I32(1)),
            self.iparm.ctypes.data_as(_P(_I32)),
            ctypes.byref(_I32(0)),
            b.ctypes.data,
            x.ctypes.data,
            ctypes.byref(err),
        )
        if err.value != 0:
            raise np.linalg.LinAlgError(
                f"PARDISO error {err.value} (phase {phase}, mtype {self.mtype})"
            )
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
        return self._pardiso(33, self.a, np.ascontiguousarray(b, dtype=self.dtype)).astype(
            np.float64
        )

    def free(self):
        """Release PARDISO's memory of this handle (phase -1)."""
        if self.a is not None or np.any(self.pt):
            self._pardiso(-1, np.zeros(1, self.dtype), np.zeros(1, self.dtype))
        self.a = None


class PardisoSymmetric:
    """Symmetric sparse solves by PARDISO: :meth:`solve` (K x = b, precision 'mixed': single-precision
    Cholesky + refinement in double, or 'double') and :meth:`solve_constrained` (a saddle-point system through
    its augmented matrix). Counters: factorisations, double_fallbacks (a single-precision factor whose
    refinement was too slow, factorised again in double), refinements (solve steps after the first)."""

    def __init__(
        self, precision: str = "mixed", *, refine_eta: float = 1e-14, max_refinements: int = 8
    ):
        if precision not in PRECISIONS:
            raise ValueError(
                f"linear solver precision {precision!r}: expected one of {PRECISIONS}"
            )
        self._call = _mkl_pardiso()
        self.precision, self.refine_eta, self.max_refinements = (
            precision,
            refine_eta,
            max_refinements,
        )
        self._factors: dict = {}
        self.last_mode = None
        self.factorisations = self.double_fallbacks = self.refinements = 0

    @property
    def counters(self) -> dict:
        """The counters of the class docstring, by name."""
        return {k: getattr(self, k) for k in ("factorisations", "double_fallbacks", "refinements")}

    def _factor(
        self, name: str, U: sp.csr_matrix, mtype: int, single: bool, key: tuple
    ) -> _Factor:
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

    def solve(self, U: sp.csr_matrix, b: np.ndarray, spd_only: bool = False) -> np.ndarray:
        """Solve K x = b with K given by its upper triangle U (CSR, sorted, full diagonal).

        spd_only: raise NotPositiveDefinite instead of falling back to the indefinite factorisation."""
        b = np.asarray(b, dtype=np.float64).ravel()
        mtypes = (2,) if spd_only else (2, -2)
        key = _pattern_key(U)
        if self.precision == "mixed":
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

    def solve_constrained(
        self,
        A: sp.csr_matrix,
        G: sp.csr_matrix,
        rho: np.ndarray,
        r: np.ndarray,
        s: np.ndarray,
        *,
        rtol: float = 1e-12,
        accept_rtol: float = 1e-8,
        max_corrections: int = 40,
    ):
        """Solve the saddle-point system ``K x - G^T lam = r``, ``G x = s`` for (x (n,), lam (m,)).

        A: the upper triangle (CSR, sorted, full diagonal) of the augmented matrix ``K + G^T diag(rho) G``;
        G (m, n) the constraints' rows (m may be 0); rho (m,) > 0 their augmentation (in the units that make
        G^T diag(rho) G a stiffness). From (x, lam) = 0 each correction solves
        ``A dx = e_r + G^T (rho e_s)``, ``dlam = -rho (G dx - e_s)`` on the residuals ``e_r = r - K x + G^T lam``,
        ``e_s = s - G x`` (K x = A x - G^T rho G x), so the iteration converges to the saddle point's solution
        whatever the factor's precision, as long as it converges. The residual's size is
        ``sqrt(|e_r|^2 + |d e_s|^2)`` with d the median of A's diagonal (a constraint residual as the force
        that would close it). A is factorised by Cholesky in single precision; if that fails (A not positive
        definite) or the corrections stop halving the residual, by Cholesky in double precision, then by
        Bunch-Kaufman (symmetric indefinite). Returns once the residual is below rtol times that of the right
        side; a residual that no factor brings below rtol is accepted below accept_rtol; LinAlgError otherwise."""
        r = np.asarray(r, dtype=np.float64).ravel()
        s = np.asarray(s, dtype=np.float64).ravel()
        rho = np.asarray(rho, dtype=np.float64).ravel()
        G = sp.csr_matrix(G)
        diag = A.diagonal()
        d = float(np.median(diag)) if len(diag) else 1.0
        b_norm = float(np.sqrt(r @ r + d * d * (s @ s)))
        x, lam = np.zeros(A.shape[0]), np.zeros(G.shape[0])
        if b_norm == 0.0:
            return x, lam
        key = _pattern_key(A)
        best, indefinite = np.inf, False
        for name, mtype, single in (("spd32", 2, True), ("spd64", 2, False), ("-2", -2, False)):
            if name == "spd64" and indefinite:
                continue  # single precision found A indefinite: a double Cholesky fails the same way
            f = self._factor(name, A, mtype, single, key)
            self.factorisations += 1
            if not f.factor(A):
                indefinite = True
                continue
            if name != "spd32":
                self.double_fallbacks += 1
            prev = np.inf
            for k in range(max_corrections):
                Gx = G @ x
                e_s = s - Gx
                e_r = r - (_symmetric_matvec(A, diag, x) - G.T @ (rho * Gx)) + G.T @ lam
                err = float(np.sqrt(e_r @ e_r + d * d * (e_s @ e_s))) / b_norm
                best = min(best, err)
                if err <= rtol:
                    self.last_mode = mtype
                    return x, lam
                if not np.isfinite(err) or err > 0.5 * prev:
                    break
                prev = err
                if k:
                    self.refinements += 1
                dx = f.solve(e_r + G.T @ (rho * e_s))
                x = x + dx
                lam = lam - rho * (G @ dx - e_s)
            if np.isfinite(err) and err <= accept_rtol:
                self.last_mode = mtype
                return x, lam
            x, lam = np.zeros(A.shape[0]), np.zeros(G.shape[0])
        raise np.linalg.LinAlgError(
            f"PARDISO: the constrained system is not solved (best relative residual {best:.1e})"
        )

    def close(self):
        """Free every factor."""
        for f in self._factors.values():
            f.free()
        self._factors = {}
