# Rules of the fem stage: verification and benchmark of the FE core (target `verify`, not part of `all`);
# verify_summary writes one row per check, and `verify` fails if any of them has status `fail`.


rule verify_hertz:
    output:
        hertz="results/verification/hertz.csv",
    log:
        "results/logs/verify_hertz.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_hertz.py"


rule verify_hertz_curve:
    input:
        hertz=rules.verify_hertz.output.hertz,
    output:
        curve="results/verification/hertz_curve.csv",
        figure=report(
            "results/verification/hertz.png",
            caption="../report/hertz.rst",
            category="Verification",
            subcategory="solver",
        ),
    log:
        "results/logs/verify_hertz_curve.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_hertz_curve.py"


rule verify_fem_cases:
    output:
        checks="results/verification/fem_checks.csv",
        hard="results/verification/hard_cases.csv",
    log:
        "results/logs/verify_fem_cases.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_cases.py"


rule verify_fem_benchmark:
    output:
        benchmark="results/verification/benchmark.csv",
    log:
        "results/logs/verify_fem_benchmark.log",
    conda:
        "../envs/deeptissue.yaml"
    threads: 2
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_benchmark.py"


rule verify_locking:
    output:
        locking="results/verification/locking.csv",
    log:
        "results/logs/verify_locking.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_locking.py"


rule verify_cylinder:
    output:
        curve="results/verification/cylinder_curve.csv",
        voi="results/verification/cylinder_voi.csv",
    log:
        "results/logs/verify_cylinder.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_cylinder.py"


# the cylinder scene on meshes refined from their own solutions, against verify_cylinder's fixed meshes
rule verify_cylinder_adaptive:
    input:
        curve=rules.verify_cylinder.output.curve,
        voi=rules.verify_cylinder.output.voi,
    output:
        table="results/verification/cylinder_adaptive.csv",
        figure="results/verification/cylinder_adaptive.png",
    log:
        "results/logs/verify_cylinder_adaptive.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/verify_fem_cylinder_adaptive.py"


rule verify_summary:
    input:
        points=rules.verify_material.output.points,
        hertz=rules.verify_hertz.output.hertz,
        curve=rules.verify_hertz_curve.output.curve,
        locking=rules.verify_locking.output.locking,
        checks=rules.verify_fem_cases.output.checks,
        hard=rules.verify_fem_cases.output.hard,
        benchmark=rules.verify_fem_benchmark.output.benchmark,
        cylinder_curve=rules.verify_cylinder.output.curve,
        cylinder_voi=rules.verify_cylinder.output.voi,
        cylinder_adaptive=rules.verify_cylinder_adaptive.output.table,
    output:
        summary="results/verification/summary.csv",
    log:
        "results/logs/verify_summary.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/verify_summary.py"


# the target: every verification output, and a failure naming the checks whose status is `fail`
rule verify:
    input:
        rules.verify_material.output,
        rules.verify_hertz.output,
        rules.verify_hertz_curve.output,
        rules.verify_fem_cases.output,
        rules.verify_fem_benchmark.output,
        rules.verify_locking.output,
        rules.verify_cylinder.output,
        rules.verify_cylinder_adaptive.output,
        summary=rules.verify_summary.output.summary,
    log:
        "results/logs/verify.log",
    conda:
        "../envs/deeptissue.yaml"
    script:
        "../scripts/verify_check.py"


rule linear_solvers:
    """Benchmark (not part of `verify`): each linear-solver backend's factorisation time on the cored
    cylinder's tangent at four element sizes, on one thread as every solve job runs."""
    output:
        table="results/verification/linear_solvers.csv",
        figure="results/verification/linear_solvers.png",
    log:
        "results/logs/linear_solvers.log",
    conda:
        "../envs/deeptissue.yaml"
    params:
        material=config["fem"]["material"],
    script:
        "../scripts/linear_solvers.py"
