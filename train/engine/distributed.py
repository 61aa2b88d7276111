"""Distributed training through ``torchrun``: one process per GPU (NCCL) or per CPU worker (gloo).

``torchrun`` sets ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK``; without them the run is a single process. Keep
NVLink multicast off on shared multi-GPU hosts (``NCCL_NVLS_ENABLE=0``): :func:`setup` sets it unless the caller
did.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

TIMEOUT = datetime.timedelta(minutes=30)
"""How long a collective waits for the other ranks before the run fails (NCCL's own default is 10 minutes). The
first all-reduce waits for every rank's ``torch.compile``, and on 4 GPUs of one host, each rank compiling beside
its simulator workers, ranks were seen waiting over 200 s for the others."""


@dataclass(frozen=True)
class Dist:
    """This process's place in the run."""

    rank: int
    """Global rank, 0 .. world - 1."""
    world: int
    """Number of processes."""
    local_rank: int
    """Rank on this host (the GPU it uses)."""
    device: torch.device
    """The device this process trains on."""

    @property
    def main(self) -> bool:
        """True on rank 0, which writes files and shows progress."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        """True when there is more than one process."""
        return self.world > 1


def setup(device: str | None = None) -> Dist:
    """Join the process group when started by ``torchrun`` and pick this process's device.

    Args:
        device: ``"cpu"``, ``"cuda"`` or None (CUDA when present). Under ``torchrun`` on CUDA each process takes
            GPU ``LOCAL_RANK``.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = torch.cuda.is_available() if device is None else str(device).startswith("cuda")
    if use_cuda:
        dev = torch.device("cuda", local if world > 1 else torch.device(device or "cuda").index or 0)
        _use_cuda_device(dev)
    else:
        dev = torch.device("cpu")
    if world > 1 and not dist.is_initialized():
        os.environ.setdefault("NCCL_NVLS_ENABLE", "0")
        dist.init_process_group("nccl" if use_cuda else "gloo", rank=rank, world_size=world, timeout=TIMEOUT)
    return Dist(rank=rank, world=world, local_rank=local, device=dev)


def _use_cuda_device(dev: torch.device) -> None:
    """Make ``dev`` this process's CUDA device.

    Raises:
        TrainingError: CUDA cannot use the device (held in exclusive mode by another process, or served by a CUDA MPS
            server that a killed run left unusable), in one line that says what to do.
    """
    try:
        torch.cuda.set_device(dev)
    except RuntimeError as e:  # torch.AcceleratorError
        from ..samples import mps_pipe, mps_running
        from .state import TrainingError

        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        reason = reason.removeprefix("CUDA error: ")
        if mps_running():
            hint = (f"CUDA MPS runs here (control pipe in {mps_pipe()}), and a run killed while it held the GPU can "
                    "leave its server unusable: restart it (`echo quit | nvidia-cuda-mps-control`, then "
                    "`nvidia-cuda-mps-control -d`)")
        else:
            hint = "another process may hold it in exclusive mode (`nvidia-smi` lists the processes on each GPU)"
        raise TrainingError(f"{dev}: CUDA cannot use this device ({reason}); {hint}") from None


def teardown() -> None:
    """Leave the process group (if any)."""
    if dist.is_initialized():
        dist.destroy_process_group()


def barrier(d: Dist) -> None:
    """Wait for every rank (no-op for one process)."""
    if d.distributed:
        dist.barrier()


def any_rank(d: Dist, flag: bool) -> bool:
    """True on every rank when ``flag`` is true on any (one all-reduce; every rank must call it at the same step)."""
    if not d.distributed:
        return flag
    t = torch.tensor([1 if flag else 0], dtype=torch.int32, device=d.device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def mean_scalars(d: Dist, values: dict[str, float]) -> dict[str, float]:
    """The mean of each scalar over the ranks (one all-reduce for all of them)."""
    if not d.distributed or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=d.device)
    dist.all_reduce(t)
    t /= d.world
    return dict(zip(keys, t.tolist(), strict=True))
