"""Sparse symmetric solves (upper-triangle CSR) by one of three direct solvers, chosen per platform.

Backends (:data:`BACKENDS`), in the order :func:`linear_backend` prefers them when it chooses:

- ``pardiso``: MKL PARDISO (the library pypardiso ships, called through ctypes). x86-64 only, where MKL exists.
  Cholesky in single or double precision and Bunch-Kaufman (symmetric indefinite), METIS ordering, the symbolic
  analysis kept per sparsity pattern. The fastest on the FE tangent (docs/solver.md).
- ``cholmod``: SuiteSparse CHOLMOD through scikit-sparse (supernodal Cholesky in double precision, the symbolic
  analysis kept per pattern); an indefinite matrix goes to SuperLU. Any platform with SuiteSparse.
- ``scipy``: SciPy's SuperLU, always there: an LU with symmetric (diagonal) pivoting and a minimum-degree
  ordering of A + A^T as the Cholesky-like factor (in single or double precision; positive definite when every
  pivot is positive), partial pivoting for an indefinite matrix. Slower; correct everywhere.

The environment variable ``DEEPTISSUE_LINEAR_SOLVER`` (one of the backends) overrides the choice, e.g. to run
the tests as on a machine without MKL.

:meth:`SymmetricSolver.solve_constrained` solves the FE solver's Newton systems, symmetric saddle-point systems
of a tangent K and active contact constraints G, ``K x - G^T lam = r, G x = s``, without factorising the
indefinite saddle-point matrix: it factorises the augmented matrix ``A = K + G^T diag(rho) G`` of the size of K
(positive definite wherever K is on the constraints' kernel, so Cholesky, in single precision where the backend
has it) and iterates the augmented-Lagrangian correction on the saddle-point residual, in double precision. With
rho a thousand times the stiffness a constraint meets, a correction gains about three digits: four to six
triangular solves reach a relative residual of 1e-12.

:meth:`SymmetricSolver.solve` solves a positive definite matrix (the linear-elastic reference of the
convergence study) by Cholesky; it falls back to the indefinite factorisation if the matrix is not positive
definite. precision 'mixed' (default): the Cholesky factor in single precision, refined in double precision
until the normwise backward error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf) is below refine_eta (1e-14); a
matrix whose refinement does not halve that error at every step is factorised again in double. The
single-precision factorisation takes 55-60 % of the time of the double one on a rat's limb (PARDISO, 41.6 k
free dofs, one core). CHOLMOD has no single precision: there 'mixed' is 'double'.

With more than one thread, PARDISO's numerical factorisation schedules its work dynamically and its
reductions follow the threads' timing, so repeated factorisations of one matrix differ in the last bits
and a Newton path that thresholds on them can differ by a few iterations; one thread, or
:func:`pin_reproducible` before the first PARDISO call, gives bitwise identical solves and, with the
assembly's sums in a fixed order (numpy, scipy, OpenBLAS), identical Newton paths.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import importlib.util
import logging
import os
import sys
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

_log = logging.getLogger(__name__)

__all__ = [
    "BACKENDS",
    "PRECISIONS",
    "NotPositiveDefinite",
    "SymmetricSolver",
    "available_backends",
    "backward_error",
    "linear_backend",
    "pin_reproducible",
]


PRECISIONS = ("mixed", "double")  # of SymmetricSolver
BACKENDS = ("pardiso", "cholmod", "scipy")
BACKEND_ENV = "DEEPTISSUE_LINEAR_SOLVER"


class NotPositiveDefinite(np.linalg.LinAlgError):
    """The Cholesky (SPD) factorisation failed."""


# ------------------------------------------------------------------------------------------ choosing


@functools.cache
def _mkl_rt():
    """The mkl_rt library pypardiso loads, once per process. Where ``PYPARDISO_MKL_RT`` does not name it,
    pypardiso searches every folder under the environment's ``lib`` (0.5-0.6 s, in every solve job); the
    one that pip's ``mkl`` installs, ``{sys.prefix}/lib/libmkl_rt.so*``, is named to it first where it
    loads."""
    import pypardiso

    if not os.environ.get("PYPARDISO_MKL_RT"):
        for path in sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len):
            try:
                ctypes.CDLL(path)
            except OSError:
                continue
            os.environ["PYPARDISO_MKL_RT"] = path
            break
    return pypardiso.PyPardisoSolver().libmkl


def _has_mkl() -> bool:
    try:
        _mkl_rt()
    except Exception as exc:  # ImportError, OSError from ctypes, pypardiso's own errors
        _log.debug("MKL PARDISO not usable: %s: %s", type(exc).__name__, exc)
        return False
    return True


def _has_cholmod() -> bool:
    if importlib.util.find_spec("sksparse") is None:
        return False
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError as exc:  # the extension is there but its SuiteSparse library is not
        _log.debug("CHOLMOD not usable: %s", exc)
        return False
    return True


_WORKS = {"pardiso": _has_mkl, "cholmod": _has_cholmod, "scipy": lambda: True}


def available_backends() -> tuple[str, ...]:
    """The backends that work in this process, in :data:`BACKENDS` order ('scipy' always)."""
    return tuple(b for b in BACKENDS if _WORKS[b]())


def linear_backend() -> str:
    """The backend solves use: ``DEEPTISSUE_LINEAR_SOLVER`` if set, else the first of :data:`BACKENDS` that
    works here. ValueError for an unknown name, RuntimeError for a named backend this machine lacks."""
    name = os.environ.get(BACKEND_ENV, "").strip().lower()
    if not name:
        return next(b for b in BACKENDS if _WORKS[b]())
    if name not in BACKENDS:
        raise ValueError(
            f"{BACKEND_ENV}={name!r}: expected one of {BACKENDS} (or unset: the fastest available)"
        )
    if not _WORKS[name]():
        raise RuntimeError(
            f"{BACKEND_ENV}={name!r}, but it is not usable here (pardiso needs MKL on x86-64: pip install "
            "pypardiso mkl; cholmod needs scikit-sparse built against libsuitesparse-dev). Unset it to use "
            f"{available_backends()[0]!r}"
        )
    return name


_MKL_CBWR_COMPATIBLE = 3  # mkl_cbwr.h: SSE2 code path without approximation instructions


def pin_reproducible() -> None:
    """Put MKL in conditional numerical reproducibility mode (code branch COMPATIBLE: deterministic
    reductions and static scheduling) with a fixed number of threads, so that PARDISO solves are bitwise
    identical from run to run with the same thread count, on any x86-64 CPU. COMPATIBLE rather than AUTO
    because a cluster's nodes may differ in instruction set. MKL allows this only before its first
    computation in the process: RuntimeError after that. Where the backend is not PARDISO it does nothing
    (CHOLMOD and SuperLU factorise in a fixed order)."""
    if linear_backend() != "pardiso":
        _log.info("reproducible mode: nothing to pin for the %s backend", linear_backend())
        return
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


def _inf_norm(U: sp.csr_matrix) -> float:
    """|K|_inf of K = U + triu(U, 1)^T: its largest absolute row sum."""
    a = abs(U)
    ones = np.ones(U.shape[0])
    return float(np.max(a @ ones + a.T @ ones - np.abs(U.diagonal())))


def _backward_error(U, diag, k_inf: float, b: np.ndarray, b_inf: float, x: np.ndarray) -> tuple:
    """(normwise backward error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf), residual b - K x); diag, k_inf
    and b_inf: U.diagonal(), _inf_norm(U) and |b|_inf, computed once per system."""
    r = b - _symmetric_matvec(U, diag, x)
    return float(np.max(np.abs(r))) / (k_inf * float(np.max(np.abs(x))) + b_inf or 1.0), r


def backward_error(U: sp.csr_matrix, x: np.ndarray, b: np.ndarray) -> float:
    """The normwise backward error of x as a solution of K x = b, K = U + triu(U, 1)^T given by its upper
    triangle U: what :class:`SymmetricSolver` refines a single-precision solve to (``refine_eta``)."""
    return _backward_error(U, U.diagonal(), _inf_norm(U), b, float(np.max(np.abs(b))), x)[0]


# ------------------------------------------------------------------------------------------ factors
# A factor is made for one sparsity pattern (upper triangle U, sorted CSR) and one kind: 'spd32' (Cholesky in
# single precision), 'spd64' (in double), 'indefinite' (symmetric indefinite or LU). factor(U) -> bool (False:
# this kind does not factorise U, e.g. not positive definite); solve(b) -> x float64; free().

_P = ctypes.POINTER
_I32 = ctypes.c_int32


@functools.cache
def _mkl_pardiso():
    """MKL's ``pardiso`` entry point."""
    f = _mkl_rt().pardiso
    f.argtypes = [_P(ctypes.c_int64)] + [_P(_I32)] * 5 + [ctypes.c_void_p] + [_P(_I32)] * 6
    f.argtypes += [ctypes.c_void_p, ctypes.c_void_p, _P(_I32)]
    f.restype = None
    return f


