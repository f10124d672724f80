"""The public planning API: a trained checkpoint, one observation in, waypoints in the robot's base frame out.

    from adlpipe.deploy import Observation, Planner
    planner = Planner.load("models/fm_cnn/best.pt")            # device="cuda" on a GPU box
    obs = Observation(rgb=frames, affordance=amap, state=state, command=last_command, task="wipe the nose")
    plan = planner.plan(obs)
    plan.waypoints, plan.times                                   # (Tp, 3) metres in base_link, seconds from now

The same code path as replay: the observation goes through the dataset's own observation builder and the model's
statistics, so what a robot runs is what adlpipe evaluated.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..dataset.loader import STATE_DIM, Normalizer, normalize_state, observation_from_arrays
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement, resolve_device, synchronize, to_device
from ..policy.checkpoint import CHECKPOINTS, load_policy
from ..policy.models import Policy
from .wire import MAX_SIDE, WireError


@dataclass
class Observation:
    """What a robot sees at one re-plan, oldest frame first (To = Planner.spec.n_obs frames; 1 for first-frame
    models). Images at any size (resized as in training); the affordance map in [0, 1] marks where to act."""

    rgb: np.ndarray | None = None  # (To, H, W, 3) uint8
    affordance: np.ndarray | None = None  # (H, W) float32 in [0, 1]
    depth: np.ndarray | None = None  # (To, H, W) float32 metres, NaN where the sensor had no return; optional
    state: np.ndarray | None = None  # (To, D): closed-loop ADL models the measured tcp x, y, z (m, base) and gripper
    command: np.ndarray | None = None  # (3,) the last commanded tcp: the anchor of a command-target model's plan
    task: str = ""


@dataclass
class Plan:
    """A plan: waypoints in the base frame at times after the observation. First-frame models plan the whole
    trajectory (times at the task's demonstrated speed, pixels beside it); closed-loop models the next Tp waypoints
    at their rate. State models (target "action") plan the bag's action stream instead (`actions`)."""

    waypoints: np.ndarray | None  # (Tp, 3) metres in the base frame; None for an action-stream model
    times: np.ndarray  # (Tp,) seconds after the observation
    pixels: np.ndarray | None = None  # (Tp, 2) u, v in the camera image (first-frame models)
    actions: np.ndarray | None = None  # (Tp, D) the action stream (target "action")
    # The models plan no gripper command: in the ADL world the grasp closes on contact and opens at the end.
    gripper: np.ndarray | None = None
    inference_ms: float = 0.0


@dataclass(frozen=True)
class PlannerSpec:
    """What a planner expects and returns: sent to every client when it connects (wire: a plain map)."""

    model: str
    family: str
    steps: int
    n_obs: int
    image: bool
    depth: bool
    state_dim: int  # per frame; 0: no state input
    needs_command: bool
    horizon: int
    rate_hz: float  # 0: a first-frame model (the whole trajectory)
    target: str
    tasks: tuple[str, ...] = ()  # () : any task name
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "extra"}
        return {**d, "tasks": list(self.tasks), **self.extra}


