"""Scanner data in: a DICOM series or a Bruker ParaVision scan read into a :class:`~deeptissue.imaging.Volume`.

DICOM headers are read with pydicom to pick one series and one volume and to check its slices; the
pixels and the voxel-to-world affine come from dcm2niix, the reference DICOM-to-NIfTI converter.
ParaVision scans are read with brkraw, in the patient coordinates ParaVision also exports as DICOM.
Neither geometry is trusted blindly: ``tests/test_scanner.py`` writes a phantom in every orientation
and patient position a scanner writes and requires the same voxels and world coordinates back.

Every refusal is an :class:`~deeptissue.imaging.ImagingError` whose message names the animal and the
folder, lists what the folder holds and names the config key that picks one.
"""

from __future__ import annotations

import json
import re
import subprocess
import tempfile
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import nibabel as nib
import numpy as np

from .imaging import ImagingError, Volume, load_nifti, write_nifti
from .io import atomic_path

__all__ = [
    "GAMMA_BAR_MHZ_PER_T",
    "MIN_SLICES",
    "SLICE_TOL_MM",
    "dicom_series",
    "read_bruker",
    "read_dicom",
    "read_scan",
    "scan_kind",
    "write_scan",
]

#: slice positions must lie this close to an even grid along the slice normal [mm]: the geometry
#: tolerance the converters are tested to (a missing slice is off by a whole spacing)
SLICE_TOL_MM = 0.01
#: a scan needs this many slices: the tibia is chosen from slice to slice along the leg and its motion fitted over
#: slices, which a single slice (a localiser, a 2D scan) cannot give
MIN_SLICES = 3
#: gyromagnetic ratio over 2 pi [MHz/T] of the nuclei a preclinical scanner images (absolute values; CODATA 2018
#: for 1H, the IUPAC table of nuclear properties for the others): the field is the base frequency BF1 over it
GAMMA_BAR_MHZ_PER_T = {
    "1H": 42.577478,
    "2H": 6.535903,
    "3He": 32.434100,
    "13C": 10.708395,
    "15N": 4.316,
    "17O": 5.772,
    "19F": 40.078,
    "23Na": 11.262,
    "31P": 17.235,
    "129Xe": 11.777,
}


def scan_kind(spec: Any, *, base_dir: str | Path = ".") -> str:
    """``"nifti"``, ``"dicom"`` or ``"bruker"``: what an animal's ``pre``/``during`` entry names.

    A string is a NIfTI file or a DICOM folder (a directory); a mapping has a ``dicom`` or a ``bruker`` key.
    """
    if isinstance(spec, dict):
        return "bruker" if "bruker" in spec else "dicom"
    return "dicom" if (Path(base_dir) / str(spec)).is_dir() else "nifti"


def _where(animal: str, folder) -> str:
    return f"animal {animal or '?'}, folder {folder}"


# --- DICOM ---


def _headers(folder: Path, where: str) -> list:
    import pydicom

    out = []
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        try:
            ds = pydicom.dcmread(path, stop_before_pixels=True)
        except Exception:  # not a DICOM file (a DICOMDIR, a note, ...): skipped
            continue
        if "SeriesInstanceUID" in ds and ("PixelData" in ds or "Rows" in ds):
            out.append((path, ds))
    if not out:
        raise ImagingError(f"{where}: no DICOM image files found")
    return out


def _series_table(headers: list) -> dict:
    table: dict[str, list] = defaultdict(list)
    for path, ds in headers:
        table[str(ds.SeriesInstanceUID)].append((path, ds))
    return dict(table)


def dicom_series(folder: str | Path) -> list[dict]:
    """The image series in a DICOM folder (searched recursively), ordered by series number.

    Returns
    -------
    list of dict
        ``series`` (SeriesNumber), ``description`` (SeriesDescription), ``n_files``, ``uid``.
    """
    table = _series_table(_headers(Path(folder), f"folder {folder}"))
    rows = []
    for uid, files in table.items():
        ds = files[0][1]
        rows.append(
            {
                "series": int(getattr(ds, "SeriesNumber", 0) or 0),
                "description": str(getattr(ds, "SeriesDescription", "")),
                "n_files": len(files),
                "uid": uid,
            }
        )
    return sorted(rows, key=lambda r: (r["series"], r["uid"]))


