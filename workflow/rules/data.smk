# Volumes: the built-in phantom as a real DICOM series, then ingestion to results/{volume}/volume.nii.gz.


rule phantom:
    output:
        directory(f"{RESULTS}/{{volume}}/phantom_dicom"),
    log:
        f"{RESULTS}/logs/phantom/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/phantom/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("phantom")["threads"]
    resources:
        mem_mb=rule_resources("phantom")["mem_mb"],
        runtime=rule_resources("phantom")["runtime"],
    params:
        phantom=phantom_params,
    script:
        "../../scripts/phantom.py"


rule ingest:
    input:
        source=ingest_source,
    output:
        volume=f"{RESULTS}/{{volume}}/volume.nii.gz",
        meta=f"{RESULTS}/{{volume}}/volume.json",
    log:
        f"{RESULTS}/logs/ingest/{{volume}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/ingest/{{volume}}.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("ingest")["threads"]
    resources:
        mem_mb=rule_resources("ingest")["mem_mb"],
        runtime=rule_resources("ingest")["runtime"],
    params:
        ingest=ingest_params,
    script:
        "../../scripts/ingest.py"
