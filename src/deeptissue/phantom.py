"""Digital phantom of a rat leg in a surface coil, before and during indentation, with exact truth.

The anatomy is analytic, so every boundary is known exactly:

- **leg** (skin surface): a star-shaped cross-section about a slowly drifting centre,
  ``r(θ, z) = R(z) (1 + e cos 2θ + h3 cos(3θ + φ3) + h4 cos(4θ + φ4))`` with a linear taper
  ``R(z) = leg_radius_mm + leg_taper * z`` (8–11 mm across with the defaults); a skin and
  subcutaneous layer ``skin_thickness_mm`` thick lines it.
- **tibia**: eccentric, its centre drifting slightly with z; a rounded-triangular cross-section
  (the rat's mid-shaft, anterior crest towards +y): the smooth maximum of three half-planes,
  ``f = (1/k) log Σ exp(k (n_i·(p - c) - d_i))``, with ``d_i`` ``tibia_inradius_mm`` (seeded ±8 % per
  side) times ``s(z) = 1 + tibia_taper z + tibia_flare z²`` (narrower distally, flaring
  proximally), corner rounding ``1/k`` growing distally (``tibia_rounding_mm``,
  ``tibia_rounding_slope``), and the crest turning ``tibia_twist`` deg per mm. A dark cortex
  ``cortex_thickness_mm`` thick on the sides (the marrow is the same shape scaled down about the
  centre) around a darker-than-muscle marrow.
- **fibula**: a thin bone (``fibula_radius_mm``, 0.84 mm across; a dark cortex
  ``fibula_cortex_mm`` thick around marrow, the tibia's intensities) lateral-posterior of the tibia, at
  ``fibula_angle_deg`` from its centre. Its circular z-sections are centred at ``c_tibia(z) + D(z) u``
  with ``D(z) = D_d + (D_p - D_d) (1 + tanh((z - z_c) / L)) / 2``: proximally it runs
  ``fibula_offset_mm`` (``D_p``) from the tibia's centre, distally it converges on the tibia (to
  ``fibula_distal_offset_mm``, ``D_d``; it fuses with the tibia distal of the slab) over a length
  ``fibula_converge_mm`` (``L``) about ``fibula_converge_z_mm`` (``z_c``). The converging stretch
  moves the fibula across the slice by up to ``(D_p - D_d) / (2 L)`` mm per mm of z (0.72 with the
  defaults; over 0.3 on five slices), so a shift of the leg bones along z moves it in the slice:
  the tibia alone, nearly a prism, hardly shows such a shift. It moves with the tibia (one rigid
  body). Kept >= 0.3 mm from the tibia and >= 0.3 mm below the skin layer (else an error).
- **coil**: a surface loop of radius ``coil_radius_mm`` above the anterior (+y) skin; sensitivity
  ``(a² / (a² + d²))^(3/2)`` with ``d`` the distance below the coil, normalised to 1 in the
  well-lit muscle 1 mm under the skin where the indenter enters; the posterior side gets about
  40 % of that.
- **noise**: Rician (magnitude of the signal plus complex Gaussian noise), ``sigma = 1 / snr``
  (muscle in the well-lit region has signal 1).
- **indenter** (during): a hollow cylinder of radius ``indenter_radius_mm`` (1.5 mm, the FE
  indenter's default, :class:`deeptissue.fem.indenters.Indenter`) ending in a hemispherical head,
  dark wall ``indenter_wall_mm`` thick, filled with bright contrast fluid. Its axis points nominally
  along −y (from the coil side into the leg) through the tibia centre at ``indenter_z_mm``, tilted
  by ``tilt_deg = (about X, about Z)``. The tip travels from 1 mm outside the skin to ``depth_mm``
  beyond the skin point on the axis. The skin conforms to the head: the tissue is ``max(φ_pre +
  dimple, −sd_indenter) < 0`` with ``φ_pre`` the radial distance outside the pre skin, ``dimple`` a
  smooth axisymmetric sag (shallower than the head, so the head defines the surface where it
  touches) and ``sd_indenter`` the indenter's signed distance; tissue in the indenter's place is
  displaced, the skin layer follows the surface.
- **tibia motion** (during): rigid, ``x -> R (x - c) + c + t`` about the pre tibia centre of mass
  ``c`` (:mod:`deeptissue.rigid`); the fibula moves with it.

Rendering is anti-aliased by ``supersample``² sub-samples per pixel in the slice plane; slices
are planes of constant z (1 mm apart), so the truth contours are the exact boundaries in those
planes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from scipy.optimize import brentq

from .contours import Contours, polygon_area_centroid, resample_closed, save_contours
from .pose import Pose, save_pose
from .pose.checks import LIMITS
from .rigid import rotation_matrix

__all__ = ["Phantom", "PhantomSpec", "check_indenter", "make_phantom", "write_phantom"]


@dataclass(frozen=True)
class PhantomSpec:
    """Parameters of a phantom. Lengths in mm, angles in degrees, intensities relative to muscle."""

    seed: int = 0
    depth_mm: float = 2.0
    tilt_deg: tuple = (0.0, 0.0)
    bone_rotation_deg: tuple = (0.0, 0.0, 0.0)
    bone_translation_mm: tuple = (0.0, 0.0, 0.0)
    snr: float = 20.0
    # anatomy
    leg_radius_mm: float = 4.7
    leg_taper: float = 0.04  # mm of radius per mm of z
    leg_ellipticity: float = 0.08
    skin_thickness_mm: float = 0.4
    tibia_centre_mm: tuple = (-0.9, -0.3)
    tibia_inradius_mm: float = (
        0.78  # centre to each flat side of the triangular cross-section at z = 0
    )
    tibia_rounding_mm: float = (
        0.2  # corner rounding (1 / sharpness of the smooth maximum) at z = 0
    )
    tibia_rounding_slope: float = (
        -0.008
    )  # its change per mm of z (a sharper crest proximally, rounder distally)
    tibia_crest_angle_deg: float = (
        100.0  # direction of the anterior crest (one corner) from +x at z = 0
    )
    tibia_twist: float = 1.0  # deg per mm: the crest turns slowly along z (torsion)
    tibia_taper: float = 0.012  # relative change of the size per mm of z (wider proximally, +z)
    tibia_flare: float = 0.0006  # relative quadratic term per mm² (the proximal flare)
    cortex_thickness_mm: float = 0.3
    fibula: bool = True  # False: no fibula (the tibia alone)
    fibula_radius_mm: float = 0.42  # radius of its circular z-sections (seeded +-5 %)
    fibula_cortex_mm: float = 0.2
    fibula_angle_deg: float = (
        -20.0
    )  # direction from the tibia centre, from +x (lateral-posterior; seeded +-5 deg)
    fibula_offset_mm: float = (
        3.8  # proximal centre-to-centre distance from the tibia (seeded +-0.1 mm)
    )
    fibula_distal_offset_mm: float = (
        2.0  # distal centre-to-centre distance, where it runs beside the tibia before fusing
    )
    fibula_converge_z_mm: float = -5.5  # z where it converges on the tibia fastest
    fibula_converge_mm: float = 1.25  # length scale of the convergence along z (tanh)
    # coil
    coil_radius_mm: float = 11.0
    coil_gap_mm: float = 1.0
    # intensities (muscle = 1 in the well-lit region)
    muscle: float = 1.0
    skin: float = 0.8
    cortex: float = 0.05
    marrow: float = 0.35
    fluid: float = 2.0
    wall: float = 0.0
    # indenter
    indenter_radius_mm: float = 1.5
    indenter_wall_mm: float = 0.5
    indenter_z_mm: float = 0.0
    # image grid
    n_pixels: int = 256
    fov_mm: float = 25.0
    n_slices: int = 20
    slice_mm: float = 1.0
    supersample: int = 8

    def __post_init__(self):
        """Refuse a parameter that is not a finite number (NaN passes every comparison, so it would pass the
        bounds and end in a phantom of NaN voxels or a missing bone boundary)."""
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            vals = v if isinstance(v, (tuple, list)) else (v,)
            try:
                finite = all(np.isfinite(float(x)) for x in vals)
            except (TypeError, ValueError):
                finite = False
            if not finite:
                shown = [*v] if isinstance(v, (tuple, list)) else v
                raise ValueError(f"phantom: {f.name} {shown}: not a finite number; give a number")

    @classmethod
    def from_config(cls, cfg: dict) -> PhantomSpec:
        """Spec from a config ``phantom`` mapping (unknown keys are an error naming them)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ValueError(f"phantom: unknown key(s) {unknown}")
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in cfg.items()}
        return cls(**kw)


