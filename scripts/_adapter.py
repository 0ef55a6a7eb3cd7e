"""Shared boilerplate of the Snakemake script adapters: import path and logging to the rule's log file.

Each ``scripts/<rule>.py`` only maps the ``snakemake`` object (input/output/params) onto one ctsplat call.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))  # fallback when ctsplat is not installed in the job's environment


@contextlib.contextmanager
def logged(snakemake) -> Iterator[logging.Logger]:  # noqa: ANN001 (the Snakemake script object)
    """Send logging, warnings, stdout and stderr (tracebacks included) of the step to ``snakemake.log[0]``."""
    log_path = Path(snakemake.log[0])
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", buffering=1) as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        logging.basicConfig(stream=fh, level=logging.INFO, force=True,
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        logging.captureWarnings(True)
        warnings.simplefilter("default")
        log = logging.getLogger(f"ctsplat.workflow.{snakemake.rule}")
        log.info("rule %s, wildcards %s", snakemake.rule, dict(snakemake.wildcards))
        try:
            yield log
        except Exception:
            log.exception("rule %s failed", snakemake.rule)
            raise
