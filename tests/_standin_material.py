"""Test-only stand-in material: compressible neo-Hookean with the API of deeptissue.fem.material
(energy, stress and stress_tangent as functions of (F, params); params with mu_mpa and bulk_mpa).

W = mu/2 (J^(-2/3) I1 - 3) + (J - 1)^2 / D  (= the uncoupled Ogden law with alpha = 2).
Used to test the FE core independently of deeptissue.fem.material.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NeoHooke:
    mu_kpa: float = 3.65
    alpha: float = 2.0
    d_mm2_per_n: float = 57.0

    @property
    def mu_mpa(self) -> float:
        return self.mu_kpa * 1e-3

    @property
    def bulk_mpa(self) -> float:
        return 2.0 / self.d_mm2_per_n


def _kin(F):
    J = np.linalg.det(F)
    ok = J > 0
    Fs = np.where(ok[..., None, None], F, np.eye(3))
    Js = np.where(ok, J, 1.0)
    H = np.swapaxes(np.linalg.inv(Fs), -1, -2)
    I1 = np.einsum("...ij,...ij->...", Fs, Fs)
    return ok, Fs, Js, H, I1


def neohooke_energy(F, material):
    ok, Fs, J, H, I1 = _kin(np.asarray(F, float))
    mu, K = material.mu_mpa, material.bulk_mpa
    W = 0.5 * mu * (J ** (-2.0 / 3.0) * I1 - 3.0) + 0.5 * K * (J - 1.0) ** 2
    return np.where(ok, W, np.inf)


def neohooke_stress(F, material):
    ok, Fs, J, H, I1 = _kin(np.asarray(F, float))
    mu, K = material.mu_mpa, material.bulk_mpa
    c = J ** (-2.0 / 3.0)
    P = (
        mu * c[..., None, None] * (Fs - (I1 / 3.0)[..., None, None] * H)
        + (K * (J - 1.0) * J)[..., None, None] * H
    )
    return P


def neohooke_stress_tangent(F, material):
    ok, Fs, J, H, I1 = _kin(np.asarray(F, float))
    mu, K = material.mu_mpa, material.bulk_mpa
    c = J ** (-2.0 / 3.0)
    W = np.where(ok, 0.5 * mu * (c * I1 - 3.0) + 0.5 * K * (J - 1.0) ** 2, np.inf)
    P = neohooke_stress(F, material)
    e = np.eye(3)
    HH = np.einsum("...iJ,...kL->...iJkL", H, H)
    HHt = np.einsum("...iL,...kJ->...iJkL", H, H)
    FH = np.einsum("...iJ,...kL->...iJkL", Fs, H)
    HF = np.einsum("...iJ,...kL->...iJkL", H, Fs)
    I4 = np.einsum("ik,JL->iJkL", e, e)
    x = lambda a: a[..., None, None, None, None]
    A = (
        mu
        * x(c)
        * (I4 - 2.0 / 3.0 * FH - 2.0 / 3.0 * HF + 2.0 / 9.0 * x(I1) * HH + 1.0 / 3.0 * x(I1) * HHt)
    )
    A = A + K * x((2.0 * J - 1.0) * J) * HH - K * x(J * J - J) * HHt
    return W, P, A


class NeoHookeLaw:
    """Bundle of the three functions, the form the solver accepts for any material."""

    energy = staticmethod(neohooke_energy)
    stress = staticmethod(neohooke_stress)
    stress_tangent = staticmethod(neohooke_stress_tangent)
