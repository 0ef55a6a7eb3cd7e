"""Evaluation: image and volume metrics (:mod:`.metrics`), a run's held-out evaluation (:mod:`.run`, re-exported as
:func:`evaluate`), its figures (:mod:`.figures`), the
volume read-out's validation-chosen sharpening (:mod:`.readout`)."""

from ctsplat.evaluation.run import evaluate

__all__ = ["evaluate"]
