# Shared helpers: config validation (before any job runs), the ablation grid (Paramspace), input functions.
# All logic lives in ctsplat.config (schema: ctsplat/schemas/config.schema.yaml) and ctsplat.grid; these are thin
# wrappers used by the rules.
import os
from pathlib import Path

from snakemake.utils import Paramspace

from ctsplat.analysis import ANALYSIS_OUTPUTS, RUN_FIGURE_KEYS
from ctsplat.config import (
    RESULTS_DIR,
    canonical,
    check_config_files,
    on_workflow_device,
    prepare_config,
)
from ctsplat.formats.sources import outputs_selector
from ctsplat.training.config import EVALUATION_KEYS
from ctsplat.sfm.step import sfm_failure
from ctsplat.grid import (
    cells_need_sfm,
    expand_grid,
    needs_sfm,
    run_axes,
    uses_colmap,
    with_train_overrides,
)
from ctsplat.utils import CtsplatError, config_hash
from ctsplat.volume import preprocessing_in_effect

try:
    # the default config when none was given (the Snakefile's configfile directive)
    check_config_files(
        workflow.config_settings.configfiles
        or [f"{workflow.basedir}/config/config.yaml"]
    )
    CFG = prepare_config(config, base_dir=os.getcwd())
except CtsplatError as exc:
    raise WorkflowError(f"ctsplat config error: {exc}") from None

RESULTS = RESULTS_DIR
GEOMETRY = CFG["grid"]["geometry"]
SFM_GEOMETRY = CFG["sfm"]["settings"]["geometry"]
BASELINE_GEOMETRY = CFG["baselines"]["geometry"]
VOLUMES = list(CFG["volumes"])
RUNS = expand_grid(CFG["grid"]["axes"], VOLUMES, CFG["grid"]["exclude"])
RUN_AXES = run_axes(RUNS.columns)
PARAMSPACE = Paramspace(RUNS[list(RUN_AXES)].drop_duplicates(), param_sep="~")
RUN_PATTERN = f"{RESULTS}/{{volume}}/runs/{PARAMSPACE.wildcard_pattern}"
RUN_LABELS = {name: f"{{{name}}}" for name in ("volume", *RUN_AXES)}


def run_dirs(volume=None, *, sfm_cells=None):
    """Run folders of the grid (optionally of one volume), in grid order, from the Paramspace instances.

    sfm_cells: None for every cell, True for only the cells that train on SfM output (poses: colmap, init: sfm),
    False for only the others.
    """
    out = []
    for v in VOLUMES if volume is None else [volume]:
        rows = RUNS[RUNS["volume"] == v]
        if sfm_cells is not None:
            rows = rows[cells_need_sfm(rows) == sfm_cells]
        cells = Paramspace(rows[list(RUN_AXES)], param_sep="~")
        out += [f"{RESULTS}/{v}/runs/{p}" for p in cells.instance_patterns]
    return out


def sfm_runs_for(volume):
    """Whether SfM runs for a volume (ctsplat.grid.needs_sfm on its grid cells)."""
    return needs_sfm(RUNS[RUNS["volume"] == volume], enabled=CFG["sfm"]["enabled"])


def sfm_run_dirs(wildcards=None):
    """The cells that train on SfM output, for the volumes whose SfM run is ok.

    `sfm` is a checkpoint: these cells are scheduled once its summary exists, and never on a failed run (gather
    lists them as not run, with the reason). Input functions only: it waits for the checkpoint.
    """
    out = []
    for v in VOLUMES:
        if sfm_runs_for(v):
            summary = checkpoints.sfm.get(volume=v).output.summary
            if sfm_failure(summary) is None:
                out += run_dirs(v, sfm_cells=True)
    return out


def baselines_enabled():
    return CFG["baselines"]["enabled"]


def run_targets(dirs):
    return [
        t
        for rd in dirs
        for t in (f"{rd}/metrics.json", f"{rd}/figures/convergence.png")
    ]


def all_targets():
    """Targets of the default target (all): per-run metrics and figures of the cells that do not wait for SfM,
    the summary and the analysis figures (the SfM cells are `sfm_targets`)."""
    targets = [f"{RESULTS}/summary.csv"]
    targets += [f"{RESULTS}/figures/{fname}" for fname, _ in ANALYSIS_OUTPUTS.values()]
    targets += run_targets(run_dirs(sfm_cells=False))
    for v in VOLUMES:
        targets.append(f"{RESULTS}/{v}/figures/volume_slices.png")
        targets.append(f"{RESULTS}/{v}/figures/radiographs_{GEOMETRY}.png")
        if sfm_runs_for(v):
            targets.append(f"{RESULTS}/{v}/sfm/summary.json")
            targets.append(f"{RESULTS}/{v}/sfm/pose_errors.png")
            targets.append(f"{RESULTS}/{v}/figures/radiographs_{SFM_GEOMETRY}.png")
        if baselines_enabled():
            targets.append(f"{RESULTS}/{v}/baselines/{BASELINE_GEOMETRY}/baselines.csv")
    return targets


