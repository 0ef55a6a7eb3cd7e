"""Training checkpoints: the full optimisation state and every random generator, so a resumed run continues
bit-for-bit on CPU."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctsplat.training.state import TrainState, make_optimizer
from ctsplat.utils import CtsplatError, atomic_path

__all__ = ["checkpoint_dir", "latest_checkpoint", "save_checkpoint", "load_checkpoint"]


def checkpoint_dir(out_dir: Path) -> Path:
    """The run folder's ``checkpoints/``."""
    return out_dir / "checkpoints"


def latest_checkpoint(out_dir: Path) -> Path | None:
    """The newest ``ckpt_*.pt`` of a run folder, or None."""
    files = sorted(checkpoint_dir(out_dir).glob("ckpt_*.pt"))
    return files[-1] if files else None


def save_checkpoint(out_dir: Path, state: TrainState, rng: np.random.Generator, gen: torch.Generator,
                    cfg_hash: str, keep: int) -> Path:
    """Write ``checkpoints/ckpt_{iteration:08d}.pt`` atomically and keep the newest ``keep``; returns its path."""
    path = checkpoint_dir(out_dir) / f"ckpt_{state.iteration:08d}.pt"
    payload = {
        "format": "ctsplat.train_checkpoint",
        "config_hash": cfg_hash,
        "iteration": state.iteration,
        "params": {k: v.detach().cpu() for k, v in state.params.items()},
        "optimizer": state.opt.state_dict(),
        "grad_accum": state.grad_accum.cpu(),
        "grad_count": state.grad_count.cpu(),
        "lr_factor": state.lr_factor,
        "nan_events": state.nan_events,
        "nan_consecutive": state.nan_consecutive,
        "elapsed_s": state.elapsed_s,
        "queue": state.queue,
        "densify_counts": state.densify_counts,
        "np_rng": json.dumps(rng.bit_generator.state),
        "torch_gen": gen.get_state(),
        "torch_rng": torch.get_rng_state(),
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    for old in sorted(checkpoint_dir(out_dir).glob("ckpt_*.pt"))[:-max(1, keep)]:
        old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: Path, cfg: dict[str, Any], device: torch.device, rng: np.random.Generator,
                     gen: torch.Generator, voxel_mm: float, cfg_hash: str) -> TrainState:
    """Read a checkpoint written with the same config (hash) and restore the random generators in place."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many kinds for corrupt files
        raise CtsplatError(f"cannot read checkpoint {path}: {str(exc).splitlines()[0]}; delete it to restart") from exc
    if ck.get("format") != "ctsplat.train_checkpoint":
        raise CtsplatError(f"{path} is not a ctsplat training checkpoint")
    if ck["config_hash"] != cfg_hash:
        raise CtsplatError(f"checkpoint {path} was written with a different config (hash {ck['config_hash']} vs "
                           f"{cfg_hash}); resume with the same config or start without --resume")
    params = {k: v.to(device).requires_grad_(True) for k, v in ck["params"].items()}
    opt = make_optimizer(params, cfg, voxel_mm)
    opt.load_state_dict(ck["optimizer"])
    rng.bit_generator.state = json.loads(ck["np_rng"])
    gen.set_state(ck["torch_gen"])
    torch.set_rng_state(ck["torch_rng"])
    return TrainState(
        params=params, opt=opt, iteration=int(ck["iteration"]), grad_accum=ck["grad_accum"].to(device),
        grad_count=ck["grad_count"].to(device), lr_factor=float(ck["lr_factor"]), nan_events=int(ck["nan_events"]),
        nan_consecutive=int(ck["nan_consecutive"]), elapsed_s=float(ck["elapsed_s"]),
        queue=[list(map(int, b)) for b in ck["queue"]], densify_counts=dict(ck["densify_counts"]),
    )

