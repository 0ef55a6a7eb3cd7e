"""Shared boilerplate of the Snakemake script adapters: import path and logging to the rule's log file.

Each ``scripts/<rule>.py`` only maps the ``snakemake`` object (input/output/params) onto one ctsplat call.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.append(str(ROOT))  # fallback when ctsplat is not installed in the job's environment

# Snakemake sets thread variables for shell jobs only: give script jobs (torch, BLAS) their `threads:` too,
# before the step's imports, so parallel jobs do not oversubscribe the cores.
_SM = getattr(sys.modules.get("__main__"), "snakemake", None)
if _SM is not None:
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_var] = str(_SM.threads)


@contextlib.contextmanager
def logged(snakemake) -> Iterator[logging.Logger]:  # noqa: ANN001 (the Snakemake script object)
    """Send logging, warnings, stdout and stderr of the step to ``snakemake.log[0]``: a ctsplat error as its one
    line (the job then exits 1), any other exception with its traceback."""
    from ctsplat.utils import CtsplatError, log_warnings_once, terminate_as_interrupt

    terminate_as_interrupt()  # a cancelled job (SIGTERM) removes its temporary files before it ends
    log_path = Path(snakemake.log[0])
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w", buffering=1) as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        logging.basicConfig(stream=fh, level=logging.INFO, force=True,
                            format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        warnings.simplefilter("default")
        log_warnings_once()  # after the filter above, which would show the warnings the library logged already
        log = logging.getLogger(f"ctsplat.workflow.{snakemake.rule}")
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(int(snakemake.threads))
        log.info("rule %s, wildcards %s, threads %s", snakemake.rule, dict(snakemake.wildcards), snakemake.threads)
        try:
            yield log
        except CtsplatError as exc:  # the library's one-line errors say what to fix: no traceback under them
            log.error("rule %s failed: %s", snakemake.rule, exc)
            raise SystemExit(1) from None
        except Exception:
            log.exception("rule %s failed", snakemake.rule)
            raise
