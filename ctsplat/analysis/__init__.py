"""Analysis of training runs: statistics of the logs (:mod:`.stats`), ``summary.csv`` (:mod:`.gather`), the
method's claims checked on the grid (:mod:`.claims`) and the figures of the results chapter (:mod:`.plots`).

The names of the outputs are defined here, apart from the plotting code, so the workflow can declare them at parse
time without importing matplotlib.
"""

from __future__ import annotations

from ctsplat.grid import GRID_AXES

__all__ = ["ANALYSIS_OUTPUTS", "RUN_FIGURES", "RUN_FIGURE_KEYS"]

# Grid-level outputs of plots.analyse: name -> (file name under results/figures/, report category).
ANALYSIS_OUTPUTS: dict[str, tuple[str, str]] = {
    "claims": ("claims.csv", "Claims"),
    **{f"convergence_by_{a}": (f"convergence_by_{a}.png", "Convergence") for a in GRID_AXES},
    "velocity": ("velocity.png", "Convergence"),
    "acf": ("acf.png", "Convergence"),
    "kde": ("kde.png", "Convergence"),
    "correlations_plot": ("correlations.png", "2D vs 3D"),
    "correlations": ("correlations.csv", "2D vs 3D"),
    "milestones": ("milestones.csv", "Milestones"),
    "ablation": ("ablation.png", "Ablation"),
    "baselines": ("baselines.png", "Baselines"),
    "provenance": ("analysis.json", "Claims"),
}
# Per-run figures of plots.run_figures, written to {run}/figures/{name}.png.
RUN_FIGURES: tuple[str, ...] = ("convergence", "porkchop", "acf", "kde")
# The analysis keys those figures read (the workflow tracks only these, so other analysis keys redraw nothing).
RUN_FIGURE_KEYS: tuple[str, ...] = ("window", "acf_max_lag", "kde_windows", "max_gap_iters")
