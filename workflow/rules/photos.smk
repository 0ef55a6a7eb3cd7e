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
    log:
        f"{RESULTS}/logs/photos_sfm/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/photos_sfm/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("sfm")["threads"]
    resources:
        mem_mb=rule_resources("sfm")["mem_mb"],
        runtime=rule_resources("sfm")["runtime"],
    params:
        sfm=lambda wildcards: dict(CFG["photos"]["sfm"]),
    script:
        "../../scripts/photos_sfm.py"


rule photos_train:
    input:
        summary=f"{RESULTS}/{{volume}}/photos/sfm/summary.json",
    output:
        metrics=f"{RESULTS}/{{volume}}/photos/run/metrics.json",
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
        f"{RESULTS}/logs/photos_train/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/photos_train/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("train")["threads"]
    resources:
        mem_mb=rule_resources("train")["mem_mb"],
        runtime=rule_resources("train")["runtime"],
    params:
        photos=lambda wildcards: dict(CFG["photos"]),
    script:
        "../../scripts/photos_train.py"
