# One training run per grid cell (Paramspace folder), then its test-split evaluation.


rule train:
    input:
        unpack(run_inputs),
    output:
        log=f"{RUN_PATTERN}/train_log.csv",
        per_view=f"{RUN_PATTERN}/per_view.csv",
        model=f"{RUN_PATTERN}/model.pt",
        metrics=f"{RUN_PATTERN}/metrics.json",
        run_config=f"{RUN_PATTERN}/config.json",
    log:
        f"{RUN_PATTERN}/logs/train.log",
    benchmark:
        f"{RUN_PATTERN}/logs/train_benchmark.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("train")["threads"]
    resources:
        mem_mb=rule_resources("train")["mem_mb"],
        runtime=rule_resources("train")["runtime"],
        gpu=train_gpu,
    params:
        train=train_params,
        config_hash=train_hash,
    script:
        "../../scripts/train.py"


rule evaluate:
    input:
        model=f"{RUN_PATTERN}/model.pt",
        run_config=f"{RUN_PATTERN}/config.json",
    output:
        metrics=f"{RUN_PATTERN}/eval_{{split}}.json",
    log:
        f"{RUN_PATTERN}/logs/evaluate_{{split}}.log",
    benchmark:
        f"{RUN_PATTERN}/logs/evaluate_{{split}}_benchmark.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("evaluate")["threads"]
    resources:
        mem_mb=rule_resources("evaluate")["mem_mb"],
        runtime=rule_resources("evaluate")["runtime"],
        gpu=train_gpu,
    params:
        evaluation=evaluation_params,
    script:
        "../../scripts/evaluate.py"
