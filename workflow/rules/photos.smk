# The sanity run on photographs: volumes of kind photos -> COLMAP poses -> alpha 3DGS -> held-out metrics, gallery
# and turntable (ctsplat.photos). The CT rules never see these volumes (prepare_config keeps them in photo_volumes).
PHOTO_VOLUMES = list(CFG["photo_volumes"])


def photo_targets():
    """Targets of the photo volumes: the SfM summary and the evaluated run with its figures."""
    out = []
    for v in PHOTO_VOLUMES:
        out += [
            f"{RESULTS}/{v}/photos/sfm/summary.json",
            f"{RESULTS}/{v}/photos/run/metrics.json",
            f"{RESULTS}/{v}/photos/run/figures/gallery.png",
            f"{RESULTS}/{v}/photos/run/figures/turntable.gif",
        ]
    return out


def photo_source(wildcards):
    return CFG["photo_volumes"][wildcards.volume]["source"]


rule photos_sfm:
    input:
        photo_source,
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
