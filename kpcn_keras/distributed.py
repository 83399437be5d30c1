"""Data-parallel training over ``torch.distributed``: the one owner of the process group.

``torchrun`` starts one process per device (or per core share) and tells each where it stands through the
environment: ``RANK`` and ``WORLD_SIZE`` (this process among all of them, over every machine),
``LOCAL_RANK`` (among those of its machine), ``MASTER_ADDR`` and ``MASTER_PORT`` (the rendezvous).
:func:`from_environment` reads them into a :class:`World`; with none set, the world is this one process
and nothing here does anything.

Gradients are averaged by a hook on every trainable weight (:func:`average_gradients`), not by wrapping
the model in ``DistributedDataParallel``: Keras owns the model, its ``fit`` loop, its optimizer and the
``.keras`` files, and a hook leaves all of them as they are. Keras's torch trainer calls ``backward()``
and then ``optimizer.apply(gradients)``; each weight's hook runs once its gradient is complete, so by the
time ``apply`` (gradient clipping included) sees the gradients they are the mean over the processes. Every
process runs the same graph, so the hooks, and their collective calls, fire in the same order in each.
With each process's batch the same size (``kpcn_keras.data.ShardPatches``' slices), the mean of their
gradients of a batch-mean loss is the gradient of the whole global batch.

Every collective runs on the device its backend reduces on: nccl (where CUDA is) has no CPU side, so the
weights broadcast and the gradients averaged are Keras's, already on this process's GPU, and the tensors
made here (the logs' mean) are put on :func:`collective_device`; gloo reduces CPU tensors.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from prep.bounds import is_integer
from prep.parts import LOCAL_RANK, RANK, WORLD_SIZE, LaunchError, launcher_variables
from prep.processes import die_with_parent

ENVIRONMENT = (RANK, WORLD_SIZE, LOCAL_RANK)


@dataclass(frozen=True)
class World:
    """Where this process stands: ``rank`` of ``size`` processes, ``local_rank`` on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    def __post_init__(self):
        for name, value, low in (("size", self.size, 1), ("rank", self.rank, 0), ("local_rank", self.local_rank, 0)):
            if not is_integer(value) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.rank >= self.size:
            raise ValueError(f"rank must be below size ({self.size}), got {self.rank}")

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def writer(self) -> bool:
        """Whether this process writes what a run keeps (checkpoints, logs, config.json): rank 0 alone."""
        return self.rank == 0


def from_environment(environ=None) -> World:
    """The :class:`World` the launcher's variables describe (``os.environ`` by default); a ValueError
    (``prep.parts.LaunchError``, one line on the command line) naming the variable and what it held when
    one is not a number, or when some are set and others not."""
    values = launcher_variables(ENVIRONMENT, environ)
    if values is None:
        return World()
    try:
        return World(rank=values[RANK], size=values[WORLD_SIZE], local_rank=values[LOCAL_RANK])
    except ValueError as exc:
        raise LaunchError(f"{exc} ({', '.join(f'{k}={v}' for k, v in values.items())})") from None


def backend() -> str:
    """nccl where CUDA is, gloo otherwise (this CPU machine)."""
    import torch

    return "nccl" if torch.cuda.is_available() else "gloo"


def start(world: World) -> None:
    """Join the process group of ``world`` (the rendezvous at ``MASTER_ADDR``:``MASTER_PORT``); nothing for
    one process, or when already joined. On CUDA each process takes the device of its ``local_rank``."""
    if not world.distributed:
        return
    import torch
    import torch.distributed as dist

    if dist.is_initialized():
        return
    # a launcher killed outright (a cancelled job) would leave its processes waiting on each other, rank 0
    # holding the run's lock
    die_with_parent(os.getppid())
    if backend() == "nccl":
        torch.cuda.set_device(world.local_rank)
    dist.init_process_group(backend(), rank=world.rank, world_size=world.size)


def stop(world: World) -> None:
    """Leave the process group :func:`start` joined, every process together. Left to the interpreter's
    exit, gloo's threads can be torn down mid-call and the process aborts ("terminate called without an
    active exception")."""
    if not world.distributed:
        return
    import torch.distributed as dist

    if dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def average_gradients(model, world: World) -> list:
    """Make every trainable weight of the Keras ``model`` (torch backend) have, after each backward pass,
    the mean of its gradient over the processes of ``world`` (module docstring). Returns the hooks' handles
    (``handle.remove()`` undoes one); none for one process. Call it for every model built: the hooks belong
    to the weights' tensors."""
    if not world.distributed:
        return []
    import torch.distributed as dist

    size = world.size

    def average(param) -> None:
        dist.all_reduce(param.grad)
        param.grad.div_(size)

    return [weight.value.register_post_accumulate_grad_hook(average)
            for weight in model.trainable_weights]


def barrier(world: World) -> None:
    """Wait until every process of ``world`` is here (rank 0 has written what the others read next)."""
    if world.distributed:
        import torch.distributed as dist

        dist.barrier()


def collective_device(backend_name: str, world: World):
    """The torch device a tensor of ours must be on for a collective of the process group's backend
    ``backend_name``: nccl reduces only CUDA tensors, those of this process's device (:func:`start` took the
    device of its ``local_rank``); gloo, CPU ones. The model's weights and gradients are already where Keras
    put them, on that same device under nccl (Keras's torch backend uses the current CUDA device)."""
    import torch

    if backend_name == "nccl":
        return torch.device("cuda", world.local_rank)
    return torch.device("cpu")


def mean_over_processes(values: dict[str, float], world: World) -> dict[str, float]:
    """``values`` averaged over the processes of ``world`` (each passes its own, same keys in the same
    order): an epoch's training loss of each process is the mean over its slices, so their mean is the
    loss of the global batches."""
    if not world.distributed or not values:
        return dict(values)
    import torch
    import torch.distributed as dist

    # float64: nccl reduces doubles too (ncclFloat64), and a sum of float32 losses would round them
    tensor = torch.tensor(list(values.values()), dtype=torch.float64,
                          device=collective_device(dist.get_backend(), world))
    dist.all_reduce(tensor)
    return {k: float(v) / world.size for k, v in zip(values, tensor.tolist())}


def broadcast_weights(model, world: World) -> None:
    """Give every process rank 0's weights (and non-trainable state): the processes start a phase equal,
    whatever their own initialisation or checkpoint read gave them."""
    if not world.distributed:
        return
    import torch
    import torch.distributed as dist

    with torch.no_grad():
        for weight in model.weights:
            dist.broadcast(weight.value.data, src=0)


__all__ = ["ENVIRONMENT", "World", "average_gradients", "backend", "barrier", "broadcast_weights", "collective_device",
           "from_environment", "mean_over_processes", "start", "stop"]
