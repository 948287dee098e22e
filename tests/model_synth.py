"""Synthetic model-stage inputs: a tapered, wobbly elliptical leg with an eccentric tibia, and a pose.

Shared by the model-stage tests (the imaging and pose stages are not needed to test the model).
"""

from __future__ import annotations

import numpy as np

from deeptissue.contours import Contours
from deeptissue.pose import Pose


def _ring(cx, cy, ax, ay, z, *, n_points, wobble=0.0, phase=0.0, start_deg=90.0):
    """Closed CCW contour starting at ``start_deg`` about its centre (n_points, 3)."""
    t = np.deg2rad(start_deg) + np.linspace(0.0, 2 * np.pi, n_points, endpoint=False)
    r = 1.0 + wobble * np.sin(3 * t + phase) + 0.5 * wobble * np.cos(5 * t - phase)
    return np.stack([cx + ax * r * np.cos(t), cy + ay * r * np.sin(t), np.full_like(t, z)], axis=1)


def leg_contours(
    *,
    n_slices=20,
    n_points=100,
    z0_mm=-9.5,
    dz_mm=1.0,
    skin_axes_mm=(5.5, 4.3),
    taper=0.12,
    wobble=0.03,
    bone_radius_mm=1.1,
    bone_centre_mm=(-0.8, -0.9),
    narrowing=None,
):
    """Skin: ellipses 11 x 8.6 mm at the proximal end, tapering by ``taper`` distally, wobbly.

    Bone: a near-circular tibia of radius ``bone_radius_mm`` (2.2 mm across) off-centre at
    ``bone_centre_mm``. ``narrowing=(z_mm, factor, width_mm)`` multiplies the skin size by
    ``factor`` in a smooth step of ``width_mm`` around ``z_mm`` (a leg that narrows sharply).
    """
    z = z0_mm + dz_mm * np.arange(n_slices)
    u = (z - z.min()) / max(z.max() - z.min(), 1e-9)  # 0 distal -> 1 proximal
    skin, bone = [], []
    for k, zk in enumerate(z):
        s = 1.0 - taper * (1.0 - u[k])
        if narrowing is not None:
            zn, f, w = narrowing
            s *= 1.0 + (f - 1.0) * 0.5 * (1.0 - np.tanh((zk - zn) / w))
        cx, cy = 0.1 * np.sin(0.2 * zk), 0.08 * np.cos(0.15 * zk)
        skin.append(
            _ring(
                cx,
                cy,
                skin_axes_mm[0] * s,
                skin_axes_mm[1] * s,
                zk,
                n_points=n_points,
                wobble=wobble,
                phase=0.3 * k,
            )
        )
        bone.append(
            _ring(
                cx + bone_centre_mm[0],
                cy + bone_centre_mm[1],
                bone_radius_mm,
                0.92 * bone_radius_mm,
                zk,
                n_points=n_points,
                wobble=0.01,
            )
        )
    return Contours(skin=np.array(skin), bone=np.array(bone))


def leg_pose(contours: Contours, *, tilt_deg=4.0, depth_mm=2.0, z_mm=0.0, turn_z_deg=0.0):
    """Indenter from +y into the leg, tilted ``tilt_deg`` about x (and ``turn_z_deg`` about z).

    The tip starts 1 mm before the skin and ends ``depth_mm`` beyond it (skin hit found on the
    linear-in-z interpolation of the contours, close enough for a synthetic pose).
    """
    from deeptissue.rigid import rotation_matrix

    axis = rotation_matrix([tilt_deg, 0.0, turn_z_deg]) @ np.array([0.0, -1.0, 0.0])
    axis /= np.linalg.norm(axis)
    k = int(np.argmin(np.abs(contours.z_mm - z_mm)))
    centre = contours.skin[k].mean(axis=0)
    centre[2] = contours.z_mm[k]
    # march along the line through the slice centre until outside the skin (2D test on nearest slice)
    from matplotlib.path import Path as MplPath

    def inside(p):
        j = int(np.argmin(np.abs(contours.z_mm - p[2])))
        return MplPath(contours.skin[j][:, :2]).contains_point(p[:2])

    s = 0.0
    while inside(centre - s * axis):
        s += 0.01
    skin_hit = centre - s * axis
    return Pose(
        indenter_axis=axis,
        tip_start_mm=skin_hit - 1.0 * axis,
        tip_end_mm=skin_hit + depth_mm * axis,
        depth_mm=depth_mm,
        bone_com_mm=contours.bone.reshape(-1, 3).mean(axis=0),
        bone_rotation_deg=np.zeros(3),
        bone_translation_mm=np.zeros(3),
    )
