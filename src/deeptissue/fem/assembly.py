"""Vectorised assembly of the hyperelastic internal force, tangent and energy on P2 (or P1) tetrahedra.

scikit-fem supplies the mesh, the P2 basis (P1 for a first-order TetMesh) and the quadrature (shape-function gradients in the
reference configuration at every quadrature point of every element); the hot loop is ours:
batched products over all elements x quadrature points, a sparsity pattern computed once and a
scatter of the element entries into CSR data by one sparse product.

Degrees of freedom: ``3 * node + component`` in TetMesh node numbering (node order of
``TetMesh.nodes_mm``), displacements in mm, forces in N, energy in mJ (N mm).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from skfem import Basis, ElementTetP1, ElementTetP2

from ..mesh import TetMesh
from .skmesh import SkMesh, to_skfem

__all__ = ["Assembler", "MaterialLaw", "as_material_law"]


@dataclass(frozen=True)
class MaterialLaw:
    """A hyperelastic law as three vectorised functions of (F, params), the API of :mod:`deeptissue.fem.material`.

    energy(F, params) -> W (...) [MPa]; stress(F, params) -> P (..., 3, 3) [MPa];
    stress_tangent(F, params) -> (W, P, A) with A (..., 3, 3, 3, 3) = dP_iJ/dF_kL [MPa].
    params must have ``mu_mpa`` and ``bulk_mpa`` (small-strain moduli, used for penalty scaling).
    """

    params: Any
    energy: Callable
    stress: Callable
    stress_tangent: Callable

    @property
    def mu_mpa(self) -> float:
        """Small-strain shear modulus [MPa]."""
        return float(self.params.mu_mpa)

    @property
    def bulk_mpa(self) -> float:
        """Small-strain bulk modulus [MPa]."""
        return float(self.params.bulk_mpa)

    @property
    def young_mpa(self) -> float:
        """Small-strain Young's modulus E = 9 K mu / (3 K + mu) [MPa]."""
        K, mu = self.bulk_mpa, self.mu_mpa
        return 9.0 * K * mu / (3.0 * K + mu)


def as_material_law(material) -> MaterialLaw:
    """A MaterialLaw as is, or an Ogden parameter set bound to deeptissue.fem.material's functions."""
    if isinstance(material, MaterialLaw):
        return material
    from . import material as ogden_module  # the Ogden law

    return MaterialLaw(
        params=material,
        energy=ogden_module.ogden_energy,
        stress=ogden_module.ogden_stress,
        stress_tangent=ogden_module.ogden_stress_tangent,
    )


