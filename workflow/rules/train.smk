# One training run per grid cell (Paramspace folder), then its evaluation on the test views (metrics.json).


rule train:
    input:
        unpack(run_inputs),
    output:
        log=f"{RUN_PATTERN}/train_log.csv",
        per_view=f"{RUN_PATTERN}/per_view.csv",
        model=f"{RUN_PATTERN}/model.pt",
        model_best=f"{RUN_PATTERN}/model_best.pt",
        ply=f"{RUN_PATTERN}/model.ply",
        run_config=f"{RUN_PATTERN}/config.json",
        training=f"{RUN_PATTERN}/training.json",
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
        unpack(evaluate_inputs),
    output:
        **evaluate_figure_outputs(),
        metrics=f"{RUN_PATTERN}/metrics.json",
        per_view=f"{RUN_PATTERN}/per_view_test.csv",
        volume=f"{RUN_PATTERN}/model_volume.nii.gz",
        volume_json=f"{RUN_PATTERN}/model_volume.json",
    log:
        f"{RUN_PATTERN}/logs/evaluate.log",
    benchmark:
        f"{RUN_PATTERN}/logs/evaluate_benchmark.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("evaluate")["threads"]
    resources:
        mem_mb=rule_resources("evaluate")["mem_mb"],
        runtime=rule_resources("evaluate")["runtime"],
        gpu=train_gpu,
    params:
        device=CFG["device"],
        milestones=evaluation_milestones(),
        settings=evaluation_settings(),
    script:
        "../../scripts/evaluate.py"
