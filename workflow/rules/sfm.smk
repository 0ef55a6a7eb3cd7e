# COLMAP poses once per volume for the C-arm view set that `project` rendered, aligned to the world frame.
# A checkpoint: the cells that train on its poses are scheduled only when its summary says ok.


checkpoint sfm:
    input:
        unpack(sfm_inputs),
    output:
        summary=f"{RESULTS}/{{volume}}/sfm/summary.json",
        poses=f"{RESULTS}/{{volume}}/sfm/poses.csv",
    log:
        f"{RESULTS}/logs/sfm/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/sfm/{{volume}}.tsv"
    # early, so the cells that wait for it (and their longer C-arm training) are not left to run alone at the end
    priority: 10
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("sfm")["threads"]
    resources:
        mem_mb=rule_resources("sfm")["mem_mb"],
        runtime=rule_resources("sfm")["runtime"],
    params:
        sfm=sfm_params,
        seed=0,
    script:
        "../../scripts/sfm.py"


rule sfm_figure:
    input:
        summary=f"{RESULTS}/{{volume}}/sfm/summary.json",
        poses=f"{RESULTS}/{{volume}}/sfm/poses.csv",
    output:
        figure=report(
            f"{RESULTS}/{{volume}}/sfm/pose_errors.png",
            caption="../report/sfm.rst",
            category="SfM",
            labels={"volume": "{volume}", "figure": "pose error vs azimuth"},
        ),
    log:
        f"{RESULTS}/logs/sfm_figure/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/sfm_figure/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("sfm_figure")["threads"]
    resources:
        mem_mb=rule_resources("sfm_figure")["mem_mb"],
        runtime=rule_resources("sfm_figure")["runtime"],
    script:
        "../../scripts/overview.py"