class Assembler:
    """Internal force, tangent and strain energy of a TetMesh (P2, or P1 for a first-order mesh; total
    Lagrangian). ``n_local`` nodes per element: 10 (P2) or 4 (P1).

    constrained: boolean (n_dofs,) mask of Dirichlet dofs; the tangent is assembled only on the
    free dofs (upper triangle, CSR, for a symmetric solver), and the coupling free x constrained
    is kept per element for the Dirichlet predictor.
    """

    def __init__(
        self,
        mesh: TetMesh,
        law: MaterialLaw,
        *,
        constrained: np.ndarray | None = None,
        intorder: int = 2,
        skmesh: SkMesh | None = None,
    ):
        self.tetmesh = mesh
        self.law = law
        self.sk = skmesh if skmesh is not None else to_skfem(mesh)
        from .skmesh import reference_jacobians

        bad = np.flatnonzero(
            np.any(
                reference_jacobians(mesh, skmesh=self.sk, order=intorder, corners=False) <= 0,
                axis=1,
            )
        )
        if len(bad):
            raise ValueError(
                f"mesh: {len(bad)} tetrahedra have a non-positive Jacobian (inverted or too curved), e.g. tet {bad[0]}"
            )
        p1 = self.sk.order == 1
        self.n_local = 4 if p1 else 10
        basis = Basis(self.sk.mesh, ElementTetP1() if p1 else ElementTetP2(), intorder=intorder)
        # (E, Q, 10, 3) reference gradients, (E, Q) weights [mm^3]
        self.dN = np.ascontiguousarray(
            np.stack([basis.basis[a][0].grad for a in range(self.n_local)], axis=0).transpose(
                2, 3, 0, 1
            )
        )
        self.w = np.ascontiguousarray(basis.dx)
        E, Q = self.w.shape
        self._dN_rows = np.ascontiguousarray(
            self.dN.transpose(0, 2, 1, 3).reshape(E, self.n_local, Q * 3)
        )  # [e, a, (q, J)]
        self._dNT = np.ascontiguousarray(np.swapaxes(self.dN, -1, -2))  # [e, q, L, b]
        self.conn = self.sk.element_nodes()  # (E, 10) TetMesh nodes
        self.n_nodes = len(mesh.nodes_mm)
        self.n_dofs = 3 * self.n_nodes
        self.edofs = (3 * self.conn[:, :, None] + np.arange(3)).reshape(
            len(self.conn), 3 * self.n_local
        )
        self.volume_mm3 = float(self.w.sum())
        self.set_constrained(np.zeros(self.n_dofs, bool) if constrained is None else constrained)

    # ---------------------------------------------------------------- sparsity pattern
    def set_constrained(self, constrained: np.ndarray) -> None:
        """Set the Dirichlet mask (n_dofs,) bool and rebuild the free-dof sparsity pattern and scatter."""
        constrained = np.asarray(constrained, bool)
        self.constrained = constrained
        self.free = np.flatnonzero(~constrained)
        self.n_free = len(self.free)
        fidx = np.full(self.n_dofs, -1, dtype=np.int64)
        fidx[self.free] = np.arange(self.n_free)
        self.fidx = fidx
        # element entries in the layout of _element_blocks, [e, a, i, k, b] (row dof (a, i), column dof (b, k))
        E, n = self.conn.shape
        ef = fidx[self.edofs].reshape(E, n, 3)  # [e, a, i]
        r = np.broadcast_to(ef[:, :, :, None, None], (E, n, 3, 3, n)).reshape(E, -1)
        c = np.broadcast_to(ef.transpose(0, 2, 1)[:, None, None, :, :], (E, n, 3, 3, n)).reshape(
            E, -1
        )
        valid = (r >= 0) & (c >= 0) & (r <= c)
        keys = r[valid] * self.n_free + c[valid]
        ukeys, inv = np.unique(keys, return_inverse=True)
        self._keys = ukeys
        # the scatter of element entries into CSR data as a sparse product (0/1 entries, columns in element
        # order): the same sums as np.bincount, about 2.5x faster on a 9 305-element P2 mesh
        pos = np.flatnonzero(valid)
        self._scatter = sp.csr_matrix(
            (np.ones(len(pos)), (inv.ravel(), pos)), shape=(len(ukeys), valid.size)
        )
        self._scatter.sort_indices()
        rows = ukeys // self.n_free
        self.indices = (ukeys % self.n_free).astype(np.int32)
        self.indptr = np.zeros(self.n_free + 1, dtype=np.int32)
        np.cumsum(np.bincount(rows, minlength=self.n_free), out=self.indptr[1:])
        self.nnz = len(ukeys)
        # elements touching constrained dofs (for the Dirichlet predictor)
        self.bc_elems = np.flatnonzero(np.any(constrained[self.edofs], axis=1))

    def pattern_index(self, rows_free: np.ndarray, cols_free: np.ndarray) -> np.ndarray:
        """CSR data positions of free-dof pairs (upper triangle is taken); -1 where not stored."""
        r, c = np.minimum(rows_free, cols_free), np.maximum(rows_free, cols_free)
        ok = (r >= 0) & (c >= 0)
        k = np.where(ok, r * self.n_free + c, 0)
        p = np.searchsorted(self._keys, k)
        p = np.minimum(p, len(self._keys) - 1)
        good = ok & (self._keys[p] == k)
        return np.where(good, p, -1)

    def csr(self, data: np.ndarray) -> sp.csr_matrix:
        """Upper-triangular CSR matrix of the free dofs from pattern data (nnz,)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_free, self.n_free))

    # ---------------------------------------------------------------- kinematics
    def deformation_gradient(self, u: np.ndarray) -> np.ndarray:
        """F (E, Q, 3, 3) at the quadrature points for the nodal displacement u (n_dofs,) [mm]."""
        ue = u.reshape(-1, 3)[self.conn]  # (E, 10, 3)
        F = np.einsum("eai,eqaJ->eqiJ", ue, self.dN, optimize=True)
        F += np.eye(3)
        return F

    def det_f(self, u: np.ndarray) -> np.ndarray:
        """det F (E, Q) at the quadrature points for the nodal displacement u (n_dofs,) [mm]."""
        return np.linalg.det(self.deformation_gradient(u))

    def energy(self, u: np.ndarray, min_det: np.ndarray | float = 0.0) -> float:
        """Total strain energy [mJ]; +inf if det F <= min_det (a bound, or one per quadrature point (E, Q))
        anywhere."""
        F = self.deformation_gradient(u)
        if np.any(np.linalg.det(F) <= min_det):
            return np.inf
        W = self.law.energy(F, self.law.params)
        return float(np.sum(W * self.w))

    def force(self, u: np.ndarray, min_det: np.ndarray | float = 0.0):
        """(energy [mJ], internal force (n_dofs,) [N]); energy inf and force None if det F <= min_det (a bound,
        or one per quadrature point (E, Q)) anywhere: inverted, or compressed past that bound."""
        F = self.deformation_gradient(u)
        if np.any(np.linalg.det(F) <= min_det):
            return np.inf, None
        W = self.law.energy(F, self.law.params)
        P = self.law.stress(F, self.law.params)
        fe = np.einsum("eqiJ,eqaJ->eai", P * self.w[..., None, None], self.dN, optimize=True)
        f = np.bincount(self.edofs.ravel(), weights=fe.ravel(), minlength=self.n_dofs)
        return float(np.sum(W * self.w)), f

    def tangent(self, u: np.ndarray):
        """Energy, internal force and tangent at u.

        Returns (energy [mJ], f (n_dofs,) [N], data (nnz,) upper-triangle CSR data of K_ff [N/mm],
        Ke_bc (n_bc_elems, 30, 30) element matrices of elements touching constrained dofs) or
        (inf, None, None, None) if det F <= 0 somewhere.
        """
        F = self.deformation_gradient(u)
        if np.any(np.linalg.det(F) <= 0):
            return np.inf, None, None, None
        W, P, A = self.law.stress_tangent(F, self.law.params)
        w = self.w
        fe = np.einsum("eqiJ,eqaJ->eai", P * w[..., None, None], self.dN, optimize=True)
        f = np.bincount(self.edofs.ravel(), weights=fe.ravel(), minlength=self.n_dofs)
        Kb = self._element_blocks(A)
        # each global entry gets one term per element, in element order: the same sums as from element_matrices
        data = self._scatter @ Kb.reshape(-1)
        return float(np.sum(W * w)), f, data, self._standard_layout(Kb[self.bc_elems])

    def element_matrices(self, A: np.ndarray) -> np.ndarray:
        """Ke (E, 30, 30) = sum_q w dN_aJ A_iJkL dN_bL, dofs ordered (node a, component i); (E, 12, 12) for P1."""
        return self._standard_layout(self._element_blocks(A))

    def _element_blocks(self, A: np.ndarray) -> np.ndarray:
        """The entries of Ke in the order [e, a, i, k, b] (E, n * 9 * n), which two batched products give
        without reordering an intermediate: about twice as fast as in Ke's order on a 9 305-element P2
        mesh, each entry bit for bit the same."""
        E, Q = self.w.shape
        n = self.n_local
        # Aw[e, q, J, i, k, L] = w A_iJkL
        Aw = np.empty((E, Q, 3, 3, 3, 3))
        np.multiply(A.transpose(0, 1, 3, 2, 4, 5), self.w[:, :, None, None, None, None], out=Aw)
        # step 1: T[e, q, J, (i, k), b] = sum_L Aw[e, q, J, i, k, L] dN[e, q, b, L]
        T = np.matmul(Aw.reshape(E, Q, 3, 9, 3), self._dNT[:, :, None])
        # step 2: K[e, a, (i, k, b)] = sum_(q, J) dN[e, q, a, J] T[e, q, J, (i, k), b]: one batched product
        # over (q, J) (about 3x faster than a loop over q of (10 x 3) @ (3 x 90) products)
        return np.matmul(self._dN_rows, T.reshape(E, Q * 3, 9 * n)).reshape(E, -1)

    def _standard_layout(self, Kb: np.ndarray) -> np.ndarray:
        """Element blocks [e, a, i, k, b] (from _element_blocks) as matrices (E, 3n, 3n) [e, (a, i), (b, k)]."""
        n = self.n_local
        return Kb.reshape(-1, n, 3, 3, n).transpose(0, 1, 2, 4, 3).reshape(-1, 3 * n, 3 * n)

    def full_matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """Symmetric full K_ff from upper-triangle data (for tests and matvecs)."""
        U = self.csr(data)
        return (U + sp.triu(U, 1).T).tocsr()

    def bc_force(self, Ke_bc: np.ndarray, du: np.ndarray) -> np.ndarray:
        """K_fd du_d as a (n_dofs,) vector: the element matrices times du restricted to constrained dofs."""
        ed = self.edofs[self.bc_elems]
        due = np.where(self.constrained[ed], du[ed], 0.0)
        fe = np.einsum("eab,eb->ea", Ke_bc, due)
        return np.bincount(ed.ravel(), weights=fe.ravel(), minlength=self.n_dofs)
