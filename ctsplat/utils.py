"""Small shared helpers: atomic writes, provenance (code version, config hash), device choice, seeding."""

from __future__ import annotations

import contextlib
import difflib
import fnmatch
import hashlib
import json
import logging
import math
import numbers
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
import warnings
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

__all__ = [
    "SEED_MAX",
    "CtsplatError",
    "LoggedWarning",
    "log_warnings_once",
    "Terminated",
    "terminate_as_interrupt",
    "atomic_path",
    "atomic_dir",
    "made_parents",
    "check_output_dir",
    "scratch_dir",
    "save_torch_atomic",
    "write_json_atomic",
    "read_json_object",
    "first_nonfinite",
    "json_safe",
    "CODE_PATHS",
    "code_version",
    "compute_platform",
    "config_hash",
    "deep_update",
    "dotted_items",
    "resolve_device",
    "seed_everything",
    "run_lock",
    "LOCK_NAME",
    "HOST_READS",
    "count_host_reads",
]


class CtsplatError(ValueError):
    """A user-facing error: one line saying what is wrong and how to fix it.

    Raised for bad input (config values, files, geometry) before any output is written. It subclasses
    :class:`ValueError`, so callers that catch ``ValueError`` also catch it; the command-line interface prints
    its message without a traceback.

    Examples
    --------
    >>> raise CtsplatError("n_views must be a positive integer, got 0; set radiographs.n_views")
    Traceback (most recent call last):
        ...
    ctsplat.utils.CtsplatError: n_views must be a positive integer, got 0; set radiographs.n_views
    """


class LoggedWarning(UserWarning):
    """A warning that ctsplat also writes to its log: a command or workflow step that routes warnings to the log
    (``logging.captureWarnings``) ignores this category, so that the log says it once."""


def log_warnings_once() -> None:
    """Route Python warnings to the log (``logging.captureWarnings``), except :class:`LoggedWarning`s, which the
    library has logged already; for the CLI and the workflow's steps."""
    logging.captureWarnings(True)
    warnings.filterwarnings("ignore", category=LoggedWarning)


_UMASK = os.umask(0o022)  # reading the process umask requires setting it; put it straight back
os.umask(_UMASK)


class Terminated(KeyboardInterrupt):
    """SIGTERM (what ``kill``, Slurm's cancel and its time limit send) raised like Ctrl-C, so that the cleanup of
    temporary outputs runs."""


def _raise_terminated(signum: int, _frame: Any) -> None:
    raise Terminated(f"terminated by signal {signum}")