def _pick_series(table: dict, series, where: str) -> list:
    """The files of the series ``series`` picks (SeriesNumber, SeriesDescription or SeriesInstanceUID); the
    listings name a series' UID where its number and description do not tell it from another."""
    rows = {uid: files[0][1] for uid, files in table.items()}

    def name(ds):
        return (getattr(ds, "SeriesNumber", "?"), str(getattr(ds, "SeriesDescription", "")))

    twins = Counter(name(ds) for ds in rows.values())
    listing = "; ".join(
        f"series {name(ds)[0]} {name(ds)[1]!r} ({len(table[uid])} files"
        + (f", uid {uid}" if twins[name(ds)] > 1 else "")
        + ")"
        for uid, ds in sorted(
            rows.items(), key=lambda t: int(getattr(t[1], "SeriesNumber", 0) or 0)
        )
    )
    if series is None:
        if len(table) == 1:
            return next(iter(table.values()))
        raise ImagingError(
            f"{where}: {len(table)} DICOM series ({listing}); pick one with "
            f"{{dicom: <folder>, series: <number or description>}}"
        )
    hits = [
        uid
        for uid, ds in rows.items()
        if (isinstance(series, int) and int(getattr(ds, "SeriesNumber", -1) or -1) == series)
        or (isinstance(series, str) and series in (str(getattr(ds, "SeriesDescription", "")), uid))
    ]
    if len(hits) != 1:
        what = "no" if not hits else f"{len(hits)}"
        hint = (
            "; pick one by its SeriesInstanceUID: {dicom: <folder>, series: '<uid>'}"
            if len(hits) > 1
            else ""
        )
        raise ImagingError(
            f"{where}: {what} DICOM series match series {series!r} ({listing}){hint}"
        )
    return table[hits[0]]


def _check_duplicates(files: list, where: str) -> None:
    """Refuse files that are copies of one image (the same SOPInstanceUID): they would be read as repetitions."""
    by_uid: dict[str, list] = defaultdict(list)
    for path, ds in files:
        by_uid[str(getattr(ds, "SOPInstanceUID", path))].append(path)
    copies = [paths for paths in by_uid.values() if len(paths) > 1]
    if copies:
        shown = "; ".join(" = ".join(p.name for p in paths) for paths in copies[:5])
        raise ImagingError(
            f"{where}: {sum(len(c) - 1 for c in copies)} file(s) are copies of others (the same "
            f"SOPInstanceUID: {shown}{'; ...' if len(copies) > 5 else ''}), not echoes or repetitions; "
            "remove the copies from the folder"
        )


def _check_slab(vol: Volume, where: str) -> None:
    if vol.n_slices < MIN_SLICES:
        raise ImagingError(
            f"{where}: {vol.n_slices} slice(s); the segmentation needs at least {MIN_SLICES} slices "
            "(the tibia is followed from slice to slice): pick the 3D or multi-slice scan of the leg, not a "
            "localiser"
        )


def _volumes(files: list) -> list[list]:
    """The files of a series split into volumes: by echo number, then by repeated slice positions."""

    def num(ds, key):
        v = getattr(ds, key, None)
        return int(v) if v not in (None, "") else 0

    groups: dict[tuple, list] = defaultdict(list)
    for path, ds in files:
        groups[(num(ds, "EchoNumbers"), num(ds, "TemporalPositionIdentifier"))].append((path, ds))
    volumes = []
    for key in sorted(groups):
        members = sorted(groups[key], key=lambda f: num(f[1], "InstanceNumber"))
        seen: Counter = Counter()
        split: dict[int, list] = defaultdict(list)
        for path, ds in members:
            pos = tuple(
                np.round(np.asarray(getattr(ds, "ImagePositionPatient", [0, 0, 0]), float), 3)
            )
            split[seen[pos]].append((path, ds))
            seen[pos] += 1
        volumes.extend(split[n] for n in sorted(split))
    return volumes


def _volume_label(files: list) -> str:
    ds = files[0][1]
    te = getattr(ds, "EchoTime", None)
    return f"echo {getattr(ds, 'EchoNumbers', '?')}, TE {te} ms, {len(files)} slices"