def sfm_targets(wildcards):
    """Per-run targets of the cells that train on an ok SfM run (waits for the sfm checkpoint)."""
    return run_targets(sfm_run_dirs())


def rule_resources(rule):
    """(threads, mem_mb, runtime) for a rule from config `resources`."""
    return CFG["resources"][rule]


def volume_cfg(wildcards):
    return CFG["volumes"][wildcards.volume]


def ingest_source(wildcards):
    """Input of `ingest`: the phantom DICOM folder, or the configured source path."""
    source = volume_cfg(wildcards)["source"]
    if source == "phantom":
        return f"{RESULTS}/{wildcards.volume}/phantom_dicom"
    return source


def ingest_params(wildcards):
    """Keyword arguments of ctsplat.volume.ingest for one volume (preprocessing merged over the global one;
    settings that do nothing at their defaults, so that changing one reruns nothing)."""
    vol = volume_cfg(wildcards)
    return canonical(
        {
            "preprocessing": preprocessing_in_effect(
                {**CFG["preprocessing"], **vol["preprocessing"]}
            ),
            "series_uid": outputs_selector(vol["series_uid"]),
            "allow_modalities": list(vol["allow_modalities"]),
            "skip_corrupt": vol["skip_corrupt"],
            "tiff_voxel_size_mm": vol["tiff_voxel_size_mm"],
            "rescale": vol["rescale"],
            "nonfinite": vol["nonfinite"],
        }
    )


def phantom_params(wildcards):
    return canonical(volume_cfg(wildcards)["phantom"])


def radiographs_params(wildcards):
    """The geometry's radiographs settings; the projector runs on the workflow's device unless set there."""
    user = (config.get("radiographs") or {}).get(wildcards.geometry)
    return canonical(
        on_workflow_device(CFG["radiographs"][wildcards.geometry], user, CFG["device"])
    )


def baselines_params(wildcards):
    """run_baselines config: the user's settings plus the view counts (baselines.n_views, else the grid's); on the
    workflow's device unless baselines.settings.device is set."""
    views = CFG["baselines"]["n_views"]
    if views is None:
        views = RUNS[RUNS["volume"] == wildcards.volume]["views"]
    user = (config.get("baselines") or {}).get("settings")
    settings = on_workflow_device(CFG["baselines"]["settings"], user, CFG["device"])
    return canonical({"n_views": sorted(set(int(v) for v in views)), **settings})


def sfm_params(wildcards):
    return canonical(CFG["sfm"]["settings"])


def radiographs_dir(volume, geometry):
    return f"{RESULTS}/{volume}/radiographs/{geometry}"


def sfm_inputs(wildcards):
    """Inputs of `sfm`: the C-arm view set of `sfm.settings.geometry` (and the volume, for naive_slices)."""
    rd = radiographs_dir(wildcards.volume, SFM_GEOMETRY)
    return {
        "volume": f"{RESULTS}/{wildcards.volume}/volume.nii.gz",
        "line_integrals": f"{rd}/line_integrals.tif",
        "views": f"{rd}/views.json",
    }


def run_inputs(wildcards):
    """Inputs of `train` and `evaluate`: the reference volume, the training geometry's view set, SfM when used.

    With poses: colmap (or colmap+refine) the training targets are the C-arm view set's radiographs at the poses SfM recovered.
    """
    rd = radiographs_dir(wildcards.volume, GEOMETRY)
    inputs = {
        "volume": f"{RESULTS}/{wildcards.volume}/volume.nii.gz",
        "line_integrals": f"{rd}/line_integrals.tif",
        "views": f"{rd}/views.json",
    }
    if uses_colmap(wildcards.poses) or wildcards.init == "sfm":
        inputs["sfm"] = f"{RESULTS}/{wildcards.volume}/sfm/summary.json"
        sfm_rd = radiographs_dir(wildcards.volume, SFM_GEOMETRY)
        inputs["sfm_views"] = f"{sfm_rd}/views.json"
        inputs["sfm_line_integrals"] = f"{sfm_rd}/line_integrals.tif"
    return inputs


def evaluate_inputs(wildcards):
    """Inputs of `evaluate`: the finished run (model, config, log) and the view sets it was trained on."""
    rd = f"{RESULTS}/{wildcards.volume}/runs/{PARAMSPACE.wildcard_pattern}".format(
        **wildcards
    )
    return {
        **run_inputs(wildcards),
        "model": f"{rd}/model.pt",
        "model_best": f"{rd}/model_best.pt",  # model_selection: best scores it
        "run_config": f"{rd}/config.json",
        "training": f"{rd}/training.json",
        "log": f"{rd}/train_log.csv",
    }


