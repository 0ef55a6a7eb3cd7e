# Per-run figures, the summary table (one row per run) and the cross-run analysis figures of the results chapter.


rule run_figures:
    input:
        log=f"{RUN_PATTERN}/train_log.csv",
        per_view=f"{RUN_PATTERN}/per_view.csv",
    output:
        convergence=report(
            f"{RUN_PATTERN}/figures/convergence.png",
            caption="../report/run_convergence.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "convergence"},
        ),
        porkchop=report(
            f"{RUN_PATTERN}/figures/porkchop.png",
            caption="../report/run_porkchop.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "per-view heatmap"},
        ),
        acf=report(
            f"{RUN_PATTERN}/figures/acf.png",
            caption="../report/run_acf.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "ACF"},
        ),
        kde=report(
            f"{RUN_PATTERN}/figures/kde.png",
            caption="../report/run_kde.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "KDE"},
        ),
    log:
        f"{RUN_PATTERN}/logs/run_figures.log",
    benchmark:
        f"{RUN_PATTERN}/logs/run_figures_benchmark.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("run_figures")["threads"]
    resources:
        mem_mb=rule_resources("run_figures")["mem_mb"],
        runtime=rule_resources("run_figures")["runtime"],
    params:
        analysis=run_figures_params(),
    script:
        "../../scripts/run_figures.py"


rule gather:
    input:
        metrics=metrics_of(run_dirs(sfm_cells=False)),
        logs=logs_of(run_dirs(sfm_cells=False)),
        sfm_metrics=sfm_metrics,
        sfm_logs=sfm_logs,
        sfm=sfm_summaries(),
        baselines=all_baselines(),
    output:
        summary=report(
            f"{RESULTS}/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
            labels={"table": "summary.csv"},
        ),
    log:
        f"{RESULTS}/logs/gather.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("gather")["threads"]
    resources:
        mem_mb=rule_resources("gather")["mem_mb"],
        runtime=rule_resources("gather")["runtime"],
    params:
        analysis=gather_params(),
        runs=run_dirs(),
    script:
        "../../scripts/gather.py"


rule analyse:
    input:
        summary=f"{RESULTS}/summary.csv",
        baselines=all_baselines(),
    output:
        **analysis_outputs(),
    log:
        f"{RESULTS}/logs/analyse.log",
    benchmark:
        f"{RESULTS}/benchmarks/analyse.tsv"
    conda:
        "../../envs/ctsplat.yaml"
    threads: rule_resources("analyse")["threads"]
    resources:
        mem_mb=rule_resources("analyse")["mem_mb"],
        runtime=rule_resources("analyse")["runtime"],
    params:
        analysis=analysis_params(),
    script:
        "../../scripts/analyse.py"