class _PardisoFactor:
    """One PARDISO handle: symbolic analysis (METIS ordering) at construction, numerical factorisation by
    :meth:`factor`."""

    def __init__(self, U: sp.csr_matrix, kind: str):
        self._call = _mkl_pardiso()
        self.mtype = -2 if kind == "indefinite" else 2
        self.dtype = np.float32 if kind == "spd32" else np.float64
        self.pt = np.zeros(64, np.int64)
        ip = self.iparm = np.zeros(64, np.int32)
        ip[0] = 1  # the settings below, not PARDISO's defaults
        ip[1] = 2  # METIS nested dissection
        ip[9] = 8 if self.mtype == -2 else 13  # pivot perturbation 1e-8 (symmetric indefinite)
        ip[20] = 1  # Bunch-Kaufman pivoting (symmetric indefinite)
        ip[27] = 1 if kind == "spd32" else 0
        ip[34] = 1  # 0-based indices
        self.n = U.shape[0]
        self.ia, self.ja = U.indptr.astype(np.int32), U.indices.astype(np.int32)
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
        self.a = np.ascontiguousarray(U.data, dtype=self.dtype)
        try:
            self._pardiso(22, self.a, np.zeros(self.n, self.dtype))
        except np.linalg.LinAlgError:
            self.a = None
            return False
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = self._pardiso(33, self.a, np.ascontiguousarray(b, dtype=self.dtype))
        return x.astype(np.float64)

    def free(self):
        """Release PARDISO's memory of this handle (phase -1)."""
        if self.a is not None or np.any(self.pt):
            self._pardiso(-1, np.zeros(1, self.dtype), np.zeros(1, self.dtype))
        self.a = None


