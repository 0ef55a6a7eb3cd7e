"""Training: settings (:mod:`.config`), seeding (:mod:`.seeding`), optimisation state (:mod:`.state`), losses
(:mod:`.losses`), densification strategies (:mod:`.densify`), the method's training features (:mod:`.features`:
augmentation, the density-regulariser schedule, redundant-coverage merging), checkpoints (:mod:`.checkpoint`),
pose refinement (:mod:`.poses`) and the loop (:mod:`.loop`)."""

from ctsplat.training.config import TRAIN_DEFAULTS, resolve_config
from ctsplat.training.loop import train

__all__ = ["TRAIN_DEFAULTS", "resolve_config", "train"]