@dataclass(frozen=True)
class Phantom:
    """A rendered phantom: volumes (n_pixels, n_pixels, n_slices) float32, RAS affine (4, 4) mm, truth."""

    spec: PhantomSpec
    pre: np.ndarray
    during: np.ndarray
    affine: np.ndarray
    truth: Pose
    truth_pre: Contours
    truth_during: Contours
    noise_sigma: float
    dense: dict = field(
        default_factory=dict
    )  # (state, structure) -> list of (m, 3) exact boundary polylines per slice (structure: skin, bone, fibula)

    @property
    def z_mm(self) -> np.ndarray:
        """Slice positions (n_slices,) [mm]."""
        return self.affine[2, 2] * np.arange(self.pre.shape[2]) + self.affine[2, 3]


class _Anatomy:
    """The analytic shapes of one phantom (pre state) plus the indenter and bone motion."""

    def __init__(self, spec: PhantomSpec):
        self.s = spec
        rng = np.random.default_rng([spec.seed, 7])
        self.h3, self.h4 = rng.uniform(0.0, 0.025, 2)
        self.p3, self.p4 = rng.uniform(0, 2 * np.pi, 2)
        self.leg_c0 = rng.uniform(-0.2, 0.2, 2)
        self.leg_drift = rng.uniform(-0.01, 0.01, 2)
        self.tib_c0 = np.asarray(spec.tibia_centre_mm, float) + rng.uniform(-0.15, 0.15, 2)
        self.tib_drift = np.array([0.015, -0.01]) + rng.uniform(-0.005, 0.005, 2)
        # the three sides differ a little (seeded): relative inradius of each side
        self.tib_side = 1.0 + rng.uniform(-0.08, 0.08, 3)
        self.tib_crest = np.radians(spec.tibia_crest_angle_deg + rng.uniform(-8.0, 8.0))
        # fibula: its own stream, so that the tibia and leg of a seed do not change with it
        frng = np.random.default_rng([spec.seed, 13])
        self.fib_radius = spec.fibula_radius_mm * (1.0 + frng.uniform(-0.05, 0.05))
        a = np.radians(spec.fibula_angle_deg + frng.uniform(-5.0, 5.0))
        self.fib_u = np.array([np.cos(a), np.sin(a)])
        self.fib_offset = spec.fibula_offset_mm + frng.uniform(-0.1, 0.1)

    # leg ------------------------------------------------------------------------------------
    def leg_centre(self, z):
        z = np.asarray(z, float)
        return self.leg_c0[0] + self.leg_drift[0] * z, self.leg_c0[1] + self.leg_drift[1] * z

    def leg_r(self, theta, z):
        s = self.s
        R = s.leg_radius_mm + s.leg_taper * np.asarray(z, float)
        return R * (
            1
            + s.leg_ellipticity * np.cos(2 * theta)
            + self.h3 * np.cos(3 * theta + self.p3)
            + self.h4 * np.cos(4 * theta + self.p4)
        )

    def phi_pre(self, x, y, z):
        """Radial distance (mm) outside the pre skin (negative inside)."""
        cx, cy = self.leg_centre(z)
        dx, dy = x - cx, y - cy
        return np.hypot(dx, dy) - self.leg_r(np.arctan2(dy, dx), z)

    # tibia ----------------------------------------------------------------------------------
    def tib_centre(self, z):
        z = np.asarray(z, float)
        return self.tib_c0[0] + self.tib_drift[0] * z, self.tib_c0[1] + self.tib_drift[1] * z

    def tib_scale(self, z):
        """Relative size of the cross-section along z: taper and proximal flare (1 at z = 0)."""
        z = np.asarray(z, float)
        return 1.0 + self.s.tibia_taper * z + self.s.tibia_flare * z**2

    def tib_rounding(self, z):
        """Corner rounding (mm) at z: 1 / the sharpness k of the smooth maximum in :meth:`bone_f`."""
        return self.s.tibia_rounding_mm + self.s.tibia_rounding_slope * np.asarray(z, float)

    def bone_f(self, x, y, z, inset=0.0):
        """Level function of the tibia (mm; < 0 inside; with ``inset`` mm: the marrow's).

        A rounded triangle: the smooth maximum (log-sum-exp, sharpness ``k = 1 / rounding(z)``) of
        the three side functions ``n_i · (p - c(z)) - d_i(z)``, outward side normals ``n_i`` at the
        crest direction ``θc(z)`` + 60°, 180°, 300° (the crest is the corner between the first and
        the last side), ``d_i = tibia_inradius_mm · side_i · scale(z)``. It is convex in (x, y), its
        zero set is the exact boundary, and its gradient has length <= 1, so ``|f|`` is at most the
        distance to the boundary. The marrow is the same shape scaled about the centre by
        ``λ = 1 - inset / d(z)`` (``f_m(p) = λ f(c + (p - c) / λ)``, gradient <= 1 too): the cortex
        is ``inset`` thick on the sides and a little thicker at the corners.
        """
        s = self.s
        z = np.asarray(z, float)
        cx, cy = self.tib_centre(z)
        d0 = s.tibia_inradius_mm * self.tib_scale(z)
        lam = 1.0 - inset / d0
        dx, dy = (x - cx) / lam, (y - cy) / lam
        k = 1.0 / self.tib_rounding(z)
        crest = self.tib_crest + np.radians(s.tibia_twist) * z
        terms = []
        for i, off in enumerate((np.pi / 3, np.pi, -np.pi / 3)):
            a = crest + off
            terms.append(k * (dx * np.cos(a) + dy * np.sin(a) - d0 * self.tib_side[i]))
        terms = np.stack(np.broadcast_arrays(*terms))
        m = terms.max(axis=0)
        return lam * (m + np.log(np.exp(terms - m).sum(axis=0))) / k

    def tib_r(self, theta, z, inset=0.0):
        """Radius (mm) of the tibia boundary (or the marrow's, ``inset``) at polar angle ``theta``
        (rad, from +x) about ``tib_centre(z)``: the root of ``bone_f`` along the ray (Newton from
        outside; ``bone_f`` is convex along the ray, so the iteration is monotone)."""
        theta, z = np.broadcast_arrays(np.asarray(theta, float), np.asarray(z, float))
        cx, cy = self.tib_centre(z)
        u, v = np.cos(theta), np.sin(theta)
        # start outside: a corner of the sharp triangle is 2 inradii out, the rounding only pulls in
        r = (
            3.0
            * self.s.tibia_inradius_mm
            * np.maximum(self.tib_scale(z), 1.0)
            * max(self.tib_side.max(), 1.0)
        )
        h = 1e-6
        for _ in range(60):
            f = self.bone_f(cx + r * u, cy + r * v, z, inset)
            df = (
                self.bone_f(cx + (r + h) * u, cy + (r + h) * v, z, inset)
                - self.bone_f(cx + (r - h) * u, cy + (r - h) * v, z, inset)
            ) / (2 * h)
            step = f / df
            r = r - step
            if np.abs(step).max() < 1e-12:
                break
        return r

    def tib_radius_range(
        self, z_lo: float, z_hi: float, inset: float = 0.0
    ) -> tuple[float, float]:
        """Smallest and largest radius (mm) of the tibia boundary (or the marrow's) for z in [z_lo, z_hi]."""
        th, zz = np.meshgrid(
            np.linspace(0, 2 * np.pi, 360, endpoint=False), np.linspace(z_lo, z_hi, 21)
        )
        r = self.tib_r(th, zz, inset)
        return float(r.min()), float(r.max())

    def tib_area_centroid(self, z: float) -> tuple[float, np.ndarray]:
        """Area (mm²) and centroid (x, y) mm of the tibia cross-section at z (polar integrals of the
        exact boundary radius, converging exponentially for this smooth periodic r(θ)):
        A = ½∮r² dθ, c = ⅓∮r³ (cos θ, sin θ) dθ / A."""
        th = np.linspace(0, 2 * np.pi, 2048, endpoint=False)
        r = self.tib_r(th, z)
        area = np.pi * np.mean(r**2)
        c = (
            2
            * np.pi
            / 3
            * np.array([np.mean(r**3 * np.cos(th)), np.mean(r**3 * np.sin(th))])
            / area
        )
        return float(area), np.asarray(self.tib_centre(z), float) + c

    # fibula ---------------------------------------------------------------------------------
    def fib_offset_at(self, z):
        """Centre-to-centre distance (mm) of the fibula from the tibia centre along ``fib_u`` at z."""
        s = self.s
        w = 0.5 * (
            1.0 + np.tanh((np.asarray(z, float) - s.fibula_converge_z_mm) / s.fibula_converge_mm)
        )
        return s.fibula_distal_offset_mm + (self.fib_offset - s.fibula_distal_offset_mm) * w

    def fib_centre(self, z):
        """Centre (x, y) mm of the fibula's circular section at z."""
        cx, cy = self.tib_centre(z)
        d = self.fib_offset_at(z)
        return cx + d * self.fib_u[0], cy + d * self.fib_u[1]

    def fib_slope_max(self) -> float:
        """Largest in-plane speed (mm per mm of z) of the fibula centre: a bound for :meth:`fibula_f`."""
        s = self.s
        conv = abs(self.fib_offset - s.fibula_distal_offset_mm) / (2.0 * s.fibula_converge_mm)
        return float(np.hypot(*self.tib_drift) + conv)

    def fibula_f(self, x, y, z, inset=0.0):
        """Level function of the fibula (mm; < 0 inside; with ``inset`` mm: the marrow's).

        ``(|p - c(z)| - r) / sqrt(1 + v²)`` with ``v`` the largest in-plane speed of the centre along
        z, so that its 3D gradient is <= 1 and ``|f|`` bounds the distance to the boundary in any
        plane (the moved bone is cut by tilted planes); its zero set is the exact circle of each z.
        """
        cx, cy = self.fib_centre(z)
        norm = np.sqrt(1.0 + self.fib_slope_max() ** 2)
        return (np.hypot(x - cx, y - cy) - (self.fib_radius - inset)) / norm

    def fib_boundary(self, z: float, n: int = 180) -> np.ndarray:
        """(n, 2) points (mm) on the fibula's circular boundary at z."""
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        cx, cy = self.fib_centre(z)
        return np.column_stack(
            [cx + self.fib_radius * np.cos(th), cy + self.fib_radius * np.sin(th)]
        )

    def tib_boundary(self, z: float, n: int = 180) -> np.ndarray:
        """(n, 2) points (mm) on the outer tibia boundary at z."""
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        r = self.tib_r(th, z)
        cx, cy = self.tib_centre(z)
        return np.column_stack([cx + r * np.cos(th), cy + r * np.sin(th)])