def _lower_csc(U: sp.csr_matrix) -> sp.csc_matrix:
    """The lower triangle of K = U + triu(U, 1)^T as CSC: U's own arrays, read transposed."""
    return sp.csc_matrix((U.data, U.indices, U.indptr), shape=U.shape)


class _CholmodFactor:
    """CHOLMOD's supernodal Cholesky in double precision; the symbolic analysis at construction."""

    def __init__(self, U: sp.csr_matrix, kind: str):
        from sksparse import cholmod

        self._cholmod = cholmod
        self._f = cholmod.analyze(_lower_csc(U), mode="supernodal")
        self._ok = False

    def factor(self, U: sp.csr_matrix) -> bool:
        with warnings.catch_warnings():
            warnings.simplefilter("error", self._cholmod.CholmodWarning)
            try:
                self._f.cholesky_inplace(_lower_csc(U))
            except (self._cholmod.CholmodError, self._cholmod.CholmodWarning):
                self._ok = False
                return False
        self._ok = True
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        return np.asarray(self._f(np.asarray(b, np.float64)), np.float64)

    def free(self):
        self._f = None


class _SuperLUFactor:
    """SciPy's SuperLU of K = U + triu(U, 1)^T. 'spd32' / 'spd64': symmetric mode (a minimum-degree ordering of
    A + A^T, diagonal pivots only), accepted as a Cholesky when no pivot left the diagonal and every pivot is
    positive (then K = L D L^T with D > 0); 'indefinite': partial pivoting."""

    def __init__(self, U: sp.csr_matrix, kind: str):
        self.kind = kind
        self.dtype = np.float32 if kind == "spd32" else np.float64
        self._lu = None

    def factor(self, U: sp.csr_matrix) -> bool:
        K = (U + sp.triu(U, 1).T).tocsc().astype(self.dtype)
        try:
            if self.kind == "indefinite":
                lu = sla.splu(K, permc_spec="MMD_AT_PLUS_A")
            else:
                lu = sla.splu(
                    K,
                    permc_spec="MMD_AT_PLUS_A",
                    diag_pivot_thresh=0.0,
                    options=dict(SymmetricMode=True),
                )
        except RuntimeError:  # exactly singular
            self._lu = None
            return False
        if self.kind != "indefinite" and not (
            np.array_equal(lu.perm_r, lu.perm_c) and np.all(lu.U.diagonal() > 0)
        ):
            self._lu = None
            return False
        self._lu = lu
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(np.ascontiguousarray(b, dtype=self.dtype)).astype(np.float64)

    def free(self):
        self._lu = None