def train_params(wildcards):
    """The run's training config: hyper-parameters + this grid cell's axis values (paths added by the script).

    Tracked by Snakemake's params rerun trigger, so changing any of it reruns the cell; its hash is recorded.
    """
    cell = PARAMSPACE.instance(wildcards)
    # the evaluation's own keys go to the evaluate rule: changing a figure setting does not train again
    cfg = {k: v for k, v in CFG["train"].items() if k not in EVALUATION_KEYS}
    cfg.update(
        init=str(cell["init"]),
        compositor=str(cell["compositor"]),
        mip=cell["mip"] == "on",
        poses=str(cell["poses"]),
        views=int(cell["views"]),
        seed=int(cell["seed"]),
        device=CFG["device"],
    )
    # the optional feature axes (ctsplat.grid.FEATURE_AXES)
    return canonical(with_train_overrides(cfg, cell))


def train_hash(wildcards):
    return config_hash(train_params(wildcards))


def evaluation_settings():
    """The train keys that only the evaluation reads (figures, turntable frames, the FPS size, which model it
    scores, the read-out sharpening)."""
    return canonical({k: CFG["train"][k] for k in EVALUATION_KEYS if k != "progress"})


def evaluation_milestones():
    """Validation targets of the time-to-milestone columns (the analysis section's, so tables agree)."""
    return canonical(CFG["analysis"]["milestones"])


def gpus(device):
    """The executor's gpu resource of a job that runs on ``device``: one on CUDA, none otherwise."""
    return 1 if str(device).startswith("cuda") else 0


def train_gpu(wildcards):
    return gpus(CFG["device"])


def analysis_params():
    return canonical(CFG["analysis"])


def run_figures_params():
    """The analysis keys the per-run figures read (changing another one redraws nothing)."""
    return canonical({k: CFG["analysis"][k] for k in RUN_FIGURE_KEYS})


def gather_params():
    """The analysis keys gather reads (so that changing a figure setting does not gather again)."""
    keys = ("milestones", "max_gap_iters", "velocity_per_iters")
    return canonical({k: CFG["analysis"][k] for k in keys})


def without_threads(settings):
    """Settings less num_threads, which the photo scripts take from the rule's threads (so it reruns nothing)."""
    return {k: v for k, v in settings.items() if k != "num_threads"}


def photos_sfm_params(wildcards):
    return canonical(without_threads(CFG["photos"]["sfm"]))


def photos_train_params(wildcards):
    """The photo training settings; on the workflow's device unless photos.train.device is set."""
    user = (config.get("photos") or {}).get("train")
    settings = on_workflow_device(CFG["photos"]["train"], user, CFG["device"])
    return canonical(without_threads(settings))


def photos_gpu(wildcards):
    return gpus(photos_train_params(wildcards)["device"])


def project_gpu(wildcards):
    """A GPU for the projector when it runs on CUDA (the workflow's device unless the geometry sets one)."""
    return gpus(radiographs_params(wildcards)["device"])


def baseline_gpu(wildcards):
    return gpus(baselines_params(wildcards)["device"])


def metrics_of(dirs):
    return [f"{rd}/metrics.json" for rd in dirs]


def logs_of(dirs):
    return [f"{rd}/train_log.csv" for rd in dirs]


def sfm_metrics(wildcards):
    return metrics_of(sfm_run_dirs())


def sfm_logs(wildcards):
    return logs_of(sfm_run_dirs())


def all_baselines():
    if not baselines_enabled():
        return []
    return [
        f"{RESULTS}/{v}/baselines/{BASELINE_GEOMETRY}/baselines.csv" for v in VOLUMES
    ]


def analysis_outputs():
    """Named outputs of `analyse`, each registered in the report with its caption and category."""
    return {
        name: report(
            f"{RESULTS}/figures/{fname}",
            caption=f"../report/{name}.rst",
            category=category,
            labels={"figure": name},
        )
        for name, (fname, category) in ANALYSIS_OUTPUTS.items()
    }


def sfm_summaries():
    """SfM summaries of the volumes with cells that train on SfM output: their pose errors are columns of
    summary.csv, and a failed run's reason is the not-run reason of those cells."""
    return [f"{RESULTS}/{v}/sfm/summary.json" for v in VOLUMES if sfm_runs_for(v)]


def contact_sheet_split(wildcards):
    """Views of a contact sheet: the training split of the training geometry, every view of the C-arm set."""
    return "train" if wildcards.geometry == GEOMETRY else None


def evaluate_figure_outputs():
    """Figures `evaluate` writes into the run folder when train.figures is on (none when off)."""
    if not CFG["train"]["figures"]:
        return {}
    return {
        "gallery": report(
            f"{RUN_PATTERN}/gallery.png",
            caption="../report/run_gallery.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "test gallery"},
        ),
        "slices": report(
            f"{RUN_PATTERN}/slices.png",
            caption="../report/run_slices.rst",
            category="Runs",
            subcategory="{volume}",
            labels=RUN_LABELS | {"figure": "volume slices"},
        ),
        "turntable": f"{RUN_PATTERN}/turntable.gif",
    }
