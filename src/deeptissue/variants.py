"""Study variants by name: indenter shape and orientation relative to the MRI estimate.

``sphere`` and ``bar`` use the estimated axis; a suffix ``_rx+15`` / ``_rz-15`` (any number of
degrees) turns the axis about the world X or Z axis through the final tip, keeping the travel.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from .rigid import rotation_matrix

__all__ = [
    "MESH_GROUPINGS",
    "Variant",
    "adaptive_turns",
    "mesh_group_of",
    "mesh_groups",
    "parse_variant",
    "solve_priority",
    "turn_base",
    "variant_travel",
]

_NAME = re.compile(r"^(?P<shape>sphere|bar)(?:_r(?P<axis>[xyz])(?P<angle>[+-]\d+(?:\.\d+)?))?$")


@dataclass(frozen=True)
class Variant:
    """A parsed variant name: indenter shape and the turn of its axis about a world axis."""

    name: str
    indenter: str  # "sphere" or "bar"
    turn_axis: str | None = None  # "x", "y" or "z": world axis the indenter axis is turned about
    turn_deg: float = 0.0  # turn angle [deg], right-handed about turn_axis

    def rotation(self) -> np.ndarray:
        """3x3 rotation applied to the estimated indenter axis (identity for no turn)."""
        if self.turn_axis is None:
            return np.eye(3)
        v = np.zeros(3)
        v["xyz".index(self.turn_axis)] = self.turn_deg
        return rotation_matrix(v)


def parse_variant(name: str) -> Variant:
    """Parse a variant name: ``'sphere_rx+15'`` -> Variant(indenter='sphere', turn_axis='x', turn_deg=15.0).

    Parameters
    ----------
    name : str
        ``sphere`` or ``bar``, optionally followed by ``_rx``, ``_ry`` or ``_rz`` and a signed angle in
        degrees (``bar_rz-7.5``).

    Returns
    -------
    Variant
        ``turn_axis`` is None for an unturned name.

    Raises
    ------
    ValueError
        If the name does not match.
    """
    m = _NAME.match(name)
    if not m:
        raise ValueError(
            f"variant {name!r}: expected 'sphere' or 'bar', optionally followed by _rx/_ry/_rz and a signed angle in degrees, e.g. 'sphere_rx+15'"
        )
    angle = float(m["angle"]) if m["angle"] else 0.0
    return Variant(
        name=name, indenter=m["shape"], turn_axis=m["axis"] if m["angle"] else None, turn_deg=angle
    )


def variant_travel(variant: Variant, *, axis, tip_start_mm, tip_end_mm):
    """Indenter axis and start/end tip positions of a variant (world mm).

    The axis is turned about the world axis through the final tip; the travel length stays the same,
    so the start point is the final tip moved back along the turned axis by the travel.

    Parameters
    ----------
    variant : Variant
        From :func:`parse_variant`.
    axis : (3,) array_like
        Estimated indenter axis (direction of travel), need not be unit length.
    tip_start_mm, tip_end_mm : (3,) array_like
        Estimated tip positions before and at full indentation [mm, world].

    Returns
    -------
    axis : (3,) ndarray
        Turned unit axis.
    tip_start_mm, tip_end_mm : (3,) ndarray
        Start and end tip of the variant [mm]; the end tip is ``tip_end_mm`` unchanged.
    """
    axis = np.asarray(axis, float)
    end = np.asarray(tip_end_mm, float)
    travel = float(np.linalg.norm(end - np.asarray(tip_start_mm, float)))
    new_axis = variant.rotation() @ axis
    new_axis /= np.linalg.norm(new_axis)
    return new_axis, end - travel * new_axis, end


MESH_GROUPINGS = ("indenter", "animal")


def mesh_groups(variants, by: str = "animal") -> dict:
    """Which variants share one mesh (config ``model.mesh_groups``).

    ``'animal'`` (the default): one mesh ``'all'`` for every variant. ``'indenter'``: one mesh per
    indenter shape, named after it (``'sphere'``: the sphere in every orientation, refined around all
    their travels, so the orientations are compared on one mesh; ``'bar'``: the bar, refined along its
    sweep), each refined only where its own indenter goes. ``'animal'`` is the default because the
    smaller per-indenter meshes, though faster (on rat02 of config/paper.yaml at 1.6 / 0.8 mm the sphere
    mesh has 34 422 DOFs against 45 633 for the shared one, and its solves take about half the time),
    miss the 1 pp accuracy goal on the bin percentages (docs/performance.md).

    Parameters
    ----------
    variants : iterable of str
        Variant names (:func:`parse_variant`).
    by : {'animal', 'indenter'}
        Grouping, one of :data:`MESH_GROUPINGS`.

    Returns
    -------
    dict
        ``{mesh name: [variant names]}`` in the order of ``variants``.

    Raises
    ------
    ValueError
        For an unknown ``by`` or a bad variant name.
    """
    parsed = [parse_variant(v) for v in variants]
    if by == "animal":
        return {"all": [v.name for v in parsed]}
    if by != "indenter":
        raise ValueError(
            f"config key model.mesh_groups: {by!r}, expected one of {list(MESH_GROUPINGS)}"
        )
    groups: dict = {}
    for v in parsed:
        groups.setdefault(v.indenter, []).append(v.name)
    return groups


def mesh_group_of(variant: str, groups: dict) -> str:
    """The name of the mesh (a key of :func:`mesh_groups`) that ``variant`` is solved on.

    Parameters
    ----------
    variant : str
        Variant name.
    groups : dict
        ``{mesh name: [variant names]}`` from :func:`mesh_groups`.

    Returns
    -------
    str
        The first group that lists ``variant``.

    Raises
    ------
    ValueError
        If no group lists it.
    """
    for g, members in groups.items():
        if variant in members:
            return g
    raise ValueError(f"variant {variant!r} is in no mesh group {groups}")


def turn_base(variant: str, variants, groups: dict | None = None) -> str | None:
    """The variant whose converged end state ``variant`` is solved from (None: solved from the start).

    A turned variant (``sphere_rx+15``) differs from the unturned one of the same shape (``sphere``) only
    by the indenter's axis, turned about the same final tip: if that one is among ``variants`` and on the
    same mesh (``groups``: :func:`mesh_groups`; None: one mesh), the solver turns the indenter from its end
    state (:func:`deeptissue.fem.solver.solve_turned`) instead of indenting from the start.

    Parameters
    ----------
    variant : str
        Variant name.
    variants : iterable of str
        The study's variants.
    groups : dict or None
        ``{mesh name: [variant names]}`` from :func:`mesh_groups`; None: every variant on one mesh.

    Returns
    -------
    str or None
        The unturned variant of the same shape (``'sphere'`` or ``'bar'``), or None for an unturned
        variant (or a turn of 0 deg), a base missing from ``variants`` or a base on another mesh.
    """
    v = parse_variant(variant)
    if v.turn_axis is None or v.turn_deg == 0:
        return None
    base = v.indenter
    if base not in list(variants):
        return None
    if groups is not None and mesh_group_of(base, groups) != mesh_group_of(variant, groups):
        return None
    return base


def adaptive_turns(
    variant: str, variants, turn_from_base: bool = True
) -> tuple[str | None, tuple[str, ...]]:
    """On adaptive meshes, where every variant has meshes of its own: the variant whose passes ``variant``
    rides (its :func:`turn_base`; None: it meshes its own) and the variants among ``variants`` that
    ride the passes of ``variant``; neither without ``turn_from_base`` (config ``study.turn_from_base``)."""
    variants = list(variants)
    if not turn_from_base:
        return None, ()
    turned = tuple(v for v in variants if turn_base(v, variants) == variant)
    return turn_base(variant, variants), turned


def solve_priority(variant: str, depth_mm: float | None = None) -> float:
    """Scheduling priority of the solve job of ``variant`` (higher starts first): the longest solves first.

    A solve cannot be split, so one that starts last runs alone at the end of a study. A bar's solve
    takes several times as long as a sphere's, and a deeper indentation longer than a shallow one, so
    starting bars first and deeper indentations first comes close to the longest-first schedule without
    knowing the solve times in advance.

    Parameters
    ----------
    variant : str
        Variant name (:func:`parse_variant`).
    depth_mm : float or None
        Indentation depth [mm] where it is known before the solve (a phantom's configured
        ``depth_mm``); None counts as 0.

    Returns
    -------
    float
        10 for a bar (any orientation), 0 for a sphere, plus ``depth_mm``.
    """
    v = parse_variant(variant)
    depth = float(depth_mm) if depth_mm is not None else 0.0
    return (10.0 if v.indenter == "bar" else 0.0) + depth