def _indenter_entry(
    an: _Anatomy, spec: PhantomSpec, tilt_deg
) -> tuple[np.ndarray, np.ndarray] | None:
    """Unit axis (3,) and skin point (3,) [mm] of the indenter aimed at the tibia centre at ``indenter_z_mm``
    (nominal -y, tilted about X then Z by ``tilt_deg``); None if the axis does not leave the leg within 30 mm."""
    z0 = spec.indenter_z_mm
    aim = np.array([*an.tib_centre(z0), z0], float)
    tx, tz = tilt_deg
    axis = rotation_matrix([0, 0, tz]) @ rotation_matrix([tx, 0, 0]) @ np.array([0.0, -1.0, 0.0])
    axis = axis / np.linalg.norm(axis)
    f = lambda s_: float(an.phi_pre(*(aim - s_ * axis)))
    if not (f(0.0) < 0.0 < f(30.0)):
        return None
    return axis, aim - brentq(f, 0.0, 30.0, xtol=1e-12) * axis


def _tilt_x_range(an: _Anatomy, spec: PhantomSpec, inside) -> tuple[float, float] | None:
    """Smallest and largest tilt about X [deg] (at the spec's tilt about Z) for which ``inside(tilt)`` holds, by
    bisection outward from 0; None if it does not hold at 0."""
    tz = spec.tilt_deg[1]
    if not inside((0.0, tz)):
        return None
    ends = []
    for sign in (-1.0, 1.0):
        good, bad = 0.0, 90.0
        while bad - good > 0.1:
            mid = 0.5 * (good + bad)
            good, bad = (mid, bad) if inside((sign * mid, tz)) else (good, mid)
        ends.append(sign * good)
    return ends[0], ends[1]