def terminate_as_interrupt() -> None:
    """Make SIGTERM raise :class:`Terminated` (a ``KeyboardInterrupt``) in this process's main thread.

    Python's default for SIGTERM ends the process at once, skipping every ``finally``: a killed step would leave
    its temporary files and folders (written under hidden names beside the outputs) behind. The command line and
    the workflow's scripts call this first; elsewhere it does nothing (signal handlers live in the main thread).
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)


@contextlib.contextmanager
def _interrupts_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) and SIGTERM for the block and deliver them when the block ends.

    Creating a temporary file and recording its name are two steps; an interrupt between them would leave a file
    that no cleanup knows of. Python runs signal handlers in the main thread only, so elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, lambda signum, _frame: caught.append(signum)) for sig in held}
    try:
        yield
    finally:
        for sig in held:
            signal.signal(sig, previous[sig])
    for sig in dict.fromkeys(caught):
        if callable(previous[sig]):
            previous[sig](sig, None)
        elif previous[sig] == signal.SIG_DFL:
            signal.raise_signal(sig)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary name keeps the final suffixes (``.x.abc123.tmp.nii.gz``) so writers that infer the format
    from the extension still work. On success the file gets the permissions a plain ``open()`` would give
    (``0o666`` minus the umask) and replaces ``path`` atomically (``os.replace``); on any error the temporary
    file is removed and the exception propagates, so no half-written output is left.

    Parameters
    ----------
    path : str or os.PathLike
        The final output file. Its parent folder is created if missing (and removed again, if still empty, when
        the write fails).

    Raises
    ------
    CtsplatError
        When ``path`` is an existing folder or ends with a path separator.

    Yields
    ------
    pathlib.Path
        The temporary file (already created, empty) to write to.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "table.csv"
    >>> with atomic_path(out) as tmp:
    ...     _ = tmp.write_text("view,psnr2d\\n0,31.2\\n")
    >>> out.read_text().splitlines()
    ['view,psnr2d', '0,31.2']
    """
    text = os.fspath(path)
    path = Path(path)
    # Path() drops a trailing separator, so "out/" would silently become a file named "out"
    if text.endswith((os.sep, os.altsep or os.sep)):
        raise CtsplatError(f"{text} names a folder (it ends in a separator), but a file is to be written there; "
                           f"give a file path, e.g. {path / 'out.csv'} or {path}")
    if path.is_dir():
        raise CtsplatError(f"{text} is a folder, but a file is to be written there; remove or rename the folder, "
                           "or give another file path")
    suffix = "".join(path.suffixes) if path.suffixes else ""
    stem = path.name[: len(path.name) - len(suffix)] if suffix else path.name
    tmp_path: Path | None = None
    with made_parents(path):
        try:
            with _interrupts_held():
                fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".tmp{suffix}", dir=path.parent)
                tmp_path = Path(tmp)
                os.close(fd)
            yield tmp_path
            if tmp_path.is_file():  # mkstemp creates 0600; give the output the permissions a plain open() would
                os.chmod(tmp_path, 0o666 & ~_UMASK)
            os.replace(tmp_path, path)
        except BaseException:
            if tmp_path is not None:
                with contextlib.suppress(FileNotFoundError):
                    tmp_path.unlink()
            raise


def check_output_dir(path: str | os.PathLike[str], *, marker: str | Sequence[str] | None = None,
                     contents: Sequence[str] = (), inputs: Sequence[str | os.PathLike[str]] = (),
                     in_place: bool = False) -> None:
    """Refuse an output folder whose replacement would destroy something that is not an earlier output.

    Parameters
    ----------
    path : str or os.PathLike
        The output folder, to be replaced as a whole (:func:`atomic_dir`).
    marker : str or sequence of str, optional
        Glob patterns, one of which an earlier output of the same step matches inside the folder
        (``"summary.json"``, ``"*.png"``); a non-empty folder without a match is refused. None: only a new or empty
        folder is accepted.
    contents : sequence of str
        Patterns of the other files an earlier output holds, as paths relative to the folder (``fnmatch``: ``*``
        also matches ``/``; ``"figures/*"``). A folder holding a file that matches neither these nor ``marker``
        is refused, whatever else it holds: replacing it would delete that file. Snakemake's
        ``.snakemake_timestamp`` in the folders it made and the temporaries a killed atomic write of an allowed
        file or folder leaves (:func:`atomic_path`, :func:`atomic_dir`) are always allowed.
    inputs : sequence of paths
        The step's inputs: the output may be neither one of them nor a folder that holds one.
    in_place : bool
        The step writes into the folder and replaces only its own files (a training run, CT SfM) instead of
        replacing the folder; only the refusal's reason differs.

    Raises
    ------
    CtsplatError
        One line naming the folder and what to do instead.

    Examples
    --------
    >>> check_output_dir("results/new_run", marker="config.json")
    """
    path = Path(path)
    target = path.resolve()
    for inp in inputs:
        source = Path(inp).resolve()
        if target == source or target in source.parents:
            raise CtsplatError(f"output folder {path} is, or holds, the input {inp}, and writing it would replace "
                               "the input; choose another output folder")
    if not path.exists():
        return
    if not path.is_dir():
        raise CtsplatError(f"output {path} exists and is not a folder; choose a new or empty folder")
    files = sorted(p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file() or p.is_symlink())
    if not files:  # empty sub-folders (as Snakemake makes them) do not count
        return
    markers = [marker] if isinstance(marker, str) else list(marker or ())
    if not any(any(path.glob(m)) for m in markers):
        what = f" (no {' or '.join(markers)} in it)" if 0 < len(markers) <= 3 else ""
        raise CtsplatError(f"output folder {path} already holds files that are not an earlier output of this "
                           f"step{what}; choose a new or empty folder, or remove it first")
    allowed = [*markers, *contents]
    allowed += [leftover for pattern in allowed for leftover in _leftover_patterns(pattern)]
    foreign = [f for f in files if Path(f).name != ".snakemake_timestamp"
               and not any(fnmatch.fnmatchcase(f, pattern) for pattern in allowed)]
    if foreign:
        more = f" and {len(foreign) - 1} more" if len(foreign) > 1 else ""
        why = "its outputs would be mixed with it" if in_place else "replacing the folder would delete it"
        raise CtsplatError(f"output folder {path} holds {foreign[0]}{more}, which this step does not write, and "
                           f"{why}; choose a new or empty folder, or move it away")


