"""Where tensors run: the device a stage asked for, bf16 autocast, and the torch.distributed process group that
torchrun starts (one process per GPU, or per CPU share with the gloo backend).

Every stage that runs a network takes --device auto|cpu|cuda[:N] and --precision fp32|bf16 (add_device_args).
"""

from __future__ import annotations

import contextlib
import os
import platform
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from .cli import Parser
from .errors import AdlError

PRECISIONS = ("fp32", "bf16")


def add_device_args(p: Parser, compile_option: bool = False) -> None:
    p.add_argument("--device", default="auto",
                   help="auto (CUDA when there is one; under torchrun the process's LOCAL_RANK GPU), cpu, cuda or "
                   "cuda:N (default auto)")
    p.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="bf16: the networks run under bfloat16 autocast (weights, sampler and losses stay fp32)")
    if compile_option:
        p.add_argument("--compile", action="store_true",
                       help="torch.compile the networks for inference (the first call compiles: slow once)")


def resolve_device(name: str) -> torch.device:
    """The torch device for --device, or a one-line error when it does not exist here."""
    local = int(os.environ.get("LOCAL_RANK", 0))
    if name == "auto":
        return torch.device("cuda", local % torch.cuda.device_count()) if torch.cuda.is_available() else \
            torch.device("cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise AdlError(f"--device {name}: not a device; use auto, cpu, cuda or cuda:N") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise AdlError(f"--device {name}: adlpipe runs on cpu or cuda")
    if not torch.cuda.is_available():
        raise AdlError(f"--device {name}: no CUDA device on this machine (torch {torch.__version__}, "
                       f"built for CUDA {torch.version.cuda or 'none'}); use --device cpu or auto")
    count = torch.cuda.device_count()
    index = dev.index if dev.index is not None else local
    if index >= count:
        raise AdlError(f"--device {name}: this machine has {count} CUDA device(s)")
    return torch.device("cuda", index)


@dataclass(frozen=True)
class Placement:
    """Where and how inference runs: the device, the precision, and whether the networks are compiled."""

    device: torch.device = torch.device("cpu")
    precision: str = "fp32"
    compile: bool = False

    @classmethod
    def from_args(cls, args: Any) -> Placement:  # the parsed options (add_device_args)
        return cls(resolve_device(args.device), args.precision, bool(getattr(args, "compile", False)))

    def autocast(self) -> contextlib.AbstractContextManager:
        return autocast(self.device, self.precision)

    def generator(self, seed: int) -> torch.Generator:
        return generator(self.device, seed)


def host(device: torch.device) -> dict:
    """The machine a timing was measured on (stated beside every latency): the CPU's model name, its cores, torch's
    threads and version, and the GPU's name when the device is one."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    out = {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "torch": torch.__version__}
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    return out


def autocast(device: torch.device, precision: str) -> contextlib.AbstractContextManager:
    """bfloat16 autocast on the device for bf16 (no gradient scaler needed: bf16 has fp32's range), else nothing."""
    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued kernels: a clock read after this measures the work, not its launch."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def generator(device: torch.device, seed: int) -> torch.Generator:
    """A seeded generator on the device the noise is drawn on (a CPU generator cannot draw CUDA tensors)."""
    return torch.Generator(device=device).manual_seed(seed)


def to_device(obj: object, device: torch.device) -> object:
    """Tensors (also inside lists and tuples) moved to the device; pinned CPU memory copies asynchronously."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device, non_blocking=True)
    if isinstance(obj, tuple | list):
        return type(obj)(to_device(o, device) for o in obj)
    return obj


@dataclass(frozen=True)
class Ranks:
    """This process's place in the run: rank 0 of 1 without torchrun."""

    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0


@contextlib.contextmanager
def process_group(device: torch.device) -> Iterator[Ranks]:
    """Join the process group torchrun describes (WORLD_SIZE > 1): NCCL between GPUs, gloo on the CPU; leave it
    on the way out. Without torchrun: one process, no group."""
    world = int(os.environ.get("WORLD_SIZE", 1))
    if world <= 1 or not dist.is_available():
        yield Ranks()
        return
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    try:
        yield Ranks(dist.get_rank(), dist.get_world_size())
    finally:
        dist.destroy_process_group()


def all_sum(values: list[float], device: torch.device, ranks: Ranks) -> list[float]:
    """Sums of the values over every process (the values themselves in a single process)."""
    if ranks.world == 1:
        return values
    t = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


def barrier(ranks: Ranks) -> None:
    if ranks.world > 1:
        dist.barrier()