def _frame_attr(frame, shared, seq: str, key: str):
    """``key`` of a multi-frame file's frame, from its own functional group ``seq`` or the shared one."""
    for group in (frame, shared):
        if (
            group is not None
            and seq in group
            and len(group[seq].value)
            and key in group[seq].value[0]
        ):
            return group[seq].value[0][key].value
    return None


def _planes(files: list) -> list:
    """(orientation, position) of every frame: one per classic file, one per frame of a multi-frame file."""
    out = []
    for _, ds in files:
        if (
            int(getattr(ds, "NumberOfFrames", 1) or 1) > 1
            and "PerFrameFunctionalGroupsSequence" in ds
        ):
            shared = (
                ds.SharedFunctionalGroupsSequence[0]
                if "SharedFunctionalGroupsSequence" in ds
                else None
            )
            for frame in ds.PerFrameFunctionalGroupsSequence:
                out.append(
                    (
                        _frame_attr(
                            frame, shared, "PlaneOrientationSequence", "ImageOrientationPatient"
                        ),
                        _frame_attr(
                            frame, shared, "PlanePositionSequence", "ImagePositionPatient"
                        ),
                    )
                )
        else:
            out.append(
                (
                    getattr(ds, "ImageOrientationPatient", None),
                    getattr(ds, "ImagePositionPatient", None),
                )
            )
    return out


def _check_slices(files: list, where: str) -> None:
    """Refuse a volume whose slices are not one evenly spaced stack with one orientation and size.

    Frames of a multi-frame file that share a position (echoes, repetitions) count as one slice.
    """
    shapes = {(int(ds.Rows), int(ds.Columns)) for _, ds in files}
    if len(shapes) > 1:
        raise ImagingError(f"{where}: slices of different sizes {sorted(shapes)} in one series")
    planes = _planes(files)
    if any(o is None or p is None for o, p in planes):
        return  # geometry not in the headers read here: left to the converter and load_nifti's checks
    iop = np.array([np.asarray(o, float) for o, _ in planes])
    if np.abs(iop - iop[0]).max() > 1e-4:
        raise ImagingError(f"{where}: slices with different orientations in one series")
    positions = np.array([np.asarray(p, float) for _, p in planes])
    if len(files) == 1:  # a multi-frame file: its echoes or repetitions repeat each position
        positions = np.unique(np.round(positions, 4), axis=0)
    if len(positions) < 2:
        return
    normal = np.cross(iop[0][:3], iop[0][3:])
    along = positions @ normal
    order = np.argsort(along)
    along, pos = along[order], positions[order]
    gaps = np.diff(along)
    step = float(np.median(gaps))
    if step < SLICE_TOL_MM:
        raise ImagingError(f"{where}: {len(pos)} slices but they repeat at the same position")
    off = np.abs(gaps - step)
    if off.max() > SLICE_TOL_MM:
        k = int(np.argmax(off))
        n_missing = int(round(gaps[k] / step)) - 1
        what = (
            f"{n_missing} slice(s) missing"
            if n_missing >= 1 and abs(gaps[k] - (n_missing + 1) * step) <= SLICE_TOL_MM
            else "unevenly spaced slices"
        )
        raise ImagingError(
            f"{where}: {what}: slice gap {gaps[k]:.4f} mm after slice position {along[k]:.4f} mm "
            f"where the others are {step:.4f} mm"
        )
    inplane = pos - np.outer(along - along[0], normal) - pos[0]
    if np.abs(inplane).max() > SLICE_TOL_MM:
        raise ImagingError(
            f"{where}: slices shifted in-plane from one to the next (a tilted stack), by up to "
            f"{np.abs(inplane).max():.4f} mm"
        )