def _leftover_patterns(pattern: str) -> list[str]:
    """What a killed atomic write of a file matching ``pattern`` leaves behind (fnmatch patterns, relative paths):
    :func:`atomic_path`'s ``.STEM.<random>.tmpSUFFIXES`` beside it, and :func:`atomic_dir`'s ``.NAME.<random>``
    folder beside each folder on its path."""
    parts = pattern.split("/")
    tail = parts[-1]
    suffix = "".join(Path(tail).suffixes) if not tail.startswith(".") else ""
    stem = tail[: len(tail) - len(suffix)] if suffix else tail
    out = ["/".join([*parts[:-1], f".{stem}.*.tmp{suffix}"])]
    out += ["/".join([*parts[:k], f".{parts[k]}.*"]) for k in range(len(parts) - 1)]
    return out


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike[str], *, marker: str | Sequence[str] | None = None,
               contents: Sequence[str] = (), inputs: Sequence[str | os.PathLike[str]] = ()) -> Iterator[Path]:
    """Yield an empty temporary folder next to ``path``; it replaces ``path`` only if the block succeeds.

    The folder-level twin of :func:`atomic_path`: an existing ``path`` is removed and the temporary folder renamed
    onto it (one file system, so readers see the old folder or the whole new one); on any error the temporary
    folder is removed and the exception propagates, leaving ``path`` as it was. Only an empty folder or an earlier
    output (``marker``, ``contents``) is ever removed, and never an input (:func:`check_output_dir`, called before
    the block and again before the removal).

    Parameters
    ----------
    path : str or os.PathLike
        The final output folder. Its parent folder is created if missing (and removed again, if still empty, when
        the block fails).
    marker, contents, inputs
        As in :func:`check_output_dir`.

    Yields
    ------
    pathlib.Path
        The temporary folder to write into (permissions as a plain ``mkdir`` would give).

    Raises
    ------
    CtsplatError
        When ``path`` may not be replaced (:func:`check_output_dir`).

    Examples
    --------
    >>> with atomic_dir("out/views", marker="views.json") as tmp:
    ...     _ = (tmp / "views.json").write_text("{}")
    """
    path = Path(path)
    check_output_dir(path, marker=marker, contents=contents, inputs=inputs)
    with made_parents(path), scratch_dir(path.parent, prefix=f".{path.name}.") as tmp:
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp creates 0700
        yield tmp
        # the folder may have changed while the block ran
        check_output_dir(path, marker=marker, contents=contents, inputs=inputs)
        if not path.exists():
            os.replace(tmp, path)
            return
        # the old folder goes aside before the new one moves in: an interrupt leaves one whole folder at ``path``,
        # never a half-deleted one (which would no longer look like an earlier output)
        with _interrupts_held():
            aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=path.parent))
            os.replace(path, aside)
            os.replace(tmp, path)
        shutil.rmtree(aside)


