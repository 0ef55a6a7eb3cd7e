# The sanity run on photographs: volumes of kind photos -> COLMAP poses -> alpha 3DGS -> held-out metrics, gallery
# and turntable (ctsplat.photos). The CT rules never see these volumes (prepare_config keeps them in photo_volumes).
# Targets of the photo volumes (rule all): the SfM summary and the evaluated run with its figures.
PHOTO_TARGETS = [
    f"{RESULTS}/{v}/photos/{f}"
    for v in CFG["photo_volumes"]
    for f in (
        "sfm/summary.json",
        "run/metrics.json",
        "run/figures/gallery.png",
        "run/figures/turntable.gif",
    )
]


rule photos_sfm:
    input:
        lambda wildcards: CFG["photo_volumes"][wildcards.volume]["source"],
    output:
        summary=f"{RESULTS}/{{volume}}/photos/sfm/summary.json",
        sparse=directory(f"{RESULTS}/{{volume}}/photos/sfm/sparse"),
        images=directory(f"{RESULTS}/{{volume}}/photos/sfm/images"),
    log:
        f"{RESULTS}/logs/photos_sfm/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/photos_sfm/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("photos_sfm")["threads"]
    resources:
        mem_mb=rule_resources("photos_sfm")["mem_mb"],
        runtime=rule_resources("photos_sfm")["runtime"],
    params:
        sfm=photos_sfm_params,
    script:
        "../../scripts/photos_sfm.py"


rule photos_train:
    input:
        summary=f"{RESULTS}/{{volume}}/photos/sfm/summary.json",
        sparse=f"{RESULTS}/{{volume}}/photos/sfm/sparse",
        images=f"{RESULTS}/{{volume}}/photos/sfm/images",
    output:
        model=f"{RESULTS}/{{volume}}/photos/run/model.pt",
        ply=f"{RESULTS}/{{volume}}/photos/run/model.ply",
        run_config=f"{RESULTS}/{{volume}}/photos/run/config.json",
        training=f"{RESULTS}/{{volume}}/photos/run/training.json",
        log=f"{RESULTS}/{{volume}}/photos/run/train_log.csv",
    log:
        f"{RESULTS}/logs/photos_train/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/photos_train/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("photos_train")["threads"]
    resources:
        mem_mb=rule_resources("photos_train")["mem_mb"],
        runtime=rule_resources("photos_train")["runtime"],
        gpu=photos_gpu,
    params:
        train=photos_train_params,
    script:
        "../../scripts/photos_train.py"


rule photos_evaluate:
    input:
        model=f"{RESULTS}/{{volume}}/photos/run/model.pt",
        run_config=f"{RESULTS}/{{volume}}/photos/run/config.json",
        training=f"{RESULTS}/{{volume}}/photos/run/training.json",
    output:
        metrics=f"{RESULTS}/{{volume}}/photos/run/metrics.json",
        per_view=f"{RESULTS}/{{volume}}/photos/run/per_view_test.csv",
        gallery=report(
            f"{RESULTS}/{{volume}}/photos/run/figures/gallery.png",
            caption="../report/photos.rst",
            category="Sanity run (photographs)",
            labels={"volume": "{volume}", "figure": "held-out renders vs photos"},
        ),
        turntable=report(
            f"{RESULTS}/{{volume}}/photos/run/figures/turntable.gif",
            caption="../report/photos.rst",
            category="Sanity run (photographs)",
            labels={"volume": "{volume}", "figure": "turntable"},
        ),
    log:
        f"{RESULTS}/logs/photos_evaluate/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/photos_evaluate/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("photos_evaluate")["threads"]
    resources:
        mem_mb=rule_resources("photos_evaluate")["mem_mb"],
        runtime=rule_resources("photos_evaluate")["runtime"],
        gpu=photos_gpu,
    params:
        evaluate=lambda wildcards: canonical(CFG["photos"]["evaluate"]),
    script:
        "../../scripts/photos_evaluate.py"
