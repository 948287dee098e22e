"""Analytical homogeneous responses of the uncoupled Ogden material (truth for the verification).

Independent of :mod:`deeptissue.fem.material`: scalar formulas in the principal stretches, no
eigen-decomposition and no tensor algebra. Units: stretches [-], stresses [MPa].

With J = l1 l2 l3, lb_a = J^(-1/3) l_a and W = 2 mu/alpha^2 (sum lb_a^alpha - 3) + (J - 1)^2 / D,
differentiating term by term (d lb_b / d l_a = lb_b (delta_ab - 1/3) / l_a, dJ / dl_a = J / l_a)
gives the principal Kirchhoff stresses

    tau_a = l_a dW/dl_a = (2 mu / alpha) (lb_a^alpha - (lb_1^alpha + lb_2^alpha + lb_3^alpha) / 3) + 2 J (J - 1) / D

with principal Cauchy stresses sigma_a = tau_a / J and nominal (first Piola-Kirchhoff) stresses
P_a = tau_a / l_a along the principal axes.

* Uniaxial tension/compression: stretches (l, t, t), lateral stretch t from tau_2 = 0 (1D root by
  Brent's method on ln t); nominal stress P_1 = tau_1 / l.
* Equibiaxial: stretches (l, l, t), t from tau_3 = 0; nominal stress P_1 = tau_1 / l.
* Simple shear F = I + gamma e1 (x) e2: J = 1, in-plane principal stretches
  l_1,2 = sqrt(1 + gamma^2/4) +- gamma/2, l_3 = 1, principal axes in the 1-2 plane. Any isotropic
  Cauchy stress is sigma = f0 I + f1 b in that plane, which gives
  sigma_12 = (sigma_1 - sigma_2) / sqrt(4 + gamma^2),
  sigma_22 = sigma_1 - (sigma_1 - sigma_2) l_1 / sqrt(4 + gamma^2),
  sigma_11 = sigma_22 + gamma sigma_12, sigma_33 = sigma_3 (all finite at gamma = 0).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

__all__ = [
    "principal_energy",
    "principal_kirchhoff",
    "uniaxial",
    "equibiaxial",
    "simple_shear_cauchy",
]


def _params(material):
    return material.mu_mpa, material.alpha, material.d_mm2_per_n


def principal_energy(l1: float, l2: float, l3: float, material) -> float:
    """W [MPa] from the principal stretches (plain float arithmetic)."""
    mu, al, D = _params(material)
    J = l1 * l2 * l3
    if J <= 0:
        return math.inf
    s = J ** (-1.0 / 3.0)
    return (
        2.0 * mu / al**2 * ((s * l1) ** al + (s * l2) ** al + (s * l3) ** al - 3.0)
        + (J - 1.0) ** 2 / D
    )


def principal_kirchhoff(l1: float, l2: float, l3: float, material) -> tuple[float, float, float]:
    """Principal Kirchhoff stresses (tau_1, tau_2, tau_3) [MPa] from the principal stretches."""
    mu, al, D = _params(material)
    J = l1 * l2 * l3
    s = J ** (-1.0 / 3.0)
    e = [(s * l) ** al for l in (l1, l2, l3)]
    mean = (e[0] + e[1] + e[2]) / 3.0
    pJ = 2.0 * J * (J - 1.0) / D
    return tuple(2.0 * mu / al * (ea - mean) + pJ for ea in e)


def _lateral(tau_lateral, what: str) -> float:
    """Root t > 0 of tau_lateral(t) = 0, bracketed on ln t in [-6, 6]."""
    f = lambda x: tau_lateral(math.exp(x))  # noqa: E731
    lo, hi = -6.0, 6.0
    if not f(lo) < 0 < f(hi):
        raise ValueError(f"{what}: no traction-free lateral stretch in [e^-6, e^6]")
    return math.exp(brentq(f, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200))


def uniaxial(stretch: float, material) -> tuple[float, float]:
    """Uniaxial stress with traction-free sides: (lateral stretch t [-], nominal stress P_11 [MPa])."""
    l = float(stretch)
    t = _lateral(lambda t: principal_kirchhoff(l, t, t, material)[1], f"uniaxial stretch {l}")
    return t, principal_kirchhoff(l, t, t, material)[0] / l


def equibiaxial(stretch: float, material) -> tuple[float, float]:
    """Equibiaxial stress (l, l, t) with a traction-free third direction: (t [-], nominal stress P_11 [MPa])."""
    l = float(stretch)
    t = _lateral(lambda t: principal_kirchhoff(l, l, t, material)[2], f"equibiaxial stretch {l}")
    return t, principal_kirchhoff(l, l, t, material)[0] / l


def simple_shear_cauchy(gamma: float, material) -> np.ndarray:
    """Cauchy stress (3, 3) [MPa] of the simple shear F = I + gamma e1 (x) e2."""
    g = float(gamma)
    root = math.sqrt(4.0 + g * g)
    l1 = 0.5 * root + 0.5 * g
    l2 = 1.0 / l1  # = 0.5 root - 0.5 g without cancellation
    s1, s2, s3 = principal_kirchhoff(l1, l2, 1.0, material)  # J = 1: Cauchy = Kirchhoff
    s12 = (s1 - s2) / root
    s22 = s1 - (s1 - s2) * l1 / root
    s11 = s22 + g * s12
    return np.array([[s11, s12, 0.0], [s12, s22, 0.0], [0.0, 0.0, s3]])