def _dcm2niix(
    files: list, workdir: Path, where: str, volume: int | None
) -> tuple[Path, int | None]:
    """Convert ``files`` with dcm2niix; return its NIfTI and the volume still to pick inside it.

    dcm2niix writes one file per echo of a multi-frame series (``volume_e1``, ``volume_e2``, ...):
    those are the series' volumes, and ``volume`` picks one.
    """
    import dcm2niix

    src, out = workdir / "in", workdir / "out"
    src.mkdir()
    out.mkdir()
    for n, (path, _) in enumerate(files):
        (src / f"{n:05d}.dcm").symlink_to(Path(path).resolve())
    proc = subprocess.run(
        [dcm2niix.bin, "-z", "n", "-b", "y", "-ba", "y", "-f", "volume", "-o", str(out), str(src)],
        capture_output=True,
        text=True,
    )
    made = sorted(
        out.glob("*.nii"),
        key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)],
    )
    if proc.returncode != 0 or not made:
        tail = (proc.stdout + proc.stderr).strip().splitlines()[-3:]
        raise ImagingError(
            f"{where}: dcm2niix made no NIfTI file (exit {proc.returncode}: {' | '.join(tail)})"
        )
    if len(made) == 1:
        return made[0], volume
    if volume is None or not 1 <= volume <= len(made):
        raise ImagingError(
            f"{where}: dcm2niix splits the series into {len(made)} volumes "
            f"({', '.join(p.stem for p in made)}: echoes or other frame groups); pick one with "
            f"{{dicom: <folder>, volume: <number>}}"
            + ("" if volume is None else f" (volume {volume} does not exist)")
        )
    return made[volume - 1], None


def _select_volume(
    img_path: Path, volume: int | None, workdir: Path, where: str, *, key: str
) -> tuple[Path, int]:
    """A 3D NIfTI: the file itself, or volume ``volume`` (1-based) of a 4D file; refuse 4D without a choice."""
    img = nib.load(str(img_path))
    n = img.shape[3] if len(img.shape) == 4 else 1
    if n == 1:
        if volume not in (None, 1):
            raise ImagingError(f"{where}: volume {volume} asked for, but it holds 1 volume")
        return img_path, 1
    if volume is None or not 1 <= volume <= n:
        raise ImagingError(
            f"{where}: {n} volumes (echoes, repetitions or frames) of shape {tuple(img.shape[:3])}; "
            f"pick one with {key}"
            + ("" if volume is None else f" (volume {volume} does not exist)")
        )
    sub = nib.Nifti1Image(np.asarray(img.dataobj[..., volume - 1], np.float32), img.affine)
    path = workdir / "picked.nii"
    nib.save(sub, str(path))
    return path, volume


def _num(ds, key, scale=1.0):
    v = getattr(ds, key, None)
    try:
        return None if v in (None, "") else float(v) * scale
    except (TypeError, ValueError):
        return None


def read_dicom(
    folder: str | Path,
    *,
    series: int | str | None = None,
    volume: int | None = None,
    animal: str = "",
) -> tuple[Volume, dict]:
    """Read one volume of one DICOM series into a :class:`Volume` (RAS mm) and its scanner metadata.

    Parameters
    ----------
    folder : str or Path
        Folder holding the series' files (searched recursively; non-DICOM files are skipped).
    series : int or str, optional
        SeriesNumber or SeriesDescription of the series to read; needed when the folder holds several.
    volume : int, optional
        1-based volume of a multi-echo or repeated series (ordered by echo number, then time); needed
        when the series holds several.
    animal : str
        Animal name, used in messages only.

    Returns
    -------
    (Volume, dict)
        The volume (``path`` is the folder; voxel axes as :func:`read_scan` says) and its metadata.

    Raises
    ------
    ImagingError
        Several series and none picked, several volumes and none picked, missing or unevenly spaced
        slices, a stack tilted in-plane, or a conversion that does not give one 3D image.
    """
    import dcm2niix
    import pydicom

    folder = Path(folder)
    where = _where(animal, folder)
    if not folder.is_dir():
        raise ImagingError(f"{where}: not a folder")
    files = _pick_series(_series_table(_headers(folder, where)), series, where)
    _check_duplicates(files, where)
    vols = _volumes(files)
    if len(vols) > 1:
        if volume is None or not 1 <= volume <= len(vols):
            listing = "; ".join(f"volume {n}: {_volume_label(v)}" for n, v in enumerate(vols, 1))
            raise ImagingError(
                f"{where}: the series holds {len(vols)} volumes ({listing}); pick one with "
                f"{{dicom: <folder>, volume: <number>}}"
                + ("" if volume is None else f" (volume {volume} does not exist)")
            )
        files, nifti_volume = vols[volume - 1], None
    else:
        files, nifti_volume = vols[0], volume
    _check_slices(files, where)
    ds = files[0][1]
    with tempfile.TemporaryDirectory(prefix="deeptissue_dicom_") as tmp:
        tmp = Path(tmp)
        path, nifti_volume = _dcm2niix(files, tmp, where, nifti_volume)
        path, _ = _select_volume(
            path, nifti_volume, tmp, where, key="{dicom: <folder>, volume: <number>}"
        )
        vol = load_nifti(path, animal=animal)
    vol = _oriented(Volume(data=vol.data, affine=vol.affine, path=str(folder), animal=animal))
    _check_slab(vol, where)
    meta = {
        "kind": "dicom",
        "source": str(folder),
        "series": int(getattr(ds, "SeriesNumber", 0) or 0),
        "series_description": str(getattr(ds, "SeriesDescription", "")),
        "volume": volume or 1,
        "n_files": len(files),
        "converter": "dcm2niix",
        "converter_version": dcm2niix.__version__,
        "header_reader": f"pydicom {pydicom.__version__}",
        "manufacturer": str(getattr(ds, "Manufacturer", "")),
        "field_strength_t": _num(ds, "MagneticFieldStrength"),
        "sequence": " ".join(
            str(getattr(ds, k, "")) for k in ("SequenceName", "ScanningSequence")
        ).strip(),
        "protocol": str(getattr(ds, "ProtocolName", "")),
        "echo_time_ms": _num(ds, "EchoTime"),
        "repetition_time_ms": _num(ds, "RepetitionTime"),
        "patient_position": str(getattr(ds, "PatientPosition", "")),
    }
    return vol, {**meta, **_geometry(vol)}


