"""Training checkpoints: the full optimisation state, every random generator and the logs so far, so a resumed run
continues bit-for-bit on CPU.

A checkpoint also carries the text of ``train_log.csv`` and ``per_view.csv`` up to its iteration: a workflow
manager deletes the declared outputs of a killed job before rerunning it, and the resumed run rewrites its logs
from the checkpoint. :func:`find_resumable` picks the newest *readable* checkpoint: a truncated or empty newest
file (a kill while the file system was flushing) is moved aside with a warning and the older one is used.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.training.state import TrainState, make_optimizer
from ctsplat.utils import CtsplatError, save_torch_atomic

__all__ = ["CHECKPOINT_LOGS", "Checkpoint", "checkpoint_dir", "list_checkpoints", "latest_checkpoint",
           "save_checkpoint", "read_checkpoint", "load_checkpoint", "find_resumable"]

log = logging.getLogger(__name__)

#: Run-folder logs whose text is stored in each checkpoint (restored on resume).
CHECKPOINT_LOGS = ("train_log.csv", "per_view.csv")

_FORMAT = "ctsplat.train_checkpoint"


def checkpoint_dir(out_dir: Path) -> Path:
    """The run folder's ``checkpoints/``.

    Parameters
    ----------
    out_dir : pathlib.Path
        Run folder.

    Returns
    -------
    pathlib.Path
        ``out_dir/checkpoints``.
    """
    return out_dir / "checkpoints"


def list_checkpoints(out_dir: Path) -> list[Path]:
    """The ``ckpt_*.pt`` files of a run folder, oldest first (by iteration).

    Parameters
    ----------
    out_dir : pathlib.Path
        Run folder.

    Returns
    -------
    list of pathlib.Path
        Possibly empty.
    """
    return sorted(checkpoint_dir(out_dir).glob("ckpt_*.pt"))


def latest_checkpoint(out_dir: Path) -> Path | None:
    """The newest ``ckpt_*.pt`` of a run folder (readable or not), or None.

    Parameters
    ----------
    out_dir : pathlib.Path
        Run folder.

    Returns
    -------
    pathlib.Path or None
    """
    files = list_checkpoints(out_dir)
    return files[-1] if files else None


def save_checkpoint(out_dir: Path, state: TrainState, rng: np.random.Generator, gen: torch.Generator,
                    cfg_hash: str, keep: int) -> Path:
    """Write ``checkpoints/ckpt_{iteration:08d}.pt`` atomically and keep the newest ``keep``.

    Parameters
    ----------
    out_dir : pathlib.Path
        Run folder; the text of its :data:`CHECKPOINT_LOGS` (as they are now) goes into the checkpoint.
    state : TrainState
        Parameters, Adam state, counters and schedules.
    rng, gen : numpy Generator, torch Generator
        The run's random generators (their states are stored, with torch's global one).
    cfg_hash : str
        The run's resume key (:func:`ctsplat.training.loop.resume_key`: config, inputs, code); a resume with
        another one is refused.
    keep : int
        Number of newest checkpoints kept (at least 1).

    Returns
    -------
    pathlib.Path
        The written checkpoint.
    """
    path = checkpoint_dir(out_dir) / f"ckpt_{state.iteration:08d}.pt"
    logs = {name: (out_dir / name).read_text() for name in CHECKPOINT_LOGS if (out_dir / name).is_file()}
    payload = {
        "format": _FORMAT,
        "config_hash": cfg_hash,
        "iteration": state.iteration,
        "params": {k: v.detach().cpu() for k, v in state.params.items()},
        "optimizer": state.opt.state_dict(),
        "grad_accum": state.grad_accum.cpu(),
        "grad_count": state.grad_count.cpu(),
        "err_accum": None if state.err_accum is None else state.err_accum.cpu(),
        "err_count": None if state.err_count is None else state.err_count.cpu(),
        "lr_factor": state.lr_factor,
        "nan_events": state.nan_events,
        "nan_consecutive": state.nan_consecutive,
        "nan_iters": list(state.nan_iters),
        "elapsed_s": state.elapsed_s,
        "queue": state.queue,
        # the mip filter of the last densify step: recomputed from the current means it would differ (cone beam)
        "filter_var": None if state.filter_var is None else state.filter_var.detach().cpu(),
        "densify_counts": state.densify_counts,
        "health": dict(state.health),
        "logs": logs,
        "pose": None if state.pose is None else {"corrections": state.pose.state(),
                                                  "optimizer": state.pose_opt.state_dict()},
        "np_rng": json.dumps(rng.bit_generator.state),
        "torch_gen": gen.get_state(),
        "torch_rng": torch.get_rng_state(),
    }
    save_torch_atomic(path, payload)
    for old in list_checkpoints(out_dir)[:-max(1, keep)]:
        old.unlink(missing_ok=True)
    return path


@dataclass
class Checkpoint:
    """A checkpoint read into memory (nothing restored yet).

    Attributes
    ----------
    path : pathlib.Path
    config_hash : str
        The resume key it was written with (:func:`ctsplat.training.loop.resume_key`).
    iteration : int
    payload : dict
        Everything :func:`save_checkpoint` stored.
    """

    path: Path
    config_hash: str
    iteration: int
    payload: dict[str, Any]


def _first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message, else its type name (never raises)."""
    for line in str(exc).splitlines():
        if line.strip():
            return line.strip()
    return type(exc).__name__