class Planner:
    """A loaded policy that plans from live observations; one per process or device."""

    def __init__(self, policy: Policy, ck: dict, steps: int | None, placement: Placement,
                 task_speeds: dict[str, float] | None, tasks: list[str] | None, name: str) -> None:
        self.policy, self.placement = policy, placement
        self.cfg = cfg = policy.cfg
        self.norm = Normalizer(ck["stats"])
        self.stats = ck["stats"]
        self.steps = steps or policy.default_steps
        self.task_speeds = dict(task_speeds or {})
        self.generator = placement.generator(0)
        if cfg.views > 1:
            raise AdlError(f"{name}: sees cameras {', '.join(cfg.cameras)}; the planner takes one camera")
        known = tuple(tasks or self.task_speeds or ())
        self.spec = PlannerSpec(
            model=cfg.model, family=policy.family, steps=self.steps, n_obs=cfg.n_obs if cfg.closed_loop else 1,
            image=cfg.use_image, depth=cfg.use_depth, state_dim=cfg.state_dim // max(cfg.n_obs, 1),
            needs_command=cfg.closed_loop and cfg.target == "command", horizon=cfg.horizon, rate_hz=cfg.rate_hz,
            target=cfg.target, tasks=known, extra={"checkpoint": name, "method": policy.default_method})

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu", steps: int | None = None,
             task_speeds: dict[str, float] | None = None, tasks: list[str] | None = None) -> Planner:
        """A checkpoint (a model folder: its best.pt, or a .pt file) on `device` ("cpu", "cuda", "cuda:1", "auto").
        steps: sampler steps (default: the objective's own, FM 1, DP 16). task_speeds (m/s per task): the speed a
        first-frame model's trajectory is run at (evaluation.replay.demonstrated_speeds); tasks: the task names
        accepted (default: those of task_speeds, else any)."""
        path = Path(path)
        if path.is_dir():
            path = path / CHECKPOINTS["best"] if (path / CHECKPOINTS["best"]).is_file() else path / CHECKPOINTS["last"]
        return cls.at(path, Placement(resolve_device(device)), steps, task_speeds, tasks)

    @classmethod
    def at(cls, path: Path, placement: Placement, steps: int | None = None,
           task_speeds: dict[str, float] | None = None, tasks: list[str] | None = None) -> Planner:
        """load() with a runtime Placement (device, precision, compilation), as the stages run it."""
        if steps is not None and (steps < 1 or steps > 1000):
            raise AdlError(f"steps {steps}: use 1 to 1000")
        policy, ck = load_policy(path, placement)
        return cls(policy, ck, steps, placement, task_speeds, tasks, str(path))

    def check(self, obs: Observation) -> None:
        """WireError naming the first field that does not fit this planner (shape, dtype, range, task)."""
        s, to = self.spec, self.spec.n_obs
        if s.tasks and obs.task not in s.tasks:
            raise WireError(f"task {obs.task!r} is not one of this policy's tasks ({', '.join(s.tasks)})")
        if s.image:
            if obs.rgb is None or obs.affordance is None:
                raise WireError(f"missing field {'rgb' if obs.rgb is None else 'affordance'!r}")
            if obs.rgb.dtype != np.uint8:
                raise WireError(f"field 'rgb' has dtype {obs.rgb.dtype}, not uint8")
            if obs.rgb.ndim != 4 or obs.rgb.shape[0] != to or obs.rgb.shape[3:] != (3,):
                raise WireError(f"field 'rgb' has shape {obs.rgb.shape}, not ({to}, H, W, 3)")
            h, w = obs.rgb.shape[1:3]
            if not (8 <= h <= MAX_SIDE and 8 <= w <= MAX_SIDE):
                raise WireError(f"field 'rgb' is {h}x{w} px; images are 8 to {MAX_SIDE} px a side")
            if obs.affordance.shape != (h, w):
                raise WireError(f"field 'affordance' has shape {obs.affordance.shape}, not the image's ({h}, {w})")
            if obs.depth is not None and obs.depth.shape != (to, h, w):
                raise WireError(f"field 'depth' has shape {obs.depth.shape}, not ({to}, {h}, {w})")
        if s.state_dim:
            if obs.state is None:
                raise WireError("missing field 'state'")
            if obs.state.shape != (to, s.state_dim):
                raise WireError(f"field 'state' has shape {obs.state.shape}, not ({to}, {s.state_dim})")
        if s.needs_command:
            if obs.command is None:
                raise WireError("missing field 'command' (the last commanded tcp: this policy plans from it)")
            if obs.command.shape != (3,):
                raise WireError(f"field 'command' has shape {obs.command.shape}, not (3,)")
        if not s.rate_hz and s.target != "action" and obs.task not in self.task_speeds:
            raise WireError(f"task {obs.task!r}: no demonstrated speed to time this first-frame model's plan "
                            "(load it with task_speeds, or serve --data)")
        for name in ("rgb", "affordance", "state", "command"):
            a = getattr(obs, name)
            if a is not None and a.dtype.kind == "f" and not np.isfinite(a).all():
                raise WireError(f"field {name!r} holds NaN or infinite values")

    def _inputs(self, obs: Observation) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        if cfg.use_image:
            assert obs.rgb is not None and obs.affordance is not None  # check() said so
            depth = obs.depth if cfg.use_depth else None
            image = np.concatenate([observation_from_arrays(
                obs.rgb[k], obs.affordance.astype(np.float32), None if depth is None else depth[k],
                cfg.image_size, cfg.use_depth) for k in range(obs.rgb.shape[0])])
            image_t = torch.from_numpy(image)[None]
        else:
            image_t = torch.zeros(1, 0)
        if not cfg.state_dim:
            return image_t
        state = np.asarray(obs.state, np.float64)[:, :cfg.state_dim // cfg.n_obs]
        return (image_t, normalize_state(state, self.stats)[None])

    def plan(self, obs: Observation, generator: torch.Generator | None = None, steps: int | None = None) -> Plan:
        """The plan for one observation (checked first: a WireError names a field that does not fit). generator:
        the sampler's noise (default: the planner's own, seeded 0 at load, drawn from plan after plan); steps: the
        sampler's steps (default: the planner's)."""
        self.check(obs)
        cfg = self.cfg
        t0 = time.perf_counter()
        with torch.inference_mode(), self.placement.autocast():
            inputs = to_device(self._inputs(obs), self.placement.device)
            pred = self.policy.predict(inputs, steps or self.steps, None,  # type: ignore[arg-type]
                                       generator or self.generator)
            synchronize(self.placement.device)
        out = self.norm.unnormalize(pred.float().cpu())[0].numpy().astype(np.float64)
        ms = 1000.0 * (time.perf_counter() - t0)
        if cfg.target == "action":
            rate = cfg.rate_hz or 10.0
            return Plan(None, np.arange(1, len(out) + 1) / rate, actions=out, inference_ms=ms)
        if cfg.closed_loop:
            anchor = obs.command if cfg.target == "command" else np.asarray(obs.state)[-1, :3]
            return Plan(np.asarray(anchor, np.float64) + out[:, 2:], np.arange(1, len(out) + 1) / cfg.rate_hz,
                        inference_ms=ms)
        waypoints = out[:, 2:]
        duration = max(float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())
                       / self.task_speeds[obs.task], 1.0)  # as replay's fixed speed profile runs it
        return Plan(waypoints, np.linspace(0.0, duration, len(waypoints)), pixels=out[:, :2], inference_ms=ms)


STATE_SIZE = STATE_DIM  # the ADL closed-loop state per frame: tcp x, y, z and the gripper joint