# --- Bruker ParaVision ---


def _param(obj, key):
    """A ParaVision parameter (or parameter file of a scan/reco) by name; None where it is missing."""
    for get in (lambda: obj[key], lambda: getattr(obj, key)):
        try:
            return get()
        except Exception:  # brkraw raises several types for a missing parameter or file
            continue
    return None


def _scalar(v):
    a = np.ravel(np.asarray(v, dtype=object)) if v is not None else []
    try:
        return float(a[0]) if len(a) else None
    except (TypeError, ValueError):
        return None


def read_bruker(
    study: str | Path, *, scan: int, reco: int = 1, volume: int | None = None, animal: str = ""
) -> tuple[Volume, dict]:
    """Read one reconstruction of one ParaVision scan into a :class:`Volume` (subject RAS mm) and its metadata.

    Parameters
    ----------
    study : str or Path
        The ParaVision study folder (holding ``subject`` and one numbered folder per scan).
    scan, reco : int
        Scan (experiment) number and reconstruction (``pdata``) number; reco 1 is the scanner's own.
    volume : int, optional
        1-based volume of a multi-echo or repeated scan; needed when the scan holds several.
    animal : str
        Animal name, used in messages only.

    Returns
    -------
    (Volume, dict)
        The volume (``path`` is the study folder; voxel axes as :func:`read_scan` says) and its metadata.

    Raises
    ------
    ImagingError
        A scan or reco number that does not exist (the message lists those that do), several slice
        packs, several volumes and none picked, or data that do not make one 3D image.
    """
    import brkraw

    study = Path(study)
    where = _where(animal, study)
    if not study.is_dir():
        raise ImagingError(f"{where}: not a folder")
    try:
        # no converter hooks (plugins) and a fixed rounding of the affine (1e-9 mm): the result does not
        # depend on what else is installed or on a user's brkraw configuration
        loader = brkraw.BrukerLoader(str(study), disable_hook=True, affine_decimals=9)
    except Exception as exc:  # brkraw raises several types for a folder it cannot read
        raise ImagingError(f"{where}: not a readable ParaVision study ({exc})") from exc
    avail = loader.avail
    if scan not in avail:
        listing = "; ".join(
            f"scan {sid} {_scan_label(s)!r} (recos {sorted(s.avail)})" for sid, s in avail.items()
        )
        raise ImagingError(f"{where}: no scan {scan}; the study holds: {listing or 'no scans'}")
    sc = avail[scan]
    if reco not in sc.avail:
        raise ImagingError(
            f"{where}, scan {scan}: no reco {reco}; the scan has recos {sorted(sc.avail)}"
        )
    where = f"{where}, scan {scan}, reco {reco}"
    visu = _param(sc.avail[reco], "visu_pars")
    for key in ("VisuCoreDataSlope", "VisuCoreDataOffs"):
        values = np.ravel(np.asarray(_param(visu, key) if visu is not None else 0.0, float))
        if values.size > 1 and np.ptp(values) > 1e-9 * np.abs(values).max():
            raise ImagingError(
                f"{where}: {key} differs between frames ({values.min():g} to {values.max():g}); brkraw "
                f"{brkraw.__version__} scales all frames by the first, so reconstruct with one scaling "
                f"or export the scan as DICOM"
            )
    try:
        # patient coordinates as ParaVision writes them (and exports to DICOM): a quadruped's anatomical
        # frame would turn the bore axis, along which the leg's slices are stacked, into y
        img = loader.convert(scan, reco, override_subject_type="Biped")
    except Exception as exc:  # brkraw raises several types for data it cannot shape
        raise ImagingError(f"{where}: brkraw cannot convert the scan ({exc})") from exc
    if isinstance(img, tuple):
        if len(img) != 1:
            raise ImagingError(
                f"{where}: {len(img)} slice packs; export the one with the leg as its own scan"
            )
        img = img[0]
    with tempfile.TemporaryDirectory(prefix="deeptissue_bruker_") as tmp:
        tmp = Path(tmp)
        raw = tmp / "scan.nii"
        if img.ndim > 4:
            img = nib.Nifti1Image(
                np.asarray(img.dataobj).reshape(*img.shape[:3], -1), img.affine, img.header
            )
        nib.save(
            img, str(raw)
        )  # saved and read back: nibabel applies the header's slope and offset
        path, picked = _select_volume(
            raw,
            volume,
            tmp,
            where,
            key="{bruker: <study>, scan: <n>, reco: <m>, volume: <number>}",
        )
        vol = load_nifti(path, animal=animal)
    vol = _oriented(Volume(data=vol.data, affine=vol.affine, path=str(study), animal=animal))
    _check_slab(vol, where)
    method = _param(sc, "method")
    acqp = _param(sc, "acqp")
    bf1 = _scalar(_param(acqp, "BF1")) if acqp is not None else None
    nucleus = _nucleus(acqp, method)
    meta = {
        "kind": "bruker",
        "source": str(study),
        "scan": scan,
        "reco": reco,
        "volume": picked,
        "converter": "brkraw",
        "converter_version": brkraw.__version__,
        "paravision_version": loader.sw_version,
        "subject": f"{_param(visu, 'VisuSubjectType')} {_param(visu, 'VisuSubjectPosition')}",
        "nucleus": nucleus,
        "field_strength_t": None
        if bf1 is None or nucleus not in GAMMA_BAR_MHZ_PER_T
        else round(bf1 / GAMMA_BAR_MHZ_PER_T[nucleus], 3),  # Larmor frequency / gamma-bar
        "sequence": str(_param(method, "Method") or "") if method is not None else "",
        "protocol": _scan_label(sc),
        "echo_time_ms": _echo_time_ms(visu, method, picked),
        "repetition_time_ms": _scalar(_param(method, "PVM_RepetitionTime"))
        if method is not None
        else None,
    }
    return vol, {**meta, **_geometry(vol)}