def _fluid_in_image(spec: PhantomSpec, front: np.ndarray, axis: np.ndarray, z_range) -> float:
    """Length [mm] of the fluid column's axis, from its ``front`` back along ``-axis``, inside the image (the
    in-plane field of view and the slab ``z_range``)."""
    half = spec.fov_mm / 2.0
    lo = np.array([-half, -half, z_range[0]])
    hi = np.array([half, half, z_range[1]])
    if np.any(front < lo) or np.any(front > hi):
        return 0.0
    back = -np.asarray(axis, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(
            back > 0, (hi - front) / back, np.where(back < 0, (lo - front) / back, np.inf)
        )
    return float(t.min())


def check_indenter(spec: PhantomSpec) -> None:
    """Refuse an indenter the phantom cannot image, saying the range that works for this leg and slab.

    The indenter axis (``tilt_deg``) must leave the leg within 30 mm of the tibia centre, its skin point and
    its tip at full depth must lie inside the imaged slab, with at least the pose stage's fluid-column length
    (:data:`deeptissue.pose.checks.LIMITS`, 5 mm) of the fluid's axis inside the image (the pose stage finds the
    indenter's axis from it; a steeper tilt out of the slices leaves less), and ``depth_mm`` must be > 0 and stop short of the tibia and fibula along the axis (of the pre
    state; the rendering checks the moved bones again). It costs milliseconds, so a configuration is
    checked before anything runs.

    Parameters
    ----------
    spec : PhantomSpec

    Raises
    ------
    ValueError
        Naming ``tilt_deg`` or ``depth_mm``, with the range of values that works.
    """
    an = _Anatomy(spec)
    z = _affine(spec)[2, 2] * np.arange(spec.n_slices) + _affine(spec)[2, 3]
    z_lo, z_hi = float(z.min()), float(z.max())
    column = LIMITS["fluid_column_length_mm"].fail

    def inside(tilt) -> bool:
        entry = _indenter_entry(an, spec, tilt)
        if entry is None:
            return False
        axis, skin = entry
        tip = skin + spec.depth_mm * axis
        if not all(z_lo <= p[2] <= z_hi for p in (skin, tip)):
            return False
        return (
            _fluid_in_image(spec, tip - spec.indenter_wall_mm * axis, axis, (z_lo, z_hi)) >= column
        )

    if spec.depth_mm <= 0:
        raise ValueError(
            f"phantom: depth_mm {spec.depth_mm} mm images no indenter (its contrast fluid stays outside "
            "the leg); depth_mm must be > 0"
        )
    if not inside(spec.tilt_deg):
        tilt = [float(t) for t in spec.tilt_deg]
        span = _tilt_x_range(an, spec, inside)
        works = (
            "no tilt about X works with this tilt about Z"
            if span is None
            # rounded toward 0, so both ends shown work
            else f"tilt about X works from {np.trunc(span[0] * 10) / 10:.1f} to "
            f"{np.trunc(span[1] * 10) / 10:.1f} deg (with this tilt about Z and depth)"
        )
        raise ValueError(
            f"phantom: tilt_deg {tilt}: the indenter does not enter the leg with its skin point and tip "
            f"inside the imaged slab (z {z_lo:g} to {z_hi:g} mm) and {column:g} mm of its fluid column in the "
            f"image (the pose stage finds the indenter's axis from it); {works}"
        )
    axis, skin = _indenter_entry(an, spec, spec.tilt_deg)
    reach = _depth_reach(an, spec, axis, skin, np.linspace(z_lo, z_hi, 21))
    if spec.depth_mm >= reach:
        below = np.floor(reach * 100.0) / 100.0
        raise ValueError(
            f"phantom: depth_mm {spec.depth_mm} mm: the indenter touches the tibia or fibula at a depth "
            f"of {reach:.2f} mm; depth_mm works from 0 to below {below:.2f} mm for this leg and tilt"
        )


def _depth_reach(
    an: _Anatomy, spec: PhantomSpec, axis: np.ndarray, skin: np.ndarray, zs: np.ndarray
) -> float:
    """The depth [mm] at which the indenter (a cylinder of ``indenter_radius_mm`` ending in a hemisphere, its tip
    ``depth`` beyond ``skin`` along ``axis``) first touches the moved tibia or fibula, sampled on the bones'
    boundaries at ``zs``; inf if it never does.

    A point at ``a`` along the axis from the skin point and ``rho < R`` from the axis is inside the indenter
    once the depth exceeds ``a + R - sqrt(R² - rho²)``. The bones move about the tibia centre at mid-slab, which
    differs from the rendering's centre of mass by a fraction of a millimetre.
    """
    pts = []
    for z in zs:
        xy = an.tib_boundary(float(z), 120)
        if spec.fibula:
            xy = np.vstack([xy, an.fib_boundary(float(z), 60)])
        pts.append(np.column_stack([xy, np.full(len(xy), z)]))
    pts = np.vstack(pts)
    z_mid = 0.5 * (zs[0] + zs[-1])
    centre = np.array([*an.tib_centre(z_mid), z_mid], float)
    pts = (
        (pts - centre) @ rotation_matrix(spec.bone_rotation_deg).T
        + centre
        + np.asarray(spec.bone_translation_mm)
    )
    rel = pts - skin
    a = rel @ axis
    rho = np.linalg.norm(rel - a[:, None] * axis, axis=1)
    r = spec.indenter_radius_mm
    near = rho < r
    if not near.any():
        return float("inf")
    return float(np.min(a[near] + r - np.sqrt(r * r - rho[near] ** 2)))


def _affine(spec: PhantomSpec) -> np.ndarray:
    dx = spec.fov_mm / spec.n_pixels
    A = np.diag([dx, dx, spec.slice_mm, 1.0])
    A[0, 3] = A[1, 3] = -(spec.n_pixels - 1) / 2 * dx
    A[2, 3] = -(spec.n_slices - 1) / 2 * spec.slice_mm
    return A


#: A bound [mm per mm] of the in-plane gradient of the tibia's, fibula's and indenter's level functions in
#: a slice: ``bone_f``'s gradient in (x, y) and ``fibula_f``'s and ``indenter_sd``'s in 3D are at most 1;
#: 2 leaves room for the slow change of the tibia along z that a moved bone's tilted slice plane picks up.
#: Where one of them is more than this times a distance from a level, it keeps its side of that level
#: within the distance, so it is evaluated only near its boundaries (:meth:`_Scene._sub_levels`,
#: :func:`_level_grid`).
_BONE_LIPSCHITZ = 2.0


def _level_grid(
    fn, x_mm: np.ndarray, y_mm: np.ndarray, *, h_mm: float, stride: int = 8
) -> np.ndarray:
    """A level function ``fn(X, Y)`` (gradient length <= :data:`_BONE_LIPSCHITZ`) on the grid ``x_mm`` ×
    ``y_mm`` (indexing ij, ``h_mm`` apart) for marching squares: ``fn``'s own values wherever its zero set
    may pass, ±1 with its sign elsewhere.

    ``fn`` is evaluated on every ``stride``-th grid line first. A cell of that coarse grid whose four
    corners share a sign and are each more than ``_BONE_LIPSCHITZ · (half its diagonal + h_mm)`` from
    zero keeps that sign at each of its points, more than ``_BONE_LIPSCHITZ · h_mm`` from zero: no grid
    edge from one of them crosses the zero set, so marching squares never interpolates their values and
    the contours are those of ``fn`` on the whole grid. ``fn`` is evaluated at the points of the other
    cells only (about a tenth of the grid around a bone's boundary).
    """
    nx, ny = len(x_mm), len(y_mm)
    ci = np.unique(np.r_[np.arange(0, nx, stride), nx - 1])
    cj = np.unique(np.r_[np.arange(0, ny, stride), ny - 1])
    coarse = fn(*np.meshgrid(x_mm[ci], y_mm[cj], indexing="ij"))
    far = np.abs(coarse) > _BONE_LIPSCHITZ * (stride * h_mm / np.sqrt(2.0) + h_mm)
    pos = coarse > 0
    corners = [(slice(None, -1), slice(None, -1)), (slice(1, None), slice(None, -1))]
    corners += [(slice(None, -1), slice(1, None)), (slice(1, None), slice(1, None))]
    settled = np.logical_and.reduce([far[c] & (pos[c] == pos[corners[0]]) for c in corners])

    def cells(i: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The coarse cell a grid line lies in, and the one before where it is that cell's first line."""
        lo = np.minimum(np.searchsorted(starts, i, side="right") - 1, len(starts) - 2)
        return lo, np.where((starts[lo] == i) & (lo > 0), lo - 1, lo)

    (a_lo, a_hi), (b_lo, b_hi) = cells(np.arange(nx), ci), cells(np.arange(ny), cj)
    exact = np.zeros((nx, ny), bool)
    for a in (a_lo, a_hi):
        for b in (b_lo, b_hi):
            exact |= ~settled[np.ix_(a, b)]
    grid = np.where(pos[:-1, :-1][np.ix_(a_lo, b_lo)], 1.0, -1.0)
    i, j = np.nonzero(exact)
    grid[i, j] = fn(x_mm[i], y_mm[j])
    return grid


class _Scene:
    """Anatomy + indenter + motion: level functions of the pre and during states."""

    def __init__(self, spec: PhantomSpec):
        self.s = spec
        self.an = _Anatomy(spec)
        self.affine = _affine(spec)
        self.z = self.affine[2, 2] * np.arange(spec.n_slices) + self.affine[2, 3]
        an = self.an
        # the tibia's shape must stay a rounded triangle with a cortex and marrow over the slab and
        # the 2 mm beyond it that the moved bone may reach
        z_lo, z_hi = self.z.min() - 2.0, self.z.max() + 2.0
        rounding = an.tib_rounding(np.array([z_lo, z_hi]))
        if rounding.min() < 0.05:
            raise ValueError(
                f"phantom: tibia_rounding_mm / tibia_rounding_slope give a corner rounding of "
                f"{rounding.min():.3g} mm along the slab; keep it >= 0.05 mm"
            )
        # a marrow (the shape scaled by 1 - cortex / inradius) at least 0.15 mm to its sides over the
        # slab and the 1 mm beyond it that a slice of the moved bone can reach (3 deg over 10 mm)
        zs = np.linspace(self.z.min() - 1.0, self.z.max() + 1.0, 41)
        marrow = (
            spec.tibia_inradius_mm * an.tib_scale(zs) * an.tib_side.min()
            - spec.cortex_thickness_mm
        )
        if marrow.min() < 0.15:
            raise ValueError(
                f"phantom: at z = {zs[np.argmin(marrow)]:.3g} mm the tibia is too thin to hold marrow "
                f"inside a {spec.cortex_thickness_mm} mm cortex; reduce tibia_taper or tibia_flare, "
                "or increase tibia_inradius_mm"
            )
        self.tib_rmin, self.tib_rmax = an.tib_radius_range(z_lo, z_hi)
        if spec.fibula:
            self._check_fibula(np.linspace(z_lo, z_hi, 45))
        # tibia centre of mass over the slices (area-weighted slice centroids, as a segmentation sees it)
        ac = [an.tib_area_centroid(float(z)) for z in self.z]
        w = np.array([a for a, _ in ac])
        cxy = np.array([c for _, c in ac])
        self.bone_com = (
            np.array([np.sum(w * cxy[:, 0]), np.sum(w * cxy[:, 1]), np.sum(w * self.z)]) / w.sum()
        )
        self.R = rotation_matrix(spec.bone_rotation_deg)
        self.t = np.asarray(spec.bone_translation_mm, float)
        z0 = spec.indenter_z_mm
        entry = _indenter_entry(an, spec, spec.tilt_deg)
        if entry is None:
            raise ValueError(
                f"phantom: tilt_deg {list(spec.tilt_deg)}: the indenter axis does not leave the leg within "
                "30 mm of the tibia centre (deeptissue.phantom.check_indenter says the range that works)"
            )
        self.axis, self.skin_point = entry
        self.tip_start = self.skin_point - 1.0 * self.axis
        self.tip_end = self.skin_point + spec.depth_mm * self.axis
        self.head_centre = self.tip_end - spec.indenter_radius_mm * self.axis
        # dimple: amplitude and width chosen shallower than the head (see module doc)
        self.dimple_a = 0.9 * spec.depth_mm
        self.dimple_w = np.sqrt(0.75 * max(self.dimple_a, 1e-9) * spec.indenter_radius_mm / 1.5)
        # coil: loop above the anterior skin; normalise to 1 in muscle 1 mm under the entry point
        th = np.linspace(-np.pi, np.pi, 721)
        lcx, lcy = an.leg_centre(z0)
        self.coil_y = float(np.max(lcy + an.leg_r(th, z0) * np.sin(th))) + spec.coil_gap_mm
        self.coil_x = float(lcx)
        ref = self.skin_point + np.array([0.0, -1.0, 0.0])
        self.coil_norm = 1.0 / self._coil_raw(ref[0], ref[1], ref[2])
        if spec.depth_mm > 0:
            gap = self.bone_gap()
            if gap <= 0:
                raise ValueError(
                    f"phantom: the indenter (depth {spec.depth_mm} mm) reaches the tibia; reduce depth_mm"
                )

    def _check_fibula(self, zs: np.ndarray) -> None:
        """The fibula must hold marrow, stay clear of the tibia (two bones in every slice) and inside
        the muscle (clear of the skin layer) over ``zs``; else a ValueError naming the key to change."""
        s, an = self.s, self.an
        if s.fibula_radius_mm <= 0 or s.fibula_converge_mm <= 0:
            raise ValueError("phantom: fibula_radius_mm and fibula_converge_mm must be > 0")
        if an.fib_radius - s.fibula_cortex_mm < 0.08:
            raise ValueError(
                f"phantom: the fibula (radius {an.fib_radius:.3g} mm) is too thin to hold marrow inside a "
                f"{s.fibula_cortex_mm} mm cortex; reduce fibula_cortex_mm or increase fibula_radius_mm"
            )
        for z in zs:
            fx, fy = an.fib_centre(z)
            circ = an.fib_boundary(float(z), 180)
            tb = an.tib_boundary(float(z), 360)
            gap = float(np.min(np.linalg.norm(circ[:, None] - tb[None], axis=-1)))
            inside_tibia = an.bone_f(fx, fy, z) < 0
            if inside_tibia or gap < 0.3:
                raise ValueError(
                    f"phantom: at z = {z:.3g} mm the fibula comes within {gap:.3g} mm of the tibia "
                    "(>= 0.3 mm needed to tell the two bones apart); increase fibula_distal_offset_mm "
                    "or change fibula_angle_deg"
                )
            depth = float(np.max(an.phi_pre(circ[:, 0], circ[:, 1], z)))
            if depth > -(s.skin_thickness_mm + 0.3):
                raise ValueError(
                    f"phantom: at z = {z:.3g} mm the fibula reaches within {-depth:.3g} mm of the skin "
                    f"(>= skin_thickness_mm + 0.3 mm needed); reduce fibula_offset_mm or change "
                    "fibula_angle_deg"
                )

    def _coil_raw(self, x, y, z):
        a = self.s.coil_radius_mm
        d = np.maximum(self.coil_y - y, 0.0)
        return (a * a / (a * a + d * d)) ** 1.5 * np.exp(
            -((x - self.coil_x) ** 2 + z**2) / (2 * 20.0**2)
        )

    def coil(self, x, y, z):
        return self.coil_norm * self._coil_raw(x, y, z)

    def indenter_sd(self, x, y, z):
        """Signed distance (mm) to the indenter (negative inside): ray from the head centre backwards."""
        p = np.stack(
            [
                x - self.head_centre[0],
                y - self.head_centre[1],
                np.broadcast_to(z - self.head_centre[2], np.shape(x)),
            ],
            -1,
        )
        back = -self.axis
        t = np.maximum(p @ back, 0.0)
        q = p - t[..., None] * back
        return np.sqrt((q**2).sum(-1)) - self.s.indenter_radius_mm

    def dimple(self, x, y, z):
        p = np.stack(
            [
                x - self.skin_point[0],
                y - self.skin_point[1],
                np.broadcast_to(z - self.skin_point[2], np.shape(x)),
            ],
            -1,
        )
        s_ax = p @ self.axis
        d2 = (p**2).sum(-1) - s_ax**2
        w_ax = np.exp(-(np.maximum(s_ax, 0.0) ** 2) / (2 * 2.5**2))
        return self.dimple_a * np.exp(-d2 / (2 * self.dimple_w**2)) * w_ax

    def phi(self, x, y, z, state):
        """Level function of the tissue (< 0 inside), mm."""
        ph = self.an.phi_pre(x, y, z)
        if state == "pre" or self.s.depth_mm <= 0:
            return ph
        return np.maximum(ph + self.dimple(x, y, z), -self.indenter_sd(x, y, z))

    def _preimage(self, x, y, z, state):
        """The pre-state point of a point of ``state`` under the bones' rigid motion: q = R^T (x - c - t) + c."""
        if state == "pre":
            return x, y, z
        p = np.stack([x, y, np.broadcast_to(z, np.shape(x))], -1) - self.bone_com - self.t
        q = p @ self.R + self.bone_com
        return q[..., 0], q[..., 1], q[..., 2]

    def bone(self, x, y, z, state, inset=0.0):
        """Level function of the tibia (mm, < 0 inside) in ``state``."""
        return self.an.bone_f(*self._preimage(x, y, z, state), inset)

    def fibula(self, x, y, z, state, inset=0.0):
        """Level function of the fibula (mm, < 0 inside) in ``state``; it moves with the tibia."""
        return self.an.fibula_f(*self._preimage(x, y, z, state), inset)

    def _moved(self, pts):
        """Pre-state points (n, 3) moved by the bones' rigid motion."""
        return (pts - self.bone_com) @ self.R.T + self.bone_com + self.t

    def bone_gap(self) -> float:
        """Smallest distance (mm) from the tibia surface (during) to the indenter, sampled."""
        zs = np.linspace(self.z[0], self.z[-1], 41)
        best = np.inf
        for z in zs:
            xy = self.an.tib_boundary(z, 180)
            if self.s.fibula:
                xy = np.vstack([xy, self.an.fib_boundary(z, 180)])
            pts = self._moved(np.column_stack([xy, np.full(len(xy), z)]))
            best = min(best, float(self.indenter_sd(pts[:, 0], pts[:, 1], pts[:, 2]).min()))
        return best

    # rendering -------------------------------------------------------------------------------
    def _tibia_levels(self, q) -> dict:
        """The tibia's and its marrow's level functions (mm) at the pre-state points ``q`` (x, y, z)."""
        return {
            "fb": self.an.bone_f(*q),
            "fm": self.an.bone_f(*q, self.s.cortex_thickness_mm),
        }

    def _fibula_levels(self, q) -> dict:
        """The fibula's and its marrow's level functions (mm) at the pre-state points ``q`` (x, y, z)."""
        return {
            "ff": self.an.fibula_f(*q),
            "ffm": self.an.fibula_f(*q, self.s.fibula_cortex_mm),
        }

    def _levels(self, X, Y, z, state) -> dict:
        """Every level function (mm, < 0 inside) at the points (X, Y) of slice ``z``: ``phi`` (tissue), ``fb``,
        ``fm`` (tibia, marrow), ``ff``, ``ffm`` (fibula, marrow; with a fibula) and ``sd`` (the indenter's
        signed distance; during, with a depth), each shaped like X."""
        q = self._preimage(X, Y, z, state)
        out = {"phi": self.phi(X, Y, z, state), **self._tibia_levels(q)}
        if self.s.fibula:
            out.update(self._fibula_levels(q))
        if state == "during" and self.s.depth_mm > 0:
            out["sd"] = self.indenter_sd(X, Y, z)
        return out

    def _intensity(self, lv: dict) -> np.ndarray:
        """Intensity without coil at the points of the level functions ``lv`` (:meth:`_levels`)."""
        s = self.s
        phi = lv["phi"]
        val = np.zeros_like(phi)
        tissue = phi < 0
        val[tissue] = s.muscle
        val[tissue & (phi > -s.skin_thickness_mm)] = s.skin
        bone = tissue & (lv["fb"] < 0)
        val[bone] = s.cortex
        val[bone & (lv["fm"] < 0)] = s.marrow
        if "ff" in lv:
            fib = tissue & (lv["ff"] < 0)
            val[fib] = s.cortex
            val[fib & (lv["ffm"] < 0)] = s.marrow
        if "sd" in lv:
            val[lv["sd"] < 0] = s.wall
            val[lv["sd"] < -s.indenter_wall_mm] = s.fluid
        return val

    def _margin(self, lv: dict) -> np.ndarray:
        """A distance-like margin (mm) to the nearest boundary at the points of ``lv`` (:meth:`_levels`):
        ``|bone_f|`` and the others are at most the distance to their zero sets (gradient length <= 1), so
        sub-sampling happens wherever a boundary crosses a pixel."""
        s, phi = self.s, lv["phi"]
        parts = [
            np.abs(phi),
            np.abs(phi + s.skin_thickness_mm),
            np.abs(lv["fb"]),
            np.abs(lv["fm"]),
        ]
        margin = np.minimum.reduce(parts)
        if "ff" in lv:
            margin = np.minimum.reduce([margin, np.abs(lv["ff"]), np.abs(lv["ffm"])])
        if "sd" in lv:
            sd = lv["sd"]
            margin = np.minimum.reduce([margin, np.abs(sd), np.abs(sd + s.indenter_wall_mm)])
        return margin

    def _sub_levels(self, centre: dict, Xs, Ys, z, state) -> dict:
        """The level functions at the sub-samples ``Xs``, ``Ys`` (n, S²) of n pixels whose centres have the
        levels ``centre`` (each (n,)): ``phi`` at every sub-sample; the bones' and the indenter's only in the
        pixels where one of them is within :data:`_BONE_LIPSCHITZ` times half a pixel diagonal of a level
        the intensity compares it with. Elsewhere every sub-sample has the centre's sign against each of
        those levels, and the centre's value stands in for them."""
        s = self.s
        reach = _BONE_LIPSCHITZ * self.affine[0, 0] / np.sqrt(2.0)
        out = {k: np.repeat(v[:, None], Xs.shape[1], axis=1) for k, v in centre.items()}
        out["phi"] = self.phi(Xs, Ys, z, state)

        def near(name: str, level: float = 0.0) -> np.ndarray:
            if name not in centre:
                return np.zeros(len(Xs), bool)
            return np.abs(centre[name] - level) < reach

        for rows, levels in (
            (near("fb") | near("fm"), lambda q: self._tibia_levels(self._preimage(*q, state))),
            (near("ff") | near("ffm"), lambda q: self._fibula_levels(self._preimage(*q, state))),
            (near("sd") | near("sd", -s.indenter_wall_mm), lambda q: {"sd": self.indenter_sd(*q)}),
        ):
            if rows.any():
                for name, value in levels((Xs[rows], Ys[rows], z)).items():
                    out[name][rows] = value
        return out

    def render_slice(self, k: int, state: str) -> np.ndarray:
        """Noise-free magnitude of slice k (n_pixels, n_pixels): sub-sampled where a boundary is near."""
        s = self.s
        n, S = s.n_pixels, s.supersample
        dx = self.affine[0, 0]
        x0 = self.affine[0, 3]
        z = float(self.z[k])
        xc = x0 + np.arange(n) * dx
        XC, YC = np.meshgrid(xc, xc, indexing="ij")  # [i, j] -> x, y
        lv = self._levels(XC, YC, z, state)
        img = self._intensity(lv)
        near = np.nonzero(self._margin(lv) < 1.5 * dx)
        if len(near[0]):
            off = ((np.arange(S) + 0.5) / S - 0.5) * dx
            ox, oy = np.meshgrid(off, off, indexing="ij")
            Xs = XC[near][:, None] + ox.ravel()[None, :]
            Ys = YC[near][:, None] + oy.ravel()[None, :]
            centre = {key: v[near] for key, v in lv.items() if key != "phi"}
            img[near] = self._intensity(self._sub_levels(centre, Xs, Ys, z, state)).mean(axis=1)
        return img * self.coil(XC, YC, z)

    # truth contours --------------------------------------------------------------------------
    def truth_polyline(
        self, k: int, state: str, structure: str, *, h_mm: float = 0.01
    ) -> np.ndarray:
        """Exact boundary (m, 2) in slice k: marching squares of the level function on a fine grid."""
        from skimage.measure import find_contours

        z = float(self.z[k])
        if structure == "skin" and (state == "pre" or self.s.depth_mm <= 0):
            th = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
            cx, cy = self.an.leg_centre(z)
            r = self.an.leg_r(th, z)
            return np.column_stack([cx + r * np.cos(th), cy + r * np.sin(th)])
        if structure == "skin":
            cx, cy = self.an.leg_centre(z)
            half = self.s.leg_radius_mm * 1.4 + 1.0
            fn = lambda X, Y: self.phi(X, Y, z, state)
            h = 3 * h_mm
        elif structure == "bone":
            cx, cy = self.an.tib_centre(z)
            if state == "during":
                cx, cy = self._moved(np.array([[cx, cy, z]]))[0, :2]
            half = self.tib_rmax * 1.3 + 0.5
            fn = lambda X, Y: self.bone(X, Y, z, state)
            h = h_mm
        elif structure == "fibula":
            cx, cy = self.an.fib_centre(z)
            if state == "during":
                cx, cy = self._moved(np.array([[cx, cy, z]]))[0, :2]
            half = self.an.fib_radius * 1.5 + 0.3
            fn = lambda X, Y: self.fibula(X, Y, z, state)
            h = 0.5 * h_mm
        else:
            raise ValueError(f"phantom: unknown structure {structure!r}")
        g = np.arange(-half, half + h / 2, h)
        if structure == "skin":
            F = fn(*np.meshgrid(cx + g, cy + g, indexing="ij"))
        else:
            F = _level_grid(fn, cx + g, cy + g, h_mm=h)
        cs = [c for c in find_contours(F, 0.0) if np.allclose(c[0], c[-1])]
        if not cs:
            raise RuntimeError(f"phantom: no closed {structure} boundary in slice {k} ({state})")
        c = max(cs, key=lambda c: abs(polygon_area_centroid(c)[0]))
        return np.column_stack([cx - half + c[:, 0] * h, cy - half + c[:, 1] * h])


def make_phantom(
    spec: PhantomSpec, *, n_points: int = 100, start_angle_deg: float = 90.0
) -> Phantom:
    """Render the pre and during volumes of ``spec`` and their exact truth.

    Parameters
    ----------
    spec : PhantomSpec
        Anatomy, motion, noise and image grid (seeded: the same spec gives the same phantom).
    n_points : int
        Points per truth contour, resampled as the segmentation does.
    start_angle_deg : float
        Polar angle of each truth contour's first point (:func:`deeptissue.contours.resample_closed`).

    Returns
    -------
    Phantom
        ``pre``/``during`` (n_pixels, n_pixels, n_slices) float32 magnitude images (muscle in the
        well-lit region = 1, Rician noise sigma = 1/snr), ``affine`` (4, 4) RAS mm, ``truth``
        (:class:`~deeptissue.pose.Pose`; ``bone_com_mm`` is the area-weighted mean of the pre
        tibia's slice centroids), ``truth_pre``/``truth_during`` (:class:`~deeptissue.contours.Contours`
        (n_slices, n_points, 3) [mm]; with ``fibula`` contours unless ``spec.fibula`` is False),
        ``noise_sigma`` and ``dense`` exact boundaries per slice.

    Raises
    ------
    ValueError
        For a spec that cannot make a valid phantom (a bone too thin to hold marrow, an indenter
        that reaches the tibia, a fibula within 0.3 mm of the tibia or of the skin layer, ...).
    """
    scene = _Scene(spec)
    rng = np.random.default_rng([spec.seed, 11])
    sigma = 1.0 / spec.snr
    vols, contours, dense = {}, {}, {}
    for state in ("pre", "during"):
        img = np.empty((spec.n_pixels, spec.n_pixels, spec.n_slices), np.float32)
        for k in range(spec.n_slices):
            clean = scene.render_slice(k, state)
            noisy = np.hypot(
                clean + sigma * rng.standard_normal(clean.shape),
                sigma * rng.standard_normal(clean.shape),
            )
            img[:, :, k] = noisy
        vols[state] = img
        out = {}
        for structure in ("skin", "bone", "fibula") if spec.fibula else ("skin", "bone"):
            polys, res = [], []
            for k in range(spec.n_slices):
                poly = scene.truth_polyline(k, state, structure)
                polys.append(np.column_stack([poly, np.full(len(poly), scene.z[k])]))
                xy = resample_closed(poly, n_points=n_points, start_angle_deg=start_angle_deg)
                res.append(np.column_stack([xy, np.full(n_points, scene.z[k])]))
            dense[(state, structure)] = polys
            out[structure] = np.stack(res)
        contours[state] = Contours(skin=out["skin"], bone=out["bone"], fibula=out.get("fibula"))
    truth = Pose(
        indenter_axis=scene.axis,
        tip_start_mm=scene.tip_start,
        tip_end_mm=scene.tip_end,
        depth_mm=spec.depth_mm,
        bone_com_mm=scene.bone_com,
        bone_rotation_deg=np.asarray(spec.bone_rotation_deg, float),
        bone_translation_mm=np.asarray(spec.bone_translation_mm, float),
        extra={
            "skin_point_mm": scene.skin_point.tolist(),
            "indenter_radius_mm": spec.indenter_radius_mm,
            "indenter_wall_mm": spec.indenter_wall_mm,
            "noise_sigma": sigma,
            "bone_indenter_gap_mm": scene.bone_gap() if spec.depth_mm > 0 else None,
        },
    )
    return Phantom(
        spec=spec,
        pre=vols["pre"],
        during=vols["during"],
        affine=scene.affine,
        truth=truth,
        truth_pre=contours["pre"],
        truth_during=contours["during"],
        noise_sigma=sigma,
        dense=dense,
    )


def write_phantom(
    spec: PhantomSpec,
    *,
    pre_path,
    during_path,
    truth_path,
    truth_pre_path,
    truth_during_path,
    n_points: int = 100,
    start_angle_deg: float = 90.0,
) -> Phantom:
    """Make the phantom and write its files, each atomically.

    Parameters
    ----------
    spec : PhantomSpec
        As in :func:`make_phantom`.
    pre_path, during_path : str or Path
        NIfTI volumes.
    truth_path : str or Path
        True pose (:func:`deeptissue.pose.save_pose`, JSON).
    truth_pre_path, truth_during_path : str or Path
        True contours (:func:`deeptissue.contours.save_contours`).
    n_points, start_angle_deg
        As in :func:`make_phantom`.

    Returns
    -------
    Phantom
        What was written.
    """
    from .imaging import write_nifti

    ph = make_phantom(spec, n_points=n_points, start_angle_deg=start_angle_deg)
    write_nifti(pre_path, ph.pre, ph.affine)
    write_nifti(during_path, ph.during, ph.affine)
    save_pose(truth_path, ph.truth)
    save_contours(truth_pre_path, ph.truth_pre)
    save_contours(truth_during_path, ph.truth_during)
    return ph