@contextlib.contextmanager
def made_parents(path: str | os.PathLike[str]) -> Iterator[list[Path]]:
    """Create the missing parent folders of ``path``; if the block fails, remove those of them left empty.

    A failed write then leaves the file system as it found it, not a trail of empty folders.

    Parameters
    ----------
    path : str or os.PathLike
        A file or folder to be written; its parent folders are created.

    Yields
    ------
    list of pathlib.Path
        The folders created, innermost first (empty when the parent existed).

    Examples
    --------
    >>> import pathlib, tempfile
    >>> root = pathlib.Path(tempfile.mkdtemp())
    >>> try:
    ...     with made_parents(root / "a" / "b" / "out.csv"):
    ...         raise ValueError("the write failed")
    ... except ValueError:
    ...     pass
    >>> (root / "a").exists()
    False
    """
    parent = Path(os.path.abspath(path)).parent  # no ".." entries, which cannot be removed by name
    created: list[Path] = []
    for d in [*reversed(parent.parents), parent]:  # outermost first; only what this call made counts as its own
        try:
            d.mkdir()
            created.insert(0, d)
        except FileExistsError:
            pass
    try:
        yield created
    except BaseException:
        for d in created:
            try:
                d.rmdir()
            except OSError:  # not empty (something else wrote there) or already gone: leave it and its parents
                break
        raise


@contextlib.contextmanager
def scratch_dir(parent: str | os.PathLike[str] | None, *, prefix: str, suffix: str = "") -> Iterator[Path]:
    """Yield a new empty folder in ``parent``; it is removed, with all it holds, when the block ends.

    The folder is removed whether the block succeeds, fails or is interrupted (Ctrl-C included, even one that lands
    while the folder is being created); what the block moved out of it beforehand stays.

    Parameters
    ----------
    parent : str, os.PathLike or None
        Where to create the folder (must exist); None for the system's temporary folder.
    prefix, suffix : str
        Start and end of the folder's random name.

    Yields
    ------
    pathlib.Path
        The folder (mode 0o700, as ``tempfile.mkdtemp`` makes it).

    Examples
    --------
    >>> with scratch_dir(None, prefix="ctsplat-") as work:
    ...     _ = (work / "part.bin").write_bytes(b"x")
    >>> work.exists()
    False
    """
    tmp: Path | None = None
    try:
        with _interrupts_held():
            tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=parent))
        yield tmp
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def is_finite_real(value: Any) -> bool:
    """Whether ``value`` is a finite real number (Python or NumPy); a bool is not one, though Python counts it an int.

    Examples
    --------
    >>> [is_finite_real(v) for v in (1, 2.5, np.float32(3), True, float("nan"), "1", None)]
    [True, True, True, False, False, False, False]
    """
    return not isinstance(value, bool) and isinstance(value, numbers.Real) and math.isfinite(value)


def first_nonfinite(obj: Any, where: str = "") -> str | None:
    """Key path (``a.b[2]``) of the first NaN/Infinity in ``obj``, or None."""
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if isinstance(obj, float | np.floating):
        return None if math.isfinite(obj) else where
    if isinstance(obj, dict):
        items = ((f"{where}.{k}" if where else str(k), v) for k, v in obj.items())
    elif isinstance(obj, list | tuple):
        items = ((f"{where}[{i}]", v) for i, v in enumerate(obj))
    else:
        return None
    for key, value in items:
        found = first_nonfinite(value, key)
        if found is not None:
            return found
    return None


def save_torch_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """``torch.save`` of ``obj`` to ``path`` atomically (:func:`atomic_path`), the same bytes for the same contents.

    The archive is written through a file object: given a path, torch names the archive's inner folder after the
    file, here the random temporary name, so two saves of one model would never be byte-identical.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.pt`` file.
    obj : any
        What ``torch.save`` takes (tensors, dicts, lists, numbers, strings).
    """
    import torch

    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        torch.save(obj, fh)


