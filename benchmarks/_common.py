"""What the benchmarks share: the one-line error exit, tables written whole, the shared train settings, cache
folders and the time to a quality level.

Imported by the scripts in this folder (Python puts a script's folder first on ``sys.path``).
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import pandas as pd


def cli_main(run: Callable[[list[str] | None], int], argv: list[str] | None, script: str) -> int:
    """Run ``run(argv)``; a :class:`~ctsplat.utils.CtsplatError` becomes one line ``script: error: ...`` and exit 2,
    Ctrl-C or SIGTERM one line and exit 130 or 143, after the steps' temporary files are removed (as the command
    line does)."""
    from ctsplat.utils import CtsplatError, Terminated, terminate_as_interrupt

    terminate_as_interrupt()  # a killed benchmark removes its temporary folders like an interrupted one
    try:
        return run(argv)
    except CtsplatError as exc:
        print(f"{script}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        how = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(f"{script}: {how}; files are written whole or not at all: run it again", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130


def write_csv(table: pd.DataFrame, path: str | Path, **kwargs: Any) -> Path:
    """Write ``table`` to ``path`` whole or not at all (:func:`ctsplat.utils.atomic_path`): an interrupted run
    leaves the earlier table, never a truncated one. ``kwargs`` go to :meth:`pandas.DataFrame.to_csv` (``index``
    False and Unix line ends unless given).

    Returns
    -------
    Path
        ``path``.
    """
    from ctsplat.utils import atomic_path

    with atomic_path(path) as tmp:
        table.to_csv(tmp, **{"index": False, "lineterminator": "\n", **kwargs})
    return Path(path)


def earlier_table(path: str | Path, option: str = "--csv") -> pd.DataFrame | None:
    """The table an earlier run of a benchmark wrote to ``path``, which this run adds rows to (None when there is
    none), read before the work; a folder or an unreadable file is one line naming ``option``. Its columns are the
    caller's to check."""
    from ctsplat.utils import CtsplatError

    path = Path(path)
    if path.is_dir():
        raise CtsplatError(f"{option} {path} is a folder; give a CSV file")
    if not path.exists():
        return None
    try:
        return pd.read_csv(path)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise CtsplatError(f"{option} {path} cannot be read ({' '.join(str(exc).split())}); give this benchmark's "
                           "table or a new file") from None


def run_child(cmd: list[str], *, grace_s: float = 60.0, **kwargs: Any) -> subprocess.CompletedProcess:
    """:func:`subprocess.run` with ``capture_output`` and ``text``, except that Ctrl-C or SIGTERM of this process
    (:func:`cli_main`'s :class:`KeyboardInterrupt`) passes SIGTERM on to the child and waits up to ``grace_s`` for it
    to remove its temporary files (``subprocess.run`` kills it after a quarter second), then re-raises."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)
    try:
        out, err = proc.communicate()
    except KeyboardInterrupt:
        proc.terminate()
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def out_folder(path: str | Path, option: str = "--out") -> Path:
    """The benchmark's output folder, created; a file in its place is one line naming ``option``."""
    from ctsplat.utils import CtsplatError

    path = Path(path)
    blocker = next((p for p in (path, *path.parents) if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise CtsplatError(f"{option} {path}: {blocker} is a file, not a folder; give a folder")
    path.mkdir(parents=True, exist_ok=True)
    return path


def shared_train_config(sets: list[str], *, own_keys: Mapping[str, str | None], defaults: Mapping[str, Any],
                        fixed: Mapping[str, Any]) -> dict[str, Any]:
    """The train settings every run of a benchmark shares, checked against the schema.

    Parameters
    ----------
    sets : list of str
        The ``--set KEY=VALUE`` options (as ``ctsplat train --set``).
    own_keys : mapping
        Keys (dotted for nested ones) that the benchmark sets per run, each to the option that sets it (or
        ``None``): one in ``sets``, or under it, is a one-line error naming that option.
    defaults : mapping
        The benchmark's defaults; ``sets`` override them (key by key inside nested sections).
    fixed : mapping
        Settings that override ``sets`` (the benchmark's own options).

    Returns
    -------
    dict
        ``{"compositor": "radiative", "device": "cpu", **defaults, **user, **fixed, "progress": False}``, with the
        schema's defaults and ranges applied.
    """
    from ctsplat.cli.train import load_train_config
    from ctsplat.config import check_section
    from ctsplat.utils import CtsplatError, deep_update, dotted_items

    user = load_train_config(None, sets)
    own = [(key, p) for key in dotted_items(user) for p in own_keys if key == p or key.startswith(p + ".")]
    if own:
        key, option = own[0][0], own_keys[own[0][1]]
        raise CtsplatError(f"--set {key} is set by this benchmark per run" + (f"; use {option}" if option else ""))
    cfg = deep_update({"compositor": "radiative", "device": "cpu", **defaults}, user)
    return check_section("train", {**cfg, **fixed, "progress": False})


def data_key(data: Path | str) -> str:
    """Eight hex digits of a data set's resolved path (of ``phantom`` as it is): what tells two scans of one name
    apart in a cache."""
    data = str(data)
    return hashlib.sha256((data if data == "phantom" else str(Path(data).resolve())).encode()).hexdigest()[:8]


def data_cache(out: Path, data: Path | str, suffix: str = "") -> Path:
    """The cache folder of one data set: its name and :func:`data_key`."""
    return Path(out) / "cache" / f"{Path(str(data)).name}-{data_key(data)}{suffix}"


def time_to(log: pd.DataFrame, value: float) -> float | None:
    """Seconds (the log's ``timestamp``) at which the 3D PSNR first reached ``value`` dB, or ``None``."""
    hit = log[log["psnr3d"] >= value]
    return None if hit.empty else float(hit["timestamp"].iloc[0])
