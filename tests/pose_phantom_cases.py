"""The six digital phantoms behind the pose accuracy numbers of docs/verification.md, and a script that
measures them.

The three demo animals of ``config/config.yaml`` plus three hard cases: tilts of (25, 0), (0, 25)
and (-18, -18) deg, depths 1-3 mm, snr 12, bone rotations up to 3 deg (one of them zero).

Run (about 2-3 min on 2 cores)::

    OMP_NUM_THREADS=1 .venv/bin/python tests/pose_phantom_cases.py [--dof 5|6] [--exact] [--cache DIR] [--extra]
    OMP_NUM_THREADS=1 .venv/bin/python tests/pose_phantom_cases.py --moves --supersample 4 [--cache DIR]

It renders every phantom (``supersample`` 8, as the ``phantom`` rule), segments both states with
Stage 1's ``segment_volume`` (or, with ``--exact``, uses the phantom's exact truth contours), runs
``estimate_pose`` and prints the errors against the phantom truth. With ``--moves`` (about 10 min) it
moves each during scan as ``tests/moved_leg.py`` does (2, 5, 20 pixels in x and y, a turn of 3 deg about
the leg, a tilt of 3 deg out of the slices), segments it again and prints the leg's registration (shift,
turn, far-field skin residual) with the errors of the corrected pose, or the refusal.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

CASES = {
    "rat01": dict(
        seed=1,
        depth_mm=2.0,
        tilt_deg=(5.0, -3.0),
        bone_rotation_deg=(1.0, -0.5, 0.8),
        bone_translation_mm=(0.05, -0.10, 0.02),
        snr=20,
    ),
    "rat02": dict(
        seed=2,
        depth_mm=2.5,
        tilt_deg=(-8.0, 6.0),
        bone_rotation_deg=(-1.5, 0.8, 0.3),
        bone_translation_mm=(-0.08, -0.12, 0.04),
        snr=15,
    ),
    "rat03": dict(
        seed=3,
        depth_mm=1.5,
        tilt_deg=(12.0, 4.0),
        bone_rotation_deg=(0.5, 1.2, -1.0),
        bone_translation_mm=(0.02, -0.06, -0.05),
        snr=25,
    ),
    "tilt25x-shallow": dict(
        seed=4,
        depth_mm=1.0,
        tilt_deg=(25.0, 0.0),
        bone_rotation_deg=(3.0, 0.0, 0.0),
        bone_translation_mm=(0.04, -0.03, 0.15),
        snr=12,
    ),
    "tilt25z-deep": dict(
        seed=5,
        depth_mm=3.0,
        tilt_deg=(0.0, 25.0),
        bone_rotation_deg=(-0.5, 1.0, 2.5),
        bone_translation_mm=(0.03, -0.05, 0.04),
        snr=12,
    ),
    "tilt18-deep-norot": dict(
        seed=6,
        depth_mm=3.0,
        tilt_deg=(-18.0, -18.0),
        bone_translation_mm=(0.05, 0.05, -0.12),
        snr=12,
    ),
}


def extra_cases() -> dict:
    """Eight random phantoms at snr 12 (seeds 7-14): tilts up to 25 deg, depths 1-3 mm, rotations
    0.5-3 deg, translations up to 0.1 mm across the leg and up to 0.15 mm along it."""
    rng = np.random.default_rng(123)
    out = {}
    for seed in range(7, 15):
        rot = rng.uniform(-1, 1, 3)
        rot = rot / np.linalg.norm(rot) * rng.uniform(0.5, 3.0)
        tilt = rng.uniform(-25, 25, 2)
        depth = float(rng.uniform(1, 3))
        tr = rng.uniform(-0.1, 0.1, 3)
        tr[2] *= 1.5  # up to 0.15 mm along the leg
        out[f"extra{seed}"] = dict(
            seed=seed,
            depth_mm=depth,
            tilt_deg=tuple(tilt),
            bone_rotation_deg=tuple(rot),
            bone_translation_mm=tuple(tr),
            snr=12,
        )
    return out


def segmented_contours(
    name: str,
    *,
    supersample: int = 8,
    cache: Path | None = None,
    exact: bool = False,
    spec_extra: dict | None = None,
):
    """(phantom truth Pose, during volume, affine, pre Contours, during Contours) of case ``name``
    (``spec_extra``: further PhantomSpec keys, e.g. ``{"fibula": False}``)."""
    from deeptissue.contours import Contours
    from deeptissue.imaging import Volume
    from deeptissue.phantom import PhantomSpec, make_phantom
    from deeptissue.pose import Pose
    from deeptissue.segment import segment_volume

    tag = "".join(f"_{k}{v}" for k, v in sorted((spec_extra or {}).items()))
    f = (
        None
        if cache is None
        else Path(cache) / f"{name}_ss{supersample}{'_exact' if exact else ''}{tag}.npz"
    )
    if f is not None and f.exists():
        d = np.load(f, allow_pickle=True)
        truth = Pose.from_dict(d["truth"].item())
        fib = {k: (d[k] if k in d.files else None) for k in ("pre_fibula", "dur_fibula")}
        return (
            truth,
            d["during"],
            d["affine"],
            Contours(d["pre_skin"], d["pre_bone"], fib["pre_fibula"]),
            Contours(d["dur_skin"], d["dur_bone"], fib["dur_fibula"]),
        )
    ph = make_phantom(
        PhantomSpec(**{**CASES[name], **(spec_extra or {})}, supersample=supersample)
    )
    if exact:
        pre, dur = ph.truth_pre, ph.truth_during
    else:
        pre, _ = segment_volume(Volume(ph.pre, ph.affine), state="pre")
        dur, _ = segment_volume(Volume(ph.during, ph.affine), state="during")
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        fib = {
            k: v
            for k, v in (("pre_fibula", pre.fibula), ("dur_fibula", dur.fibula))
            if v is not None
        }
        np.savez(
            f,
            truth=np.array(ph.truth.to_dict(), dtype=object),
            during=ph.during,
            affine=ph.affine,
            pre_skin=pre.skin,
            pre_bone=pre.bone,
            dur_skin=dur.skin,
            dur_bone=dur.bone,
            **fib,
        )
    return ph.truth, ph.during, ph.affine, pre, dur


def print_moves(name: str, case: tuple, opts) -> None:
    """One line per move of ``tests/moved_leg.py`` (and the unmoved scan) of case ``name`` =
    (truth, during, affine, pre, during contours): the leg's registration and the pose errors, or the
    refusal."""
    from moved_leg import MOVES, move

    from deeptissue.imaging import Volume
    from deeptissue.pose import estimate_pose, pose_errors
    from deeptissue.pose_error import PoseError
    from deeptissue.segment import SegmentationError, segment_volume

    truth, during, affine, pre, dur = case
    for mv in [None, *MOVES]:
        head = f"{name:18s} {mv or '-':6s}"
        vol = during if mv is None else move(during, affine, mv)
        try:
            dc = dur if mv is None else segment_volume(Volume(vol, affine), state="during")[0]
            pose, _ = estimate_pose(vol, affine, pre, dc, options=opts, animal=name)
        except (PoseError, SegmentationError) as exc:
            print(f"{head} refused: {str(exc)[:110]}", flush=True)
            continue
        e, x = pose_errors(pose, truth), pose.extra
        print(
            f"{head} shift {x['leg_shift_mm']:.4f} turn {x['leg_rotation_deg']:+.3f} "
            f"residual {x['leg_skin_residual_mm']:.4f} | axis {e['axis_error_deg']:.3f} "
            f"tip {e['tip_end_error_mm']:.3f} depth {e['depth_error_mm']:.3f} "
            f"rot {e['bone_rotation_error_deg']:.3f} trans {e['bone_translation_error_mm']:.4f}",
            flush=True,
        )


def main() -> None:
    from deeptissue.pose import PoseOptions, estimate_pose, pose_errors
    from deeptissue.rigid import rotation_matrix

    ap = argparse.ArgumentParser()
    ap.add_argument("--dof", type=int, default=None)
    ap.add_argument("--exact", action="store_true")
    ap.add_argument("--cache", default=None)
    ap.add_argument("--supersample", type=int, default=8)
    ap.add_argument(
        "--extra", action="store_true", help="the eight random phantoms of extra_cases() instead"
    )
    ap.add_argument(
        "--spec",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="a further PhantomSpec key for every case, e.g. --spec fibula=false",
    )
    ap.add_argument(
        "--moves", action="store_true", help="each during scan moved (tests/moved_leg.py) too"
    )
    ap.add_argument("cases", nargs="*")
    a = ap.parse_args()
    import json

    spec_extra = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in a.spec)}
    if a.extra:
        CASES.update(extra_cases())
    names = a.cases or ([n for n in CASES if n.startswith("extra")] if a.extra else list(CASES))
    opts = PoseOptions() if a.dof is None else PoseOptions(bone_dof=a.dof)
    print(
        f"bone_dof {opts.bone_dof}, {'exact' if a.exact else 'segmented'} contours, spec {spec_extra}"
    )
    print(
        ""
        if a.moves
        else f"{'case':20s} {'axis':>6s} {'tip':>6s} {'depth':>6s} {'start':>6s} {'rot':>6s} {'drx':>7s} {'dry':>7s} {'drz':>7s}"
        f" {'trans':>6s} {'dtx':>7s} {'dty':>7s} {'dtz':>7s} {'dof':>3s} {'fib':>5s} {'s':>5s}"
    )
    from deeptissue.segment import SegmentationError

    for name in names:
        t0 = time.time()
        try:
            truth, during, affine, pre, dur = segmented_contours(
                name,
                supersample=a.supersample,
                cache=a.cache,
                exact=a.exact,
                spec_extra=spec_extra,
            )
        except SegmentationError as exc:
            print(f"{name:20s} segmentation failed: {exc}", flush=True)
            continue
        if a.moves:
            print_moves(name, (truth, during, affine, pre, dur), opts)
            continue
        pose, _ = estimate_pose(during, affine, pre, dur, options=opts, animal=name)
        e = pose_errors(pose, truth)
        R = rotation_matrix(pose.bone_rotation_deg)
        t = pose.bone_translation_mm + (R - np.eye(3)) @ (truth.bone_com_mm - pose.bone_com_mm)
        dt = t - truth.bone_translation_mm
        dr = pose.bone_rotation_deg - truth.bone_rotation_deg
        print(
            f"{name:20s} {e['axis_error_deg']:6.3f} {e['tip_end_error_mm']:6.3f} {e['depth_error_mm']:6.3f} "
            f"{e['tip_start_error_mm']:6.3f} {e['bone_rotation_error_deg']:6.3f} {dr[0]:7.3f} {dr[1]:7.3f} {dr[2]:7.3f} "
            f"{e['bone_translation_error_mm']:6.3f} {dt[0]:7.3f} {dt[1]:7.3f} {dt[2]:7.3f} "
            f"{pose.extra.get('bone_dof', '-')!s:>3s} {'/'.join(map(str, pose.extra.get('bone_fibula_slices', [])))!s:>5s} "
            f"{time.time() - t0:5.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
