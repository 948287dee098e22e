"""A volume written as a classic MR DICOM series with pydicom, in the geometry a scanner writes it.

The writer knows nothing of the reader under test: a voxel (i, j, k) of ``data`` with the RAS
``affine`` becomes column i, row j of the file whose ImagePositionPatient is the LPS position of
(0, 0, k). DICOM stores integers, so the data are quantised with one RescaleSlope for the series;
:func:`quantised` is what a reader must give back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid
from pydicom.valuerep import format_number_as_ds

MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4"
LPS = np.diag([-1.0, -1.0, 1.0])  # RAS <-> DICOM patient coordinates (LPS)
LEVELS = 4000  # integer levels of the data's maximum


def slope_of(data: np.ndarray) -> float:
    """The RescaleSlope that maps the integer levels to the data's values."""
    return float(np.max(data)) / LEVELS


def _ds(value) -> str:
    """A number as a DICOM decimal string at the most precision its 16 characters hold."""
    return format_number_as_ds(float(value))


def quantised(data: np.ndarray) -> np.ndarray:
    """The values a DICOM series of ``data`` holds (integer levels times the slope), float32."""
    s = slope_of(data)
    return (np.round(np.asarray(data, float) / s) * s).astype(np.float32)


def reorder(data: np.ndarray, affine: np.ndarray, *, perm=(0, 1, 2), flip=(False, False, False)):
    """The same voxels in another index order: axes permuted, then flipped; world coordinates unchanged."""
    d = np.transpose(data, perm)
    a = np.asarray(affine, float)[:, list(perm) + [3]].copy()
    for ax, f in enumerate(flip):
        if f:
            n = d.shape[ax]
            d = np.flip(d, axis=ax)
            a[:3, 3] = a[:3, 3] + a[:3, ax] * (n - 1)
            a[:3, ax] = -a[:3, ax]
    return np.ascontiguousarray(d), a


def rotated(affine: np.ndarray, angles_deg) -> np.ndarray:
    """The affine turned about the world origin by rotations about x, y, z (deg): an oblique acquisition."""
    ax, ay, az = np.deg2rad(angles_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    out = np.asarray(affine, float).copy()
    out[:3] = (rz @ ry @ rx) @ out[:3]
    return out


def _new_instance(sop_class_uid: str) -> Dataset:
    """An empty SOP instance of that class with its file meta (explicit VR little endian) and a new UID."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class_uid
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class_uid
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    return ds


def write_series(
    folder,
    data: np.ndarray,
    affine: np.ndarray,
    *,
    patient_position: str = "HFS",
    series_number: int = 1,
    description: str = "T2 RARE",
    echo_time_ms: float = 12.0,
    echo_number: int = 1,
    repetition_time_ms: float = 2500.0,
    study_uid: str | None = None,
    series_uid: str | None = None,
    slices=None,
    instance_start: int = 1,
    temporal_position: int | None = None,
    name: str = "IM",
    slope: float | None = None,
) -> list[Path]:
    """Write ``data`` (ni, nj, nk) with its RAS ``affine`` as one file per slice into ``folder``.

    ``slices`` picks (and orders) the slices written (default all, in order k = 0..nk-1); files are
    named ``{name}{series_number}_{instance}.dcm``; ``slope`` defaults to :func:`slope_of`. Returns
    the paths written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    data = np.asarray(data, float)
    slope = slope or slope_of(data)
    levels = np.round(data / slope).astype(np.uint16)
    lps = LPS @ np.asarray(affine, float)[:3]
    row_dir = lps[:, 0] / np.linalg.norm(lps[:, 0])  # along a row: column index i grows
    col_dir = lps[:, 1] / np.linalg.norm(lps[:, 1])  # down a column: row index j grows
    study_uid = study_uid or generate_uid()
    series_uid = series_uid or generate_uid()
    frame_uid = generate_uid()
    ks = list(range(data.shape[2])) if slices is None else list(slices)
    paths = []
    for n, k in enumerate(ks):
        ds = _new_instance(MR_IMAGE_STORAGE)
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.FrameOfReferenceUID = frame_uid
        ds.Modality = "MR"
        ds.Manufacturer = "Bruker BioSpin MRI GmbH"
        ds.PatientName = "phantom"
        ds.PatientID = "phantom"
        ds.PatientPosition = patient_position
        ds.StudyDate = ds.SeriesDate = ds.AcquisitionDate = "20260101"
        ds.StudyTime = ds.SeriesTime = "120000"
        ds.AcquisitionTime = f"12{series_number % 60:02d}00"
        ds.StudyID = "1"
        ds.SeriesNumber = series_number
        ds.AcquisitionNumber = 1
        ds.InstanceNumber = instance_start + n
        ds.SeriesDescription = description
        ds.ProtocolName = description
        ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "NONE"]
        ds.ScanningSequence = "SE"
        ds.SequenceVariant = "NONE"
        ds.SequenceName = "RARE"
        ds.MRAcquisitionType = "2D"
        ds.MagneticFieldStrength = 7.0
        ds.ImagingFrequency = 300.3
        ds.EchoTime = echo_time_ms
        ds.EchoNumbers = echo_number
        ds.RepetitionTime = repetition_time_ms
        if temporal_position is not None:
            ds.TemporalPositionIdentifier = temporal_position
            ds.NumberOfTemporalPositions = 2
        ds.ImagePositionPatient = [_ds(v) for v in lps @ np.array([0.0, 0.0, k, 1.0])]
        ds.ImageOrientationPatient = [_ds(v) for v in (*row_dir, *col_dir)]
        ds.PixelSpacing = [_ds(np.linalg.norm(lps[:, 1])), _ds(np.linalg.norm(lps[:, 0]))]
        ds.SliceThickness = _ds(np.linalg.norm(lps[:, 2]))
        ds.SpacingBetweenSlices = _ds(np.linalg.norm(lps[:, 2]))
        ds.SliceLocation = _ds(
            np.dot(np.cross(row_dir, col_dir), lps @ np.array([0.0, 0.0, k, 1.0]))
        )
        ds.Rows, ds.Columns = data.shape[1], data.shape[0]
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.RescaleSlope = _ds(slope)
        ds.RescaleIntercept = "0"
        ds.PixelData = np.ascontiguousarray(levels[:, :, k].T).tobytes()
        path = folder / f"{name}{series_number}_{instance_start + n:04d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths


def _jcamp(path: Path, params: dict) -> None:
    """A JCAMP-DX parameter file as ParaVision writes them: ``##$Key=value``, arrays as ``( n )`` then values."""
    lines = [
        "##TITLE=Parameter List, ParaVision 6.0.1",
        "##JCAMPDX=4.24",
        "##DATATYPE=Parameter Values",
    ]
    for key, value in params.items():
        if isinstance(value, np.ndarray):
            dims = ", ".join(str(n) for n in value.shape)
            lines += [
                f"##${key}=( {dims} )",
                " ".join(
                    repr(float(v)) if value.dtype.kind == "f" else str(v) for v in value.ravel()
                ),
            ]
        elif isinstance(value, tuple):  # (shape, text): a structured value written as is
            lines += [f"##${key}=( {value[0]} )", value[1]]
        else:
            lines.append(f"##${key}={value}")
    lines.append("##END=")
    path.write_text("\n".join(lines) + "\n")


def write_paravision(
    study,
    scan: int,
    data: np.ndarray,
    affine: np.ndarray,
    *,
    reco: int = 1,
    subject_position: str = "Head_Prone",
    subject_type: str = "Quadruped",
    protocol: str = "T2_TurboRARE",
    echo_time_ms: float = 12.0,
    repetition_time_ms: float = 2500.0,
    slope: float | None = None,
    nucleus: str = "1H",
    bf1_mhz: float = 300.300,
) -> Path:
    """Write ``data`` (ni, nj, nk) with its RAS ``affine`` as scan ``scan`` / reco ``reco`` of a ParaVision study.

    ``data`` (ni, nj, nk, ne) is a multi-echo scan: frames in echo-fastest order, an FG_ECHO frame group
    before FG_SLICE, positions per slice.

    The layout is the one brkraw discovers (``<scan>/method``, ``acqp``, ``pdata/<reco>/2dseq``,
    ``visu_pars``, ``reco``); ``VisuCoreOrientation`` holds the row, column and slice direction
    cosines and ``VisuCorePosition`` the first voxel of each slice, in the LPS patient coordinates
    that ParaVision also exports as DICOM ImageOrientationPatient / ImagePositionPatient. The
    2dseq is int16 in Fortran order (i fastest) with one slope for all frames (default :func:`slope_of`).
    ``nucleus`` and ``bf1_mhz`` are the imaged nucleus and the base frequency of acqp (1H at 7.05 T by default).
    """
    study = Path(study)
    scan_dir = study / str(scan)
    reco_dir = scan_dir / "pdata" / str(reco)
    reco_dir.mkdir(parents=True, exist_ok=True)
    (study / "subject").write_text(
        "##TITLE=Parameter List, ParaVision 6.0.1\n##JCAMPDX=4.24\n##$SUBJECT_id=<phantom>\n##END=\n"
    )
    data = np.asarray(data, float)
    ne = data.shape[3] if data.ndim == 4 else 1
    ni, nj, nk = data.shape[:3]
    slope = slope or slope_of(data)
    levels = np.round(data / slope).astype("<i2").reshape(ni, nj, nk, ne)
    lps = LPS @ np.asarray(affine, float)[:3]
    dirs = lps[:, :3] / np.linalg.norm(lps[:, :3], axis=0)
    step = np.linalg.norm(lps[:, :3], axis=0)
    orient = np.tile(dirs.T.ravel(), (nk, 1))
    pos = np.array([lps @ np.array([0.0, 0.0, k, 1.0]) for k in range(nk)])
    _jcamp(
        scan_dir / "acqp",
        {
            "ACQ_protocol_name": ("64", f"<{protocol}>"),
            "ACQ_scan_name": ("64", f"<{protocol}>"),
            "BF1": bf1_mhz,
            "NUCLEUS1": f"<{nucleus}>",
            "BYTORDA": "little",
            "ACQ_word_size": "_32_BIT",
            "ACQ_scaling_phase": 1,
            "ACQ_dim": 2,
        },
    )
    _jcamp(
        scan_dir / "method",
        {
            "Method": "<Bruker:RARE>",
            "PVM_EchoTime": echo_time_ms,
            "PVM_RepetitionTime": repetition_time_ms,
            "PVM_NSPacks": 1,
            "PVM_SPackArrNSlices": np.array([nk]),
            "PVM_SPackArrSliceDistance": np.array([float(step[2])]),
            "PVM_SPackArrSliceGap": np.array([0.0]),
            "PVM_SPackArrSliceOrient": ("1", "axial"),
            "PVM_ObjOrderScheme": "Interlaced",
        },
    )
    _jcamp(
        reco_dir / "reco", {"RECO_wordtype": "_16BIT_SGN_INT", "RECO_byte_order": "littleEndian"}
    )
    _jcamp(
        reco_dir / "visu_pars",
        {
            "VisuCoreFrameCount": nk * ne,
            "VisuCoreDim": 2,
            "VisuCoreSize": np.array([ni, nj]),
            "VisuCoreDimDesc": ("2", "spatial spatial"),
            "VisuCoreExtent": np.array([float(step[0] * ni), float(step[1] * nj)]),
            "VisuCoreFrameThickness": np.array([float(step[2])]),
            "VisuCoreUnits": ("2, 65", "<mm> <mm>"),
            "VisuCoreOrientation": orient,
            "VisuCorePosition": pos,
            "VisuCoreDataMin": np.zeros(nk * ne),
            "VisuCoreDataMax": np.full(nk * ne, levels.max() * slope),
            "VisuCoreDataOffs": np.zeros(nk * ne),
            "VisuCoreDataSlope": np.full(nk * ne, slope),
            "VisuCoreFrameType": "MAGNITUDE_IMAGE",
            "VisuCoreWordType": "_16BIT_SGN_INT",
            "VisuCoreByteOrder": "littleEndian",
            "VisuFGOrderDescDim": 1 if ne == 1 else 2,
            "VisuFGOrderDesc": ("1", f"({nk}, <FG_SLICE>, <>, 0, 2)")
            if ne == 1
            else ("2", f"({ne}, <FG_ECHO>, <>, 0, 0) ({nk}, <FG_SLICE>, <>, 0, 2)"),
            "VisuGroupDepVals": ("2", "(<VisuCoreOrientation>, 0) (<VisuCorePosition>, 0)"),
            "VisuSubjectPosition": subject_position,
            "VisuSubjectType": subject_type,
            "VisuAcqEchoTime": echo_time_ms * np.arange(1.0, ne + 1),
            "VisuAcqRepetitionTime": np.array([repetition_time_ms]),
            "VisuMagneticFieldStrength": 7.0,
            "VisuCreatorVersion": "<6.0.1>",
            "VisuCoreVersion": 5,
        },
    )
    (reco_dir / "2dseq").write_bytes(levels.transpose(0, 1, 3, 2).tobytes(order="F"))
    return study