def _nucleus(acqp, method) -> str:
    """The imaged nucleus (``1H``, ``13C``, ...): acqp NUCLEUS1, else the method's PVM_Nucleus1, else 1H."""
    for obj, key in ((acqp, "NUCLEUS1"), (method, "PVM_Nucleus1")):
        v = _param(obj, key) if obj is not None else None
        if v is not None:
            text = str(np.ravel(np.asarray(v, dtype=object))[0]).strip("<> ")
            if text:
                return text
    return "1H"


def _echo_time_ms(visu, method, volume: int) -> float | None:
    """The echo time of the chosen volume: VisuAcqEchoTime per echo, else the method's PVM_EchoTime [ms]."""
    per_echo = _param(visu, "VisuAcqEchoTime") if visu is not None else None
    values = np.ravel(np.asarray(per_echo, float)) if per_echo is not None else np.zeros(0)
    if values.size:
        return float(values[min(volume, values.size) - 1])
    return _scalar(_param(method, "PVM_EchoTime")) if method is not None else None


def _scan_label(sc) -> str:
    for name, key in (
        ("acqp", "ACQ_protocol_name"),
        ("acqp", "ACQ_scan_name"),
        ("method", "Method"),
    ):
        try:
            v = getattr(sc, name)[key]
        except Exception:
            continue
        if v is not None:
            return str(v).strip("<>")
    return ""


