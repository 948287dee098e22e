"""Small synthetic inputs with known truth for the pose tests (not a test module itself).

Built independently of :mod:`deeptissue.pose`: a voxelised indenter (fluid-filled capsule) in an
anisotropic grid, a circular leg with a dimple that conforms to the indenter head, and a tapered,
curved, non-circular bone sampled at fixed z planes before and after a known rigid motion.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

SLICE_Z = np.arange(20) - 9.5  # 20 slices of 1 mm, world z [mm]


def grid_affine(*, pixel_mm=0.1, slice_mm=1.0, n_pixels=256):
    """256 x 256 x 20 axial grid centred at the origin (world mm)."""
    A = np.diag([pixel_mm, pixel_mm, slice_mm, 1.0])
    A[:3, 3] = [-(n_pixels - 1) * pixel_mm / 2, -(n_pixels - 1) * pixel_mm / 2, SLICE_Z[0]]
    return A


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def axis_from_tilt(tilt_x_deg, tilt_z_deg, nominal=(0.0, -1.0, 0.0)):
    """Nominal axis (from anterior +y into the leg) tilted about world X, then Z."""
    R = Rotation.from_euler("xz", [tilt_x_deg, tilt_z_deg], degrees=True)
    return unit(R.apply(np.asarray(nominal, float)))


def capsule_sd(p, head, axis, radius):
    """Signed distance [mm] of points p (..., 3) to the capsule: ray from ``head`` backwards along -axis."""
    d = p - head
    s = np.minimum(d @ axis, 0.0)
    return np.linalg.norm(d - s[..., None] * axis, axis=-1) - radius


def indenter_volume(
    *,
    head_mm,
    axis,
    inner_radius_mm=1.2,
    leg_radius_mm=5.0,
    fluid=3.0,
    tissue=1.0,
    subsamples=5,
    blobs=(),
    rng=None,
    noise_sigma=0.0,
):
    """Intensity volume (256, 256, 20) with the fluid of the indenter, a leg disc and bright blobs.

    Partial volume along z: each voxel averages ``subsamples`` planes over its 1 mm thickness.
    ``blobs``: (centre_mm, radius_mm, intensity) bright balls (noise or tissue distractors).
    """
    A = grid_affine()
    n = 256
    x = A[0, 3] + np.arange(n) * A[0, 0]
    y = A[1, 3] + np.arange(n) * A[1, 1]
    X, Y = np.meshgrid(x, y, indexing="ij")
    vol = np.zeros((n, n, len(SLICE_Z)))
    offs = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    for k, z in enumerate(SLICE_Z):
        acc = np.zeros((n, n))
        for dz in offs:
            P = np.stack([X, Y, np.full_like(X, z + dz)], axis=-1)
            img = np.where(X**2 + Y**2 <= leg_radius_mm**2, tissue, 0.0)
            img = np.where(capsule_sd(P, head_mm, axis, inner_radius_mm) <= 0, fluid, img)
            for c, r, val in blobs:
                img = np.where(np.linalg.norm(P - np.asarray(c, float), axis=-1) <= r, val, img)
            acc += img
        vol[:, :, k] = acc / subsamples
    if noise_sigma:
        vol = vol + (rng or np.random.default_rng(0)).normal(0, noise_sigma, vol.shape)
    return vol, A


def leg_skin(
    *, leg_radius_mm=5.0, n_points=100, head_mm=None, axis=None, outer_radius_mm=1.5, drho=0.001
):
    """Skin contours (20, n_points, 3): circles, pushed in where the indenter capsule occupies them."""
    th = np.radians(90.0) + 2 * np.pi * np.arange(n_points) / n_points
    rho = np.arange(leg_radius_mm - 4.0, leg_radius_mm + drho / 2, drho)  # dimples are < 4 mm deep
    out = np.empty((len(SLICE_Z), n_points, 3))
    for k, z in enumerate(SLICE_Z):
        r = np.full(n_points, leg_radius_mm)
        if head_mm is not None:
            P = np.stack(
                [
                    np.cos(th)[:, None] * rho,
                    np.sin(th)[:, None] * rho,
                    np.full((n_points, rho.size), z),
                ],
                -1,
            )
            inside = capsule_sd(P, head_mm, axis, outer_radius_mm) <= 0
            first = np.where(inside.any(axis=1), inside.argmax(axis=1), rho.size - 1)
            r = np.minimum(r, rho[first])
        out[k] = np.column_stack([r * np.cos(th), r * np.sin(th), np.full(n_points, z)])
    return out


def circle_entry(axis, *, aim_mm=(0.0, 0.0, 0.0), leg_radius_mm=5.0):
    """Where the line through ``aim_mm`` along ``axis`` enters the cylinder x^2 + y^2 = R^2 (from -axis side)."""
    a = unit(axis)
    p = np.asarray(aim_mm, float)
    A = a[0] ** 2 + a[1] ** 2
    B = 2 * (p[0] * a[0] + p[1] * a[1])
    C = p[0] ** 2 + p[1] ** 2 - leg_radius_mm**2
    t = (-B - np.sqrt(B * B - 4 * A * C)) / (2 * A)
    return p + t * a


# --- bone -----------------------------------------------------------------------------------


def _bone_body(theta, w):
    """Body-frame bone surface point for polar angle theta and height w (arrays broadcast)."""
    r0 = 1.0 + 0.03 * w + 0.002 * w**2
    r = r0 * (1 + 0.18 * np.cos(2 * theta) + 0.10 * np.cos(3 * (theta - 0.3)))
    cx = 0.6 + 0.03 * w
    cy = -1.0 + 0.004 * w**2
    return np.stack([cx + r * np.cos(theta), cy + r * np.sin(theta), w + 0 * theta], axis=-1)


def prism_body(theta, w):
    """A tibia that is a prism along z (no taper, no bend): its contours cannot show a shift along z."""
    r = 1.0 * (1 + 0.18 * np.cos(2 * theta) + 0.10 * np.cos(3 * (theta - 0.3)))
    return np.stack([0.6 + r * np.cos(theta), -1.0 + r * np.sin(theta), w + 0 * theta], axis=-1)


def fibula_body(theta, w):
    """A thin round bone (radius 0.4 mm) whose centre runs obliquely to the prism: 0.3 mm across the
    slice per mm of z, converging on the tibia distally (-z)."""
    d = 2.8 + 0.3 * w
    u = np.array([np.cos(np.radians(-30.0)), np.sin(np.radians(-30.0))])
    return np.stack(
        [
            0.6 + d * u[0] + 0.4 * np.cos(theta),
            -1.0 + d * u[1] + 0.4 * np.sin(theta),
            w + 0 * theta,
        ],
        axis=-1,
    )


def bone_stack(
    *,
    rotation_deg=(0, 0, 0),
    centre_mm=(0, 0, 0),
    translation_mm=(0, 0, 0),
    n_points=100,
    noise_mm=0.0,
    rng=None,
    body=_bone_body,
):
    """Bone contours (20, n_points, 3) at the fixed slice planes of the bone moved rigidly.

    The moved surface x' = R (x - c) + c + t is cut by each plane z = z_k: for every polar angle the
    body height w is found by Newton iteration so that the moved point lies on the plane. ``body``:
    the surface in the body frame, ``(theta, w) -> (..., 3)`` (default: the tapered, bent bone).
    """
    R = Rotation.from_rotvec(np.radians(rotation_deg)).as_matrix()
    c = np.asarray(centre_mm, float)
    t = np.asarray(translation_mm, float)
    th = np.radians(90.0) + 2 * np.pi * np.arange(n_points) / n_points
    out = np.empty((len(SLICE_Z), n_points, 3))
    for k, z in enumerate(SLICE_Z):
        w = np.full(n_points, z)
        for _ in range(30):
            X = (body(th, w) - c) @ R.T + c + t
            h = 1e-5
            dX = ((body(th, w + h) - c) @ R.T + c + t - X) / h
            w = w - (X[:, 2] - z) / dX[:, 2]
        X = (body(th, w) - c) @ R.T + c + t
        out[k] = X
    if noise_mm:
        rng = rng or np.random.default_rng(0)
        out[..., :2] += rng.normal(0, noise_mm, out[..., :2].shape)
    return out
