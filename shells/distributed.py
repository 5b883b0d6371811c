"""torch.distributed for the training stages and for rendering frames: the process group and the
few collectives the project uses.

Launch with torchrun (one process per GPU, or several CPU processes), e.g.
``torchrun --nproc-per-node 2 $(which shells-train) --data D --out R``: torchrun sets RANK,
WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT, and `world()` joins the group (backend nccl
on CUDA, gloo on the CPU). Without those variables everything runs as one process and every
function here is a no-op, so the single-process path is unchanged.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    rank: int = 0  # this process, 0 .. size - 1
    size: int = 1  # processes in the job
    local_rank: int = 0  # this process on its machine (its GPU index on CUDA)

    @property
    def main(self) -> bool:
        """Rank 0: the one that writes checkpoints, logs, progress and outputs."""
        return self.rank == 0


def world(device: torch.device | str | None = None) -> World:
    """This process's place in the job, joining the process group on first use when the job has
    more than one process (torchrun's environment variables)."""
    if launched_world() <= 1:
        return World()
    if not dist.is_initialized():
        cuda = device is not None and torch.device(device).type == "cuda"
        dist.init_process_group("nccl" if cuda else "gloo",
                                timeout=datetime.timedelta(minutes=10))
    return World(rank=dist.get_rank(), size=dist.get_world_size(),
                 local_rank=int(os.environ.get("LOCAL_RANK", "0")))


def launched_world() -> int:
    """WORLD_SIZE as torchrun set it (1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def launched_rank() -> int:
    """RANK as torchrun set it (0 without torchrun), before or after the group is joined."""
    return int(os.environ.get("RANK", "0"))


def rank_device(device: torch.device) -> torch.device:
    """The torch device of this rank: its own GPU (cuda:LOCAL_RANK) under torchrun."""
    if device.type != "cuda" or launched_world() <= 1:
        return device
    local = int(os.environ.get("LOCAL_RANK", "0"))
    torch.cuda.set_device(local)
    return torch.device("cuda", local)


def active() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def barrier() -> None:
    if active():
        dist.barrier()


def mean_of(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """The mean over ranks of each value (the same keys on every rank)."""
    if not active():
        return values
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    t /= dist.get_world_size()
    return dict(zip(keys, t.tolist()))


def any_rank(flag: bool, device: torch.device) -> bool:
    """True when ``flag`` is true on at least one rank."""
    if not active():
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


def gather_objects(obj: Any) -> list[Any]:
    """Every rank's ``obj``, in rank order (on every rank)."""
    if not active():
        return [obj]
    out: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj: Any) -> Any:
    """Rank 0's ``obj`` on every rank."""
    if not active():
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def shutdown() -> None:
    """Leave the process group together: every rank waits for the others (rank 0 may still be
    writing), then the group is destroyed."""
    if dist.is_available() and dist.is_initialized():
        try:
            dist.barrier()
        finally:
            dist.destroy_process_group()
