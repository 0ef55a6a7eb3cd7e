"""Classical reconstructions for every geometry, and their free parameters chosen on validation views.

Modules (the baseline step, :func:`ctsplat.baselines.run_baselines`, runs them through :mod:`.suite`):

- :mod:`.operators`: the system matrix ``A`` (the project's projector) and its exact adjoint ``Aᵀ``;
- :mod:`.fdk`: FDK for circular cone beams (full scan, or short scan with Parker weights);
- :mod:`.iterative`: SART/SIRT (ordered subsets, non-negative) and ASD-POCS (TV-regularised), any geometry;
- :mod:`.mbir`: MBIR (qGGMRF) through svmbir, circular parallel beams;
- :mod:`.select`: re-projection PSNR on validation views, and the choice of parameters by it;
- :mod:`.suite`: which methods apply to a geometry, detector binning, and all methods with their choices.
"""

from ctsplat.recon.fdk import FDK_FILTERS, fdk_volume, is_circular_cone
from ctsplat.recon.iterative import asd_pocs_iterates, asd_pocs_volume, sart_iterates, sart_volume
from ctsplat.recon.mbir import mbir_volume
from ctsplat.recon.operators import Operator
from ctsplat.recon.select import Choice, Validator, choose, choose_iterative
from ctsplat.recon.suite import METHODS, applicable_methods, best_choice, classical_reconstructions

__all__ = [
    "FDK_FILTERS",
    "METHODS",
    "Choice",
    "Operator",
    "Validator",
    "applicable_methods",
    "asd_pocs_iterates",
    "asd_pocs_volume",
    "best_choice",
    "choose",
    "choose_iterative",
    "classical_reconstructions",
    "fdk_volume",
    "is_circular_cone",
    "mbir_volume",
    "sart_iterates",
    "sart_volume",
]
