"""Glue: segment skin, tibia and fibula on every slice of one state; write contours, checks and the QC figure."""

from deeptissue.io import script_log
from deeptissue.segment import SegmentJob, segment_files

with script_log(snakemake.log[0], "segment"):  # noqa: F821
    inp = snakemake.input  # noqa: F821
    out = snakemake.output  # noqa: F821
    p = snakemake.params  # noqa: F821
    segment_files(
        SegmentJob(
            image=inp.image,
            contours_out=out.contours,
            qc_out=out.qc,
            checks_out=out.checks,
            animal=snakemake.wildcards.animal,  # noqa: F821
            state=snakemake.wildcards.state,  # noqa: F821
            settings=p.settings,
            crop_mm=p.crop_mm,
            leg_point_mm=p.leg_point_mm,
            reference=inp.get("reference"),
            overrides=inp.get("overrides"),
            truth=inp.get("truth"),
            pre_contours=inp.get("pre_contours"),
            pose_options=dict(p.pose_options),
        )
    )
