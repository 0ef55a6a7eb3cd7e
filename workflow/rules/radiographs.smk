# Synthetic radiographs once per volume and geometry, and the classical baselines on them (any geometry).


rule project:
    input:
        volume=f"{RESULTS}/{{volume}}/volume.nii.gz",
        meta=f"{RESULTS}/{{volume}}/volume.json",
    output:
        line_integrals=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/line_integrals.tif",
        views=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/views.json",
        meta=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/radiographs.json",
        png=directory(f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/png"),
    log:
        f"{RESULTS}/logs/project/{{volume}}/{{geometry}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/project/{{volume}}/{{geometry}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("project")["threads"]
    resources:
        mem_mb=rule_resources("project")["mem_mb"],
        runtime=rule_resources("project")["runtime"],
        gpu=project_gpu,
    params:
        radiographs=radiographs_params,
        seed=0,
    script:
        "../../scripts/project.py"


rule baseline:
    input:
        volume=f"{RESULTS}/{{volume}}/volume.nii.gz",
        line_integrals=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/line_integrals.tif",
        views=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/views.json",
    output:
        csv=report(
            f"{RESULTS}/{{volume}}/baselines/{{geometry}}/baselines.csv",
            caption="../report/baselines_csv.rst",
            category="Baselines",
            subcategory="{volume}",
            labels={
                "volume": "{volume}",
                "geometry": "{geometry}",
                "table": "classical baselines",
            },
        ),
        info=f"{RESULTS}/{{volume}}/baselines/{{geometry}}/baselines.json",
    log:
        f"{RESULTS}/logs/baseline/{{volume}}/{{geometry}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/baseline/{{volume}}/{{geometry}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("baseline")["threads"]
    resources:
        mem_mb=rule_resources("baseline")["mem_mb"],
        runtime=rule_resources("baseline")["runtime"],
        gpu=baseline_gpu,
    params:
        baselines=baselines_params,
    script:
        "../../scripts/baseline.py"