def read_json_object(path: str | os.PathLike[str], *, what: str, fix: str) -> dict[str, Any]:
    """The JSON object (a mapping) a file holds, or a one-line error naming the file, what is wrong and ``fix``.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    what : str
        What the file is, for the message (``"view set"``, ``"run config"``).
    fix : str
        How to get a good one, for the message (``"re-render the radiographs"``).

    Returns
    -------
    dict
        The parsed object.

    Raises
    ------
    CtsplatError
        When the file is missing, not UTF-8 JSON, or holds something other than an object.

    Examples
    --------
    >>> _ = Path("list.json").write_text("[1, 2]")
    >>> read_json_object("list.json", what="run config", fix="train the run again")
    Traceback (most recent call last):
    ...
    ctsplat.utils.CtsplatError: run config list.json holds a JSON array, not an object; train the run again
    """
    path = Path(path)
    if not path.exists():
        raise CtsplatError(f"{what} {path} does not exist; {fix}")
    if path.is_dir():
        raise CtsplatError(f"{what} {path} is a folder, not a JSON file; give the file itself")
    try:
        obj = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise CtsplatError(f"{what} {path} is not a text (JSON) file; {fix}") from None
    except json.JSONDecodeError as exc:
        raise CtsplatError(f"{what} {path} is not valid JSON ({exc}); {fix}") from None
    if not isinstance(obj, dict):
        kind = {list: "array", str: "string", bool: "boolean", type(None): "null"}.get(type(obj), "number")
        raise CtsplatError(f"{what} {path} holds a JSON {kind}, not an object; {fix}")
    return obj


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented, standard JSON atomically (NumPy scalars/arrays converted).

    NaN and ±Infinity are refused (they are not JSON; strict parsers reject the file): a
    :class:`CtsplatError` names the key path. Values that may legitimately be undefined (metrics)
    go through :func:`json_safe` first, which writes them as ``null``.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (replaced atomically, see :func:`atomic_path`).
    obj : JSON-like
        Dicts, lists, str, int, float, bool, None, NumPy arrays/scalars, Paths. Keys are sorted.

    Raises
    ------
    CtsplatError
        When ``obj`` holds a NaN or ±Infinity; nothing is written.

    Examples
    --------
    >>> write_json_atomic("run/metrics.json", json_safe({"psnr2d": 31.2, "lpips": float("nan")}))
    """
    try:
        text = json.dumps(obj, indent=2, sort_keys=True, default=_json_default, allow_nan=False)
    except ValueError as exc:
        if "Out of range float" not in str(exc):
            raise
        where = first_nonfinite(obj)
        raise CtsplatError(
            f"{path}: refusing to write NaN/Infinity at {where or '<top>'} (not valid JSON); fix the value, or "
            f"pass the object through ctsplat.utils.json_safe to write undefined numbers as null"
        ) from None
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def json_safe(obj: Any) -> Any:
    """A copy of ``obj`` with every non-finite float (NaN, ±Infinity) replaced by ``None`` (JSON ``null``).

    For metrics that can be undefined or unbounded (PSNR of identical images is +Infinity, a median
    over no registered views is NaN). Dicts, lists and tuples are walked; NumPy arrays and scalars
    become lists and Python numbers; everything else is returned unchanged.

    Parameters
    ----------
    obj : JSON-like
        The object to write.

    Returns
    -------
    JSON-like
        The same structure with ``None`` for each non-finite float (tuples become lists).

    Examples
    --------
    >>> json_safe({"psnr": float("inf"), "x": np.float32(1.5), "v": np.arange(2)})
    {'psnr': None, 'x': 1.5, 'v': [0, 1]}
    """
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    return obj


#: What a run's code version covers: the library and what wires it (rules compute parameters, scripts call the
#: library).
CODE_PATHS = ("ctsplat", "workflow", "scripts", "Snakefile")


def code_version(root: str | Path | None = None) -> str:
    """The ``ctsplat`` version, plus the git commit when run from a checkout.

    Parameters
    ----------
    root : str or Path, optional
        The checkout (default: the one this module lies in).

    Returns
    -------
    str
        ``"<version>+g<12-hex commit>"``; when files under :data:`CODE_PATHS` differ from the commit (or are new),
        ``-dirty-<8 hex>`` follows, a SHA-256 of the differences and the new files' contents, so that two edits of
        one commit are two versions (a checkpoint resumes only under its own code). The bare version when git or
        the checkout is unavailable.

    Examples
    --------
    >>> code_version("/nonexistent").count("+g")
    0
    """
    from ctsplat import __version__

    root = Path(root) if root is not None else Path(__file__).resolve().parent.parent

    def git(*args: str) -> bytes:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, timeout=10, check=True).stdout

    try:
        sha = git("rev-parse", "--short=12", "HEAD").decode().strip()
        new = git("ls-files", "--others", "--exclude-standard", "-z", "--", *CODE_PATHS).split(b"\0")
        diff = git("diff", "--binary", "HEAD", "--", *CODE_PATHS)
    except (OSError, subprocess.SubprocessError):
        return __version__
    new = sorted(n for n in new if n)
    if not diff and not new:
        return f"{__version__}+g{sha}"
    h = hashlib.sha256(diff)
    for name in new:
        h.update(b"\0" + name + b"\0")
        with contextlib.suppress(OSError):  # a file removed meanwhile counts by its name
            h.update((root / name.decode(errors="surrogateescape")).read_bytes())
    return f"{__version__}+g{sha}-dirty-{h.hexdigest()[:8]}"


def compute_platform(device: Any = "cpu") -> dict[str, Any]:
    """What decides a run's rounding besides its config, seed and code, for its provenance.

    Torch picks its CPU kernels by the vector instructions the CPU has (AVX2, AVX512, ...), and they sum in other
    orders, so a run repeats bit for bit on a CPU of the same capability with the same threads, and takes another
    path on another one.

    Parameters
    ----------
    device : torch.device or str
        The device the run computes on.

    Returns
    -------
    dict
        ``torch`` (version), ``cpu_capability`` (``torch.backends.cpu.get_cpu_capability()``), ``threads``
        (torch's intra-op threads), ``gpu`` (the CUDA device's name; None on CPU).

    Examples
    --------
    >>> sorted(compute_platform())
    ['cpu_capability', 'gpu', 'threads', 'torch']
    """
    import torch

    dev = torch.device(device)
    return {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "threads": torch.get_num_threads(),
            "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None}


def config_hash(config: Any) -> str:
    """Stable 16-hex-digit SHA-256 prefix of a JSON-serialisable config (key order ignored).

    Parameters
    ----------
    config : JSON-like
        The config; values JSON cannot encode are hashed by their ``str()``.

    Returns
    -------
    str
        The first 16 hex digits of the SHA-256 of the compact, key-sorted JSON text.

    Examples
    --------
    >>> config_hash({"a": 1})
    '015abd7f5cc57a2d'
    """
    blob = json.dumps(config, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def resolve_device(device: str = "auto") -> torch.device:
    """The torch device for a config value: ``auto`` picks CUDA when available, else CPU.

    Parameters
    ----------
    device : {"auto", "cpu", "cuda", "cuda:N"}
        The requested device.

    Returns
    -------
    torch.device
        The device to compute on.

    Raises
    ------
    CtsplatError
        For ``cuda`` without a CUDA GPU, or an unknown device name.
    """
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise CtsplatError("device 'cuda' requested but no CUDA GPU is available; use device: auto or cpu")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise CtsplatError(f"unknown device {device!r}; allowed: auto, cpu, cuda")
    return torch.device(device)


#: The largest random seed: what NumPy's legacy generators and every RNG the steps use accept (0 .. 2³² − 1).
SEED_MAX = 2**32 - 1


def seed_everything(seed: int) -> np.random.Generator:
    """Seed Python's, NumPy's global and torch's random number generators.

    Parameters
    ----------
    seed : int
        The seed (NumPy's global generator gets ``seed mod 2**32``).

    Returns
    -------
    numpy.random.Generator
        A fresh generator seeded with ``seed``, for code that draws explicitly.
    """
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))  # noqa: NPY002  (legacy global RNG used by some libraries)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


#: The lock file a step holds in the folder it writes (:func:`run_lock`).
LOCK_NAME = ".ctsplat.lock"

# folders this process holds a lock on -> (open lock file, nesting depth): flock locks belong to an open file, so a
# second open() in the same process would block itself; nested run_lock calls reuse the first one instead
_HELD_LOCKS: dict[str, list[Any]] = {}


@contextlib.contextmanager
def run_lock(folder: str | os.PathLike[str], what: str = "run folder") -> Iterator[Path]:
    """Hold an exclusive lock on an output folder while a step writes it; fail fast if another process holds it.

    The lock is ``fcntl.flock`` on ``folder/.ctsplat.lock``, which records the holder's pid and command. The
    kernel releases it when the holder exits, however it ends (a killed job leaves no stale lock; the file
    stays, unlocked). Nested calls for the same folder in one process share the outer lock. When the step fails
    in a folder that this call created and that holds nothing but the lock file, the folder is removed: a run
    that failed on its inputs leaves nothing behind.

    Parameters
    ----------
    folder : path
        The output folder (created if missing).
    what : str
        How the message names the folder (``run folder``, ``output folder``).

    Yields
    ------
    pathlib.Path
        The lock file.

    Raises
    ------
    CtsplatError
        When another process holds the lock (naming its pid), or the folder cannot be created or written.
    """
    import fcntl

    folder = Path(folder)
    created = not folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        key = str(folder.resolve())
        if not os.access(folder, os.W_OK | os.X_OK):  # an existing lock file opens even in a read-only folder
            raise PermissionError(13, "Permission denied")
    except OSError as exc:
        raise CtsplatError(f"{what} {folder} is not writable ({exc.strerror or exc}); choose another folder or fix "
                           "its permissions") from exc
    lock_path = folder / LOCK_NAME
    held = _HELD_LOCKS.get(key)
    if held is not None:
        held[1] += 1
        try:
            yield lock_path
        finally:
            held[1] -= 1
        return
    try:
        fh = open(lock_path, "a+")  # noqa: SIM115 - kept open for the lifetime of the lock
    except OSError as exc:
        raise CtsplatError(f"{what} {folder} is not writable ({exc.strerror or exc}); choose another folder or fix "
                           "its permissions") from exc
    failed_empty = False
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read().strip().splitlines()
            pid = holder[0] if holder else "unknown"
            cmd = f" ({holder[1]})" if len(holder) > 1 else ""
            raise CtsplatError(f"{what} {folder} is in use by another ctsplat process (pid {pid}{cmd}); wait for it "
                               "to finish or choose another folder") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"{os.getpid()}\n{_command_name()}\n")
        fh.flush()
        _HELD_LOCKS[key] = [fh, 1]
        try:
            yield lock_path
        except BaseException:
            failed_empty = created and {p.name for p in folder.iterdir()} <= {LOCK_NAME}
            raise
        finally:
            del _HELD_LOCKS[key]
            # the file is left in place: removing it would let a waiting process lock an unlinked inode while a
            # third one creates and locks a new file
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)
    finally:
        fh.close()
        if failed_empty:
            shutil.rmtree(folder, ignore_errors=True)


def _command_name() -> str:
    """A short name of this process's command for lock messages (``ctsplat train``, ``train.py``), no arguments."""
    argv = sys.argv or ["python"]
    name = Path(argv[0]).name if argv[0] not in ("-c", "-m", "") else f"python {argv[0]}".strip()
    if name in ("ctsplat", "__main__.py") and len(argv) > 1 and argv[1].isidentifier():
        name = f"ctsplat {argv[1]}"
    return name


def deep_update(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` applied key by key: nested dicts are merged, any other value replaces (no checks).

    Examples
    --------
    >>> deep_update({"densify": {"interval": 100, "strategy": "gradient"}}, {"densify": {"strategy": "error"}})
    {'densify': {'interval': 100, 'strategy': 'error'}}
    """
    out = dict(base)
    for k, v in over.items():
        out[k] = deep_update(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def dotted_items(d: Mapping[str, Any], *, lists_as_json: bool = False) -> dict[str, Any]:
    """The leaves of a nested mapping under dotted keys (``densify.strategy``), in the mapping's order.

    Parameters
    ----------
    d : mapping
        Nested sections (mappings); any other value is a leaf.
    lists_as_json : bool
        Write list and tuple leaves as JSON text, so that each value fits one CSV cell.

    Returns
    -------
    dict
        Dotted key -> leaf value.

    Examples
    --------
    >>> dotted_items({"iterations": 6000, "densify": {"strategy": "mcmc", "steps": [1, 2]}}, lists_as_json=True)
    {'iterations': 6000, 'densify.strategy': 'mcmc', 'densify.steps': '[1, 2]'}
    """
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update({f"{k}.{sub}": leaf for sub, leaf in dotted_items(v, lists_as_json=lists_as_json).items()})
        elif lists_as_json and isinstance(v, list | tuple):
            out[str(k)] = json.dumps(v)
        else:
            out[str(k)] = v
    return out


def unknown_key_message(section: str, key: Any, allowed: Iterable[str]) -> str:
    """One line for a config key ``section.key`` that is not among ``allowed``: the closest allowed key, if one is
    close, and the list.

    Examples
    --------
    >>> unknown_key_message("train", "iteratons", ["iterations", "lr"])
    'unknown config key train.iteratons (did you mean iterations?); allowed keys in train: iterations, lr'
    """
    allowed = sorted(str(a) for a in allowed)
    close = difflib.get_close_matches(str(key), allowed, n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    path, where = (f"{section}.{key}", f"in {section}") if section else (str(key), "at the top level")
    return f"unknown config key {path}{hint}; allowed keys {where}: {', '.join(allowed)}"


def merge_config(section: str, user: dict[str, Any] | None, defaults: dict[str, Any]) -> dict[str, Any]:
    """Fill a user config section with its defaults (recursively); unknown keys fail fast naming their path.

    Parameters
    ----------
    section : str
        Name of the section, used in error messages (``train``, ``radiographs.noise``).
    user : dict or None
        The user's values; ``None`` means all defaults.
    defaults : dict
        Every allowed key with its default. A nested dict default is merged key by key when the user gives a
        dict for it; any other user value replaces the default whole.

    Returns
    -------
    dict
        The merged section, keys in the order of ``defaults``.

    Raises
    ------
    CtsplatError
        When ``user`` has a key that ``defaults`` lacks (the message lists the allowed keys).

    Examples
    --------
    >>> merge_config("train", {"iterations": 10}, {"iterations": 100, "lr": 3e-3})
    {'iterations': 10, 'lr': 0.003}
    """
    user = dict(user or {})
    unknown = sorted(set(user) - set(defaults))
    if unknown:
        raise CtsplatError(unknown_key_message(section, unknown[0], defaults))
    out: dict[str, Any] = {}
    for key, default in defaults.items():
        if key in user and isinstance(default, dict) and default and isinstance(user[key], dict):
            out[key] = merge_config(f"{section}.{key}", user[key], default)
        else:
            out[key] = user.get(key, default)
    return out


#: the tensor methods through which the host reads a tensor's values (on a GPU each waits for the queued work)
HOST_READS = ("item", "__bool__", "__int__", "__float__", "__index__", "tolist")


@contextlib.contextmanager
def count_host_reads() -> Iterator[Counter]:
    """Count the reads of tensor values made directly by ctsplat code while the context is open.

    Wraps the :data:`HOST_READS` methods of ``torch.Tensor`` (restored on exit) and counts each call whose immediate
    caller is a file under ``ctsplat/``; reads inside torch (e.g. Adam's step counters) are not counted. Keys are
    ``(method, "path/in/ctsplat.py:line", function, source line)``. A diagnostic for the GPU path (each such read of
    a device tensor is a host synchronisation); it counts reads of CPU tensors too, which the caller can tell apart
    by the site.

    Yields
    ------
    collections.Counter
        Filled while the context is open.

    Examples
    --------
    >>> import torch
    >>> with count_host_reads() as reads:
    ...     _ = float(torch.ones(()))  # this caller is not in ctsplat/
    >>> sum(reads.values())
    0
    """
    import torch

    reads: Counter = Counter()
    marker = "ctsplat" + os.sep
    originals = {name: getattr(torch.Tensor, name) for name in HOST_READS}

    def wrap(name: str, orig: Any) -> Any:
        def read(self: Any, *args: Any, **kwargs: Any) -> Any:
            caller = traceback.extract_stack(limit=2)[0]
            if marker in caller.filename:
                site = f"{caller.filename.split(marker)[-1]}:{caller.lineno}"
                reads[(name, site, caller.name, (caller.line or "").strip())] += 1
            return orig(self, *args, **kwargs)

        return read

    for name, orig in originals.items():
        setattr(torch.Tensor, name, wrap(name, orig))
    try:
        yield reads
    finally:
        for name, orig in originals.items():
            setattr(torch.Tensor, name, orig)
