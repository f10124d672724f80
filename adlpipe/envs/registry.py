"""The benchmarks the benchmark stage can run: each environment's module, its action size, whether image policies run
on it, what its score and success mean, and its episode limit."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType

from .kitchen import TASKS as KITCHEN_TASKS


@dataclass(frozen=True)
class Benchmark:
    module: str  # adlpipe.envs.<module>: make_env, run_policy, reference, REFERENCES
    title: str
    action_dim: int
    images: bool  # image policies run here (Push-T); state-only policies run on every benchmark
    protocol: str  # what the table's score and success mean
    max_steps: int  # the environment's episode limit
    tasks: tuple[str, ...] = ()  # subtasks whose success rates the table gives (Franka Kitchen's four)

    def env(self) -> ModuleType:
        return importlib.import_module(f"adlpipe.envs.{self.module}")


BENCHMARKS = {
    "pusht": Benchmark("pusht", "Push-T", 2, True,
                       "Score: the mean over episodes of the highest goal coverage reached; success: coverage above "
                       "0.95.", 300),
    "kitchen": Benchmark("kitchen", "Franka Kitchen", 9, False,
                         "Score: the mean share of the four tasks done (microwave, kettle, light switch, slide "
                         "cabinet); success: all four.", 280, KITCHEN_TASKS),
}