def read_checkpoint(path: Path) -> Checkpoint:
    """Read and sanity-check a checkpoint file.

    Parameters
    ----------
    path : pathlib.Path
        A ``ckpt_*.pt`` file.

    Returns
    -------
    Checkpoint

    Raises
    ------
    CtsplatError
        The file is empty, truncated, unreadable or not a ctsplat training checkpoint (one line naming it).
    """
    try:
        size = path.stat().st_size
        if size == 0:
            raise CtsplatError(f"cannot read checkpoint {path}: the file is empty")
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except CtsplatError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds (EOFError, RuntimeError, pickle errors)
        raise CtsplatError(f"cannot read checkpoint {path}: {_first_line(exc)}") from exc
    if not isinstance(ck, dict) or ck.get("format") != _FORMAT:
        raise CtsplatError(f"{path} is not a ctsplat training checkpoint")
    missing = [k for k in ("config_hash", "iteration", "params", "optimizer", "np_rng", "torch_gen", "torch_rng")
               if k not in ck]
    if missing:
        raise CtsplatError(f"checkpoint {path} is incomplete (no {', '.join(missing)})")
    return Checkpoint(path, str(ck["config_hash"]), int(ck["iteration"]), ck)


def load_checkpoint(ck: Checkpoint | Path, cfg: dict[str, Any], device: torch.device, rng: np.random.Generator,
                    gen: torch.Generator, voxel_mm: float, cfg_hash: str,
                    half_extent_mm: float | None = None) -> TrainState:
    """Rebuild the training state of a checkpoint written with the same config; restore the generators in place.

    Parameters
    ----------
    ck : Checkpoint or pathlib.Path
        A checkpoint read by :func:`read_checkpoint`, or its file.
    cfg : dict
        The resolved ``train`` config (the optimiser's learning rates).
    device : torch.device
        Where the parameters go.
    rng, gen : numpy Generator, torch Generator
        Set to the checkpoint's states (torch's global generator too).
    voxel_mm : float
        Mean voxel edge (mm), for the mean learning rates.
    cfg_hash : str
        The run's resume key (:func:`ctsplat.training.loop.resume_key`); must equal the checkpoint's.
    half_extent_mm : float, optional
        Half the volume's largest extent (mm), for ``optimizer_preset: method``.

    Returns
    -------
    TrainState

    Raises
    ------
    CtsplatError
        Unreadable checkpoint, or one written with a different config.
    """
    if not isinstance(ck, Checkpoint):
        ck = read_checkpoint(Path(ck))
    if ck.config_hash != cfg_hash:
        raise CtsplatError(f"checkpoint {ck.path} was written with a different config, other inputs or other code "
                           f"(key {ck.config_hash} vs {cfg_hash}); resume with the same ones, or start over "
                           "(ctsplat train --restart)")
    p = ck.payload
    try:
        params = {k: v.to(device).requires_grad_(True) for k, v in p["params"].items()}
        opt = make_optimizer(params, cfg, voxel_mm, half_extent_mm)
        opt.load_state_dict(p["optimizer"])
        state = TrainState(
            params=params, opt=opt, iteration=int(p["iteration"]), grad_accum=p["grad_accum"].to(device),
            grad_count=p["grad_count"].to(device), lr_factor=float(p["lr_factor"]), nan_events=int(p["nan_events"]),
            nan_consecutive=int(p["nan_consecutive"]), nan_iters=[int(i) for i in p.get("nan_iters", [])],
            elapsed_s=float(p["elapsed_s"]), queue=[list(map(int, b)) for b in p["queue"]],
            densify_counts=dict(p["densify_counts"]), health=dict(p.get("health", {})),
        )
        if p.get("err_accum") is not None:
            state.err_accum, state.err_count = p["err_accum"].to(device), p["err_count"].to(device)
        if p.get("filter_var") is not None:
            state.filter_var = p["filter_var"].to(device)
        np_state = json.loads(p["np_rng"])
    except Exception as exc:  # noqa: BLE001 - a damaged payload fails in many ways
        raise CtsplatError(f"cannot read checkpoint {ck.path}: {_first_line(exc)}") from exc
    rng.bit_generator.state = np_state
    gen.set_state(p["torch_gen"])
    torch.set_rng_state(p["torch_rng"])
    return state


def find_resumable(out_dir: Path, cfg_hash: str) -> tuple[Checkpoint | None, list[Path]]:
    """The newest readable checkpoint of a run folder; unreadable newer ones are moved aside.

    Each unreadable file (empty, truncated, not a checkpoint) gets a warning naming it and is renamed to
    ``*.pt.corrupt`` (kept for diagnosis, no longer picked up or counted towards ``keep_checkpoints``).

    Parameters
    ----------
    out_dir : pathlib.Path
        Run folder.
    cfg_hash : str
        The run's resume key (only logged here; :func:`load_checkpoint` enforces it).

    Returns
    -------
    (Checkpoint or None, list of pathlib.Path)
        The checkpoint to resume from (None when there is no readable one) and the files moved aside.
    """
    bad: list[Path] = []
    for path in reversed(list_checkpoints(out_dir)):
        try:
            ck = read_checkpoint(path)
        except CtsplatError as exc:
            aside = path.with_name(path.name + ".corrupt")
            log.warning("%s; moved aside to %s, trying the previous checkpoint", exc, aside.name)
            try:
                path.replace(aside)
            except OSError as move_exc:
                log.warning("could not move %s aside (%s)", path, _first_line(move_exc))
            bad.append(path)
            continue
        if ck.config_hash != cfg_hash:
            log.info("newest checkpoint %s has config hash %s (this run: %s)", path, ck.config_hash, cfg_hash)
        return ck, bad
    return None, bad
