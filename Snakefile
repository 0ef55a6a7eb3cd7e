# ctsplat: CT volume -> synthetic radiographs -> (COLMAP poses) -> Gaussian training -> metrics, figures, report.
# Run: snakemake --cores 2 --configfile config/config.yaml ; snakemake --report results/report.html
from snakemake.utils import min_version

min_version("9")


# The default grid, unless config files were given (--configfile replaces it rather than merging into it);
# --config key=value still overrides single keys of either.
if not workflow.config_settings.configfiles:

    configfile: f"{workflow.basedir}/config/config.yaml"


include: "workflow/rules/common.smk"


wildcard_constraints:
    volume="[A-Za-z0-9][A-Za-z0-9_.-]*",
    geometry="[A-Za-z0-9][A-Za-z0-9_.-]*",
    init="volume|uniform|fbp|sfm",
    compositor="radiative|radiative_unrectified|alpha",
    mip="on|off",
    poses=r"gt|perturbed|colmap|gt\+refine|perturbed\+refine|colmap\+refine",
    views="[0-9]+",
    seed="[0-9]+",


include: "workflow/rules/data.smk"
include: "workflow/rules/radiographs.smk"
include: "workflow/rules/sfm.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/analysis.smk"
include: "workflow/rules/overview.smk"
include: "workflow/rules/photos.smk"


report: "workflow/report/workflow.rst"


rule all:
    default_target: True
    input:
        all_targets(),
        sfm_targets,
        PHOTO_TARGETS,