ENHANCED_MR_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.4.1"


def write_enhanced(
    path,
    data: np.ndarray,
    affine: np.ndarray,
    *,
    echo_times_ms=(12.0,),
    series_number: int = 1,
    description: str = "T2 RARE",
    slope: float | None = None,
    skip_slices=(),
) -> Path:
    """Write ``data`` (ni, nj, nk) or (ni, nj, nk, ne echoes) as one enhanced (multi-frame) MR DICOM file.

    One frame per slice and echo (echo fastest), each with its PlanePositionSequence, the orientation
    and pixel measures shared, and an MREchoSequence per frame; one RescaleSlope for all frames.
    ``skip_slices`` leaves those slices' frames out (a stack with a gap).
    """
    from pydicom.sequence import Sequence

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.asarray(data, float)
    ne = data.shape[3] if data.ndim == 4 else 1
    ni, nj, nk = data.shape[:3]
    data = data.reshape(ni, nj, nk, ne)
    slope = slope or slope_of(data)
    levels = np.round(data / slope).astype(np.uint16)
    lps = LPS @ np.asarray(affine, float)[:3]
    row_dir = lps[:, 0] / np.linalg.norm(lps[:, 0])
    col_dir = lps[:, 1] / np.linalg.norm(lps[:, 1])
    ds = _new_instance(ENHANCED_MR_IMAGE_STORAGE)
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = (
        generate_uid(),
        generate_uid(),
        generate_uid(),
    )
    ds.Modality, ds.Manufacturer = "MR", "Bruker BioSpin MRI GmbH"
    ds.PatientName = ds.PatientID = "phantom"
    ds.PatientPosition = "HFS"
    ds.StudyDate = ds.SeriesDate = ds.AcquisitionDate = ds.ContentDate = "20260101"
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = "120000"
    ds.AcquisitionDateTime = "20260101120000"
    ds.SeriesNumber, ds.InstanceNumber = series_number, 1
    ds.SeriesDescription = ds.ProtocolName = description
    ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "NONE"]
    ds.MagneticFieldStrength = 7.0
    ds.RepetitionTime = 2500.0
    ds.Rows, ds.Columns = nj, ni
    ds.NumberOfFrames = (nk - len(skip_slices)) * ne
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    shared = Dataset()
    measures = Dataset()
    measures.PixelSpacing = [_ds(np.linalg.norm(lps[:, 1])), _ds(np.linalg.norm(lps[:, 0]))]
    measures.SliceThickness = _ds(np.linalg.norm(lps[:, 2]))
    measures.SpacingBetweenSlices = _ds(np.linalg.norm(lps[:, 2]))
    shared.PixelMeasuresSequence = Sequence([measures])
    orient = Dataset()
    orient.ImageOrientationPatient = [_ds(v) for v in (*row_dir, *col_dir)]
    shared.PlaneOrientationSequence = Sequence([orient])
    scale = Dataset()
    scale.RescaleSlope, scale.RescaleIntercept, scale.RescaleType = _ds(slope), "0", "US"
    shared.PixelValueTransformationSequence = Sequence([scale])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    dims = []
    for pointer, group in (
        (0x00189082, 0x00189114),
        (0x00209057, 0x00209111),
    ):  # echo time (MR echo), stack position
        dim = Dataset()
        dim.DimensionIndexPointer = pointer
        dim.FunctionalGroupPointer = group
        dims.append(dim)
    ds.DimensionIndexSequence = Sequence(dims)
    frames, pixels = [], []
    for k in (k for k in range(nk) if k not in skip_slices):
        for e in range(ne):
            fr = Dataset()
            pos = Dataset()
            pos.ImagePositionPatient = [_ds(v) for v in lps @ np.array([0.0, 0.0, k, 1.0])]
            fr.PlanePositionSequence = Sequence([pos])
            echo = Dataset()
            echo.EffectiveEchoTime = float(echo_times_ms[e])
            fr.MREchoSequence = Sequence([echo])
            content = Dataset()
            content.InStackPositionNumber = k + 1
            content.StackID = "1"
            content.DimensionIndexValues = [e + 1, k + 1]
            content.TemporalPositionIndex = 1
            fr.FrameContentSequence = Sequence([content])
            frames.append(fr)
            pixels.append(levels[:, :, k, e].T)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelData = np.ascontiguousarray(np.stack(pixels)).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path