# --- any input ---


def _oriented(vol: Volume) -> Volume:
    """The same voxels with the in-plane axes ordered and every axis flipped toward +x, +y, +z world; slices stay third.

    Converters keep the order a scanner stored (rows top to bottom, slices in acquisition order); this
    fixed order makes a scan and its NIfTI twin the same array, while the slice axis stays the third
    axis that later stages read slices along.
    """
    data, affine = vol.data, vol.affine.copy()
    dominant = np.argmax(np.abs(affine[:3, :2]), axis=0)
    if dominant[0] > dominant[1]:
        data = np.swapaxes(data, 0, 1)
        affine[:, [0, 1]] = affine[:, [1, 0]]
    for ax in range(3):
        col = affine[:3, ax]
        if col[np.argmax(np.abs(col))] < 0:
            data = np.flip(data, axis=ax)
            affine[:3, 3] += col * (data.shape[ax] - 1)
            affine[:3, ax] = -col
    return Volume(data=np.ascontiguousarray(data), affine=affine, path=vol.path, animal=vol.animal)


def _geometry(vol: Volume) -> dict:
    return {
        "shape": list(vol.data.shape),
        "voxel_mm": [round(float(v), 6) for v in np.linalg.norm(vol.affine[:3, :3], axis=0)],
        "orientation": "".join(nib.aff2axcodes(vol.affine)),
        "affine": np.round(vol.affine, 6).tolist(),
    }


def read_scan(
    spec: str | dict, *, base_dir: str | Path = ".", animal: str = ""
) -> tuple[Volume, dict]:
    """Read an animal's ``pre`` or ``during`` entry, whatever its kind, into a :class:`Volume` and metadata.

    Parameters
    ----------
    spec : str or dict
        A NIfTI file or a DICOM folder (path), ``{dicom: folder, series: .., volume: ..}`` or
        ``{bruker: study folder, scan: n, reco: m, volume: ..}``; paths relative to ``base_dir``.
    base_dir : str or Path
        Directory the paths are relative to (the workflow directory).
    animal : str
        Animal name, used in messages only.

    Returns
    -------
    (Volume, dict)
        The volume (affine to RAS mm). Scanner data keep the acquired slice axis third, with the in-plane
        axes ordered and all axes flipped toward +x, +y, +z world (an axial scan reads as RAS, like a NIfTI
        twin); a NIfTI file is read as it is. Metadata: ``kind``, ``source``, ``converter`` and
        ``converter_version``, ``field_strength_t``, ``sequence``, ``echo_time_ms``,
        ``repetition_time_ms`` (None where the data do not say), ``shape``, ``voxel_mm``,
        ``orientation`` (nibabel axis codes of the voxel axes, e.g. ``RAS``) and ``affine``.
    """
    base = Path(base_dir)
    kind = scan_kind(spec, base_dir=base)
    if kind == "bruker":
        return read_bruker(
            base / spec["bruker"],
            scan=int(spec["scan"]),
            reco=int(spec.get("reco", 1)),
            volume=spec.get("volume"),
            animal=animal,
        )
    if kind == "dicom":
        folder = spec["dicom"] if isinstance(spec, dict) else spec
        opts = spec if isinstance(spec, dict) else {}
        return read_dicom(
            base / folder, series=opts.get("series"), volume=opts.get("volume"), animal=animal
        )
    vol = load_nifti(base / spec, animal=animal)
    meta = {
        "kind": "nifti",
        "source": str(spec),
        "converter": "nibabel",
        "converter_version": nib.__version__,
        "field_strength_t": None,
        "sequence": "",
        "echo_time_ms": None,
        "repetition_time_ms": None,
    }
    return vol, {**meta, **_geometry(vol)}


def write_scan(vol: Volume, meta: dict, nifti_path: str | Path, json_path: str | Path) -> None:
    """Write the volume as NIfTI (float32, qform and sform set) and its metadata as a JSON sidecar, atomically."""
    write_nifti(nifti_path, vol.data, vol.affine)
    with atomic_path(json_path) as tmp:
        Path(tmp).write_text(json.dumps(meta, indent=2) + "\n")