# the factor of each kind a backend has (a kind it lacks is skipped: CHOLMOD has no single precision, and its
# indefinite matrices go to SuperLU)
_FACTORS = {
    "pardiso": {"spd32": _PardisoFactor, "spd64": _PardisoFactor, "indefinite": _PardisoFactor},
    "cholmod": {"spd64": _CholmodFactor, "indefinite": _SuperLUFactor},
    "scipy": {"spd32": _SuperLUFactor, "spd64": _SuperLUFactor, "indefinite": _SuperLUFactor},
}
_MODE = {"spd32": 2, "spd64": 2, "indefinite": -2}  # ``last_mode``: PARDISO's matrix type


class SymmetricSolver:
    """Symmetric sparse solves by a backend (:func:`linear_backend` unless named): :meth:`solve` (K x = b,
    precision 'mixed': single-precision Cholesky + refinement in double, or 'double') and
    :meth:`solve_constrained` (a saddle-point system through its augmented matrix). Counters: analyses
    (symbolic analyses: one per sparsity pattern and kind of factor), factorisations, double_fallbacks (a
    single-precision factor whose refinement was too slow, or that failed, factorised again), refinements
    (solve steps after the first). ``last_mode``: 2 (Cholesky) or -2 (indefinite) for the last solve."""

    def __init__(
        self,
        precision: str = "mixed",
        *,
        backend: str | None = None,
        refine_eta: float = 1e-14,
        max_refinements: int = 8,
    ):
        if precision not in PRECISIONS:
            raise ValueError(
                f"linear solver precision {precision!r}: expected one of {PRECISIONS}"
            )
        self.backend = backend or linear_backend()
        if self.backend not in BACKENDS:
            raise ValueError(f"linear solver backend {self.backend!r}: expected one of {BACKENDS}")
        self._kinds = _FACTORS[self.backend]
        self.precision, self.refine_eta = precision, refine_eta
        self.max_refinements = max_refinements
        self._factors: dict = {}  # kind -> (pattern key, factor)
        self.last_mode = None
        self.analyses = self.factorisations = self.double_fallbacks = self.refinements = 0

    @property
    def counters(self) -> dict:
        """The counters of the class docstring, by name."""
        names = ("analyses", "factorisations", "double_fallbacks", "refinements")
        return {k: getattr(self, k) for k in names}

    def _kinds_to_try(self, spd_only: bool) -> list[str]:
        kinds = ["spd32"] if self.precision == "mixed" else []
        kinds += ["spd64"] + ([] if spd_only else ["indefinite"])
        return [k for k in kinds if k in self._kinds]

    def _factor(self, kind: str, U: sp.csr_matrix):
        """The factor of this kind, analysed again (the old one freed) if U's pattern changed, then
        factorised; None if that fails."""
        key = _pattern_key(U)
        old = self._factors.get(kind)
        if old is None or old[0] != key:
            if old is not None:
                old[1].free()
            self._factors[kind] = (key, self._kinds[kind](U, kind))
            self.analyses += 1
        f = self._factors[kind][1]
        self.factorisations += 1
        return f if f.factor(U) else None

    def _refined(self, f, U: sp.csr_matrix, b: np.ndarray) -> np.ndarray | None:
        """Iterative refinement with K = U + triu(U, 1)^T applied in double, until the normwise backward
        error |b - K x|_inf / (|K|_inf |x|_inf + |b|_inf) is below refine_eta; None if it stalls."""
        x = f.solve(b)
        diag, k_inf, b_inf = U.diagonal(), _inf_norm(U), float(np.max(np.abs(b)))
        eta_prev = np.inf
        for _ in range(self.max_refinements + 1):
            if not np.all(np.isfinite(x)):
                return None
            eta, r = _backward_error(U, diag, k_inf, b, b_inf, x)
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
        not_spd = False
        kinds = self._kinds_to_try(spd_only)
        for kind in kinds:
            if kind == "spd64" and not_spd:
                continue  # the single-precision Cholesky found K indefinite: double fails the same way
            self.double_fallbacks += kind == "spd64" and kind != kinds[0]
            f = self._factor(kind, U)
            if f is None:
                not_spd = not_spd or kind == "spd32"
                continue
            x = self._refined(f, U, b) if kind == "spd32" else f.solve(b)
            if x is not None and np.all(np.isfinite(x)):
                self.last_mode = _MODE[kind]
                return x
        if spd_only:
            raise NotPositiveDefinite(f"{self.backend}: the matrix is not positive definite")
        raise np.linalg.LinAlgError(f"{self.backend}: no factorisation solves the matrix")

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
    ):
        """Solve the saddle-point system ``K x - G^T lam = r``, ``G x = s`` for (x (n,), lam (m,)).

        A: the upper triangle (CSR, sorted, full diagonal) of the augmented matrix ``K + G^T diag(rho) G``;
        G (m, n) the constraints' rows (m may be 0); rho (m,) > 0 their augmentation (in the units that make
        G^T diag(rho) G a stiffness). From (x, lam) = 0 each correction solves
        ``A dx = e_r + G^T (rho e_s)``, ``dlam = -rho (G dx - e_s)`` on the residuals ``e_r = r - K x + G^T lam``,
        ``e_s = s - G x`` (K x = A x - G^T rho G x), so the iteration converges to the saddle point's solution
        whatever the factor's precision, as long as it converges. The residual's size is
        ``sqrt(|e_r|^2 + |d e_s|^2)`` with d the median of A's diagonal (a constraint residual as the force
        that would close it). A is factorised by Cholesky in single precision (where the backend has it); if
        that fails (A not positive definite) or the corrections stop halving the residual, by Cholesky in
        double precision, then by the indefinite factorisation. Returns once the residual is below rtol times
        that of the right side; a residual that no factor brings below rtol is accepted below accept_rtol;
        LinAlgError otherwise."""
        r = np.asarray(r, dtype=np.float64).ravel()
        s = np.asarray(s, dtype=np.float64).ravel()
        rho = np.asarray(rho, dtype=np.float64).ravel()
        G = sp.csr_matrix(G)
        diag = A.diagonal()
        d = float(np.median(diag)) if len(diag) else 1.0
        b_norm = float(np.sqrt(r @ r + d * d * (s @ s)))
        if b_norm == 0.0:
            return np.zeros(A.shape[0]), np.zeros(G.shape[0])
        system = (A, diag, G, rho, r, s, d * d, b_norm)
        best, not_spd = np.inf, False
        kinds = self._kinds_to_try(spd_only=False)
        for kind in kinds:
            if kind == "spd64" and not_spd:
                continue  # single precision found A indefinite: a double Cholesky fails the same way
            f = self._factor(kind, A)
            if f is None:
                not_spd = not_spd or kind == "spd32"
                continue
            self.double_fallbacks += kind != kinds[0]
            x, lam, err = self._corrected(f, system, rtol)
            best = min(best, err)
            if err <= accept_rtol:
                self.last_mode = _MODE[kind]
                return x, lam
        raise np.linalg.LinAlgError(
            f"{self.backend}: the constrained system is not solved (best relative residual {best:.1e})"
        )

    def _corrected(self, f, system, rtol: float, max_corrections: int = 40):
        """The augmented-Lagrangian corrections of :meth:`solve_constrained` with factor f, from zero, until the
        relative residual is below rtol or stops halving: (x, lam, the last relative residual computed)."""
        A, diag, G, rho, r, s, d2, b_norm = system
        x, lam = np.zeros(A.shape[0]), np.zeros(G.shape[0])
        prev = err = np.inf
        for k in range(max_corrections):
            Gx = G @ x
            e_s = s - Gx
            e_r = r - (_symmetric_matvec(A, diag, x) - G.T @ (rho * Gx)) + G.T @ lam
            err = float(np.sqrt(e_r @ e_r + d2 * (e_s @ e_s))) / b_norm
            if err <= rtol or not np.isfinite(err) or err > 0.5 * prev:
                break
            prev = err
            if k:
                self.refinements += 1
            dx = f.solve(e_r + G.T @ (rho * e_s))
            x = x + dx
            lam = lam - rho * (G @ dx - e_s)
        return x, lam, (err if np.isfinite(err) else np.inf)

    def close(self):
        """Free every factor."""
        for _, f in self._factors.values():
            f.free()
        self._factors = {}
