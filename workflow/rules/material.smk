# Rules of the material stage: verification of the Ogden material point (part of `verify`).


rule verify_material:
    output:
        points="results/verification/material_point.csv",
        homogeneous="results/verification/homogeneous.csv",
        figure=report(
            "results/verification/homogeneous.png",
            caption="../report/homogeneous.rst",
            category="Verification",
            subcategory="material",
        ),
        speed="results/verification/material_speed.csv",
    log:
        "results/logs/verify_material.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_material.py"
