# The paper's claims answered by the study: results/summary/<study>/findings.csv, findings.md and the claim
# figures (deeptissue.findings), first in the report. `snakemake --cores 2 findings`.
FINDINGS_FIGURES = {
    "tissue_png": ("findings_tissue.png", "findings_tissue.rst"),
    "peaks_png": ("findings_peaks.png", "findings_peaks.rst"),
    "orientation_png": ("findings_orientation.png", "findings_orientation.rst"),
    "bins_png": ("findings_bins.png", "findings_bins.rst"),
    "skin_png": ("findings_skin.png", "findings_skin.rst"),
}
# the sphere's and the bar's strain fields, for where the highest strains lie (claim 2)
PEAK_RUNS = [(a, v) for a in STUDY_ANIMALS for v in ("sphere", "bar") if v in VARIANTS_OF[a]]
FINDINGS_OUTPUTS = [f"{SUMMARY}/findings.csv", f"{SUMMARY}/findings.md"] + [
    f"{SUMMARY}/{name}" for name, _ in FINDINGS_FIGURES.values()
]
FINAL_OUTPUTS.extend(FINDINGS_OUTPUTS if STUDY_ANIMALS else [])


# a claim figure of the report, first of all categories
findings_figure = lambda key: report(
    f"{SUMMARY}/{FINDINGS_FIGURES[key][0]}",
    caption=f"../report/{FINDINGS_FIGURES[key][1]}",
    category="Findings",
    subcategory="Claims",
)


rule findings:
    """The paper's claims against the study's tables: `snakemake --cores 2 findings`."""
    input:
        voi=f"{SUMMARY}/voi.csv",
        bins=f"{SUMMARY}/bins.csv",
        results=[variant_output(a, v, "result.vtu") for a, v in PEAK_RUNS],
        poses=[f"results/{a}/pose.json" for a, _ in PEAK_RUNS],
    output:
        findings_csv=report(
            f"{SUMMARY}/findings.csv",
            caption="../report/findings_csv.rst",
            category="Findings",
            subcategory="Claims",
        ),
        findings_md=f"{SUMMARY}/findings.md",
        tissue_png=findings_figure("tissue_png"),
        peaks_png=findings_figure("peaks_png"),
        orientation_png=findings_figure("orientation_png"),
        bins_png=findings_figure("bins_png"),
        skin_png=findings_figure("skin_png"),
    log:
        f"{SUMMARY}/findings.log",
    conda:
        "../envs/deeptissue.yaml"
    resources:
        mem_mb=4000,
        runtime=30,
    params:
        study=STUDY_NAME,
        runs=PEAK_RUNS,
        strain_measure=STUDY["strain_measure"],
        threshold=STUDY["threshold"],
        bar_length_mm=float(config.get("fem", {}).get("bar_length_mm", 10.0)),
    script:
        "../scripts/findings.py"
