# Report sections on the inputs of every run: the ingested volume and the view sets it was projected to.


rule overview_data:
    input:
        volume=f"{RESULTS}/{{volume}}/volume.nii.gz",
    output:
        figure=report(
            f"{RESULTS}/{{volume}}/figures/volume_slices.png",
            caption="../report/data.rst",
            category="Data",
            labels={"volume": "{volume}", "figure": "central slices"},
        ),
    log:
        f"{RESULTS}/logs/overview_data/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/overview_data/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("overview_data")["threads"]
    resources:
        mem_mb=rule_resources("overview_data")["mem_mb"],
        runtime=rule_resources("overview_data")["runtime"],
    script:
        "../../scripts/overview.py"


rule overview_radiographs:
    input:
        line_integrals=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/line_integrals.tif",
        views=f"{RESULTS}/{{volume}}/radiographs/{{geometry}}/views.json",
    output:
        figure=report(
            f"{RESULTS}/{{volume}}/figures/radiographs_{{geometry}}.png",
            caption="../report/radiographs.rst",
            category="Radiographs",
            labels={"volume": "{volume}", "view set": "{geometry}"},
        ),
    log:
        f"{RESULTS}/logs/overview_radiographs/{{volume}}/{{geometry}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/overview_radiographs/{{volume}}/{{geometry}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("overview_radiographs")["threads"]
    resources:
        mem_mb=rule_resources("overview_radiographs")["mem_mb"],
        runtime=rule_resources("overview_radiographs")["runtime"],
    params:
        split=contact_sheet_split,
        max_images=16,
    script:
        "../../scripts/overview.py"
