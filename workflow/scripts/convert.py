"""Glue: read one animal's DICOM series or ParaVision scan; write it as NIfTI with its JSON sidecar."""

from deeptissue.io import script_log
from deeptissue.scanner import read_scan, write_scan

with script_log(snakemake.log[0], "convert"):  # noqa: F821
    vol, meta = read_scan(snakemake.params.spec, base_dir=".", animal=snakemake.wildcards.animal)  # noqa: F821
    write_scan(vol, meta, snakemake.output.nifti, snakemake.output.sidecar)  # noqa: F821
