"""The named policies: an image encoder + a network + an objective, in two size presets.

    fm_cnn           flow matching (clean-trajectory prediction), 1D conditional U-Net   (the paper's method)
    fm_cnn_velocity  flow matching with the paper's velocity target, same U-Net           (ablation)
    fm_transformer   flow matching (clean-trajectory prediction), transformer denoiser
    mf_cnn           MeanFlow (average velocity, clean-trajectory output), same U-Net     (one step, mode-committing)
    mf_transformer   MeanFlow, transformer denoiser
    dp_cnn           Diffusion Policy: DDPM, clean-sample prediction, same U-Net   (FM-x1's like-for-like pair)
    dp_cnn_epsilon   Diffusion Policy: DDPM, noise (epsilon) prediction, same U-Net (the paper's pair of FM-velocity)
    bc_cnn           behaviour cloning, MSE, same U-Net fed a constant input (x = 0, t = 0)
    bc_transformer   behaviour cloning, MSE, transformer regressor                       (the paper's BC)

FM-CNN, DP-CNN and BC-CNN differ only by their objective (FM and DP both output the clean trajectory);
FM-CNN-velocity vs DP-CNN-epsilon is the paper's pair (both output a velocity or noise); FM-Transformer vs
BC-Transformer is the paper's transformer pair.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import torch
from torch import nn

from ..dataset.loader import ACTION_DIM
from .nets.resnet import ResNet18GN
from .nets.transformer import TransformerDenoiser, TransformerRegressor
from .nets.unet1d import ConditionalUnet1D
from .objectives import DDPM, FlowMatching, MeanFlow, MSERegression, Noise, draw_noise

MODELS = {  # name -> (objective, network)
    "fm_cnn": ("fm", "unet"),
    "fm_cnn_velocity": ("fm_velocity", "unet"),
    "fm_transformer": ("fm", "transformer"),
    "mf_cnn": ("meanflow", "unet"),
    "mf_transformer": ("meanflow", "transformer"),
    "dp_cnn": ("ddpm", "unet"),
    "dp_cnn_epsilon": ("ddpm_epsilon", "unet"),
    "bc_cnn": ("mse", "unet_regressor"),
    "bc_transformer": ("mse", "transformer_regressor"),
}
# Each objective's default sampler and step count: what validation selects on, replay runs and the report compares.
DEFAULT_METHOD = {"fm": "euler", "fm_velocity": "euler", "meanflow": "euler", "ddpm": "ddpm", "ddpm_epsilon": "ddpm",
                  "mse": "direct"}
DEFAULT_STEPS = {"fm": 1, "fm_velocity": 1, "meanflow": 1, "ddpm": 16, "ddpm_epsilon": 16, "mse": 1}


@dataclass(frozen=True)
class ModelConfig:
    model: str = "fm_cnn"
    image_size: int = 64
    horizon: int = 32
    use_depth: bool = False
    encoder_width: int = 16  # 64 = standard ResNet-18
    obs_dim: int = 64
    down_dims: tuple[int, ...] = (32, 64, 128)
    kernel: int = 5
    groups: int = 8
    d_model: int = 64
    n_layers: int = 2
    n_heads: int = 4
    n_obs: int = 1  # observation frames stacked as channels (closed loop: 2)
    state_dim: int = 0  # closed loop: the end effector's position at each observation frame (3 * n_obs)
    rate_hz: float = 0.0  # 0: first frame -> whole trajectory (the seed's ADL setting); > 0: next `horizon`
    #                       waypoints at this rate from the current frame (closed loop, adlpipe.dataset.loader.Windows)
    action_dim: int = ACTION_DIM  # waypoint (u, v, x, y, z); with target "action" the recorded action's size
    target: str = "ee"  # closed loop: "ee" (end-effector waypoints) or "action" (the bag's action stream, with its
    #                     state stream as the state input: Push-T, joint-space policies)
    use_image: bool = True  # False: no image encoder, the state alone conditions the network (Franka Kitchen)
    cameras: tuple[str, ...] = ()  # the cameras it sees, in order, each through the one shared encoder (features
    #                                concatenated, as Diffusion Policy does with several image keys); (): the first
    pool: str = "avg"  # the encoder's pooling: "avg" (global average) or "spatial_softmax" (Diffusion Policy's)
    crop: int = 0  # > 0: the encoder sees a crop x crop window: a random one in training (the loader's Augment), the
    #                centre at validation, test and inference (here); 0: the whole image
    per_frame: bool = False  # each observation frame through the shared encoder, features concatenated (Diffusion
    #                          Policy); False: the To frames stacked as channels into one pass

    @property
    def views(self) -> int:
        return max(1, len(self.cameras))

    @property
    def frame_channels(self) -> int:
        return 5 if self.use_depth else 4

    @property
    def in_channels(self) -> int:
        """Channels of one camera's observation stack (To frames)."""
        return self.frame_channels * self.n_obs

    @property
    def encoder_channels(self) -> int:
        """Channels of one encoder pass: a frame (per_frame) or a camera's whole stack."""
        return self.frame_channels if self.per_frame else self.in_channels

    @property
    def encoder_passes(self) -> int:
        """Encoder passes per observation, whose features are concatenated."""
        return self.views * (self.n_obs if self.per_frame else 1)

    @property
    def closed_loop(self) -> bool:
        return self.rate_hz > 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["down_dims"] = list(self.down_dims)
        d["cameras"] = list(self.cameras)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        d = dict(d)
        d["down_dims"] = tuple(d["down_dims"])
        d["cameras"] = tuple(d.get("cameras", ()))
        return cls(**d)


PRESETS = {
    "small": ModelConfig(),  # trains on 2 CPU cores in minutes
    "paper": ModelConfig(image_size=224, encoder_width=64, obs_dim=512, down_dims=(256, 512, 1024), d_model=256,
                         n_layers=6, n_heads=8),
}

# The paper's lr (1e-4) suits its long runs of full-size networks; the small CPU preset trains ~10x fewer steps,
# where 1e-3 converges within the budget (measured on 10 tasks x 40 episodes: FM test loss 0.06 vs 0.42 at 50 epochs).
PRESET_LR = {"small": 1e-3, "paper": 1e-4}


def preset(name: str, model: str, **overrides: object) -> ModelConfig:
    return replace(PRESETS[name], model=model, **overrides)


def make_objective(kind: str) -> FlowMatching | MeanFlow | DDPM | MSERegression:
    if kind == "fm_velocity":
        return FlowMatching("velocity")
    if kind == "ddpm_epsilon":
        return DDPM(prediction="epsilon")
    return {"fm": FlowMatching, "meanflow": MeanFlow, "ddpm": DDPM, "mse": MSERegression}[kind]()


# An observation: image channels (B, C, S, S), or (image channels, normalised state (B, state_dim)) in closed loop.
Observation = torch.Tensor | tuple[torch.Tensor, torch.Tensor]


class UnetRegressor(nn.Module):
    """The conditional U-Net as a regressor: fed a constant input (zeros) at time 0, it maps the observation feature
    to the trajectory through exactly the layers that FM-CNN and DP-CNN use."""

    def __init__(self, unet: ConditionalUnet1D, horizon: int, action_dim: int) -> None:
        super().__init__()
        self.unet, self.horizon, self.action_dim = unet, horizon, action_dim

    def forward(self, cond: torch.Tensor) -> torch.Tensor:
        x = cond.new_zeros(cond.shape[0], self.horizon, self.action_dim)
        return self.unet(x, cond.new_zeros(cond.shape[0]), cond)


class Policy(nn.Module):
    """obs (B, C, S, S) (closed loop: with the state (B, state_dim)) -> normalised trajectory (B, horizon,
    action_dim)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        if cfg.model not in MODELS:
            raise ValueError(f"unknown model {cfg.model!r}; models: {sorted(MODELS)}")
        self.cfg = cfg
        self.kind, net = MODELS[cfg.model]
        self.objective = make_objective(self.kind)
        self.encoder = (ResNet18GN(cfg.encoder_channels, cfg.obs_dim, cfg.encoder_width, cfg.pool) if cfg.use_image
                        else None)
        cond = (cfg.obs_dim * cfg.encoder_passes if cfg.use_image else 0) + cfg.state_dim
        if net in ("unet", "unet_regressor"):
            self.net = ConditionalUnet1D(cfg.action_dim, cond, cfg.down_dims, cfg.kernel, cfg.groups)
            if net == "unet_regressor":
                self.net = UnetRegressor(self.net, cfg.horizon, cfg.action_dim)
        elif net == "transformer":
            self.net = TransformerDenoiser(cfg.action_dim, cond, cfg.horizon, cfg.d_model, cfg.n_layers,
                                           cfg.n_heads)
        else:
            self.net = TransformerRegressor(cfg.action_dim, cond, cfg.horizon, cfg.d_model, cfg.n_layers,
                                            cfg.n_heads)

    @property
    def default_method(self) -> str:
        return DEFAULT_METHOD[self.kind]

    @property
    def default_steps(self) -> int:
        return DEFAULT_STEPS[self.kind]

    @property
    def family(self) -> str:
        """fm, meanflow, ddpm or mse: which samplers apply."""
        return self.kind.split("_")[0]

    def condition(self, obs: Observation) -> torch.Tensor:
        """The image feature, with the normalised state beside it when the model takes one (a state-only model:
        the state alone; its image part is empty)."""
        if isinstance(obs, tuple | list):
            image, state = obs
            return state if self.encoder is None else torch.cat([self.encode(image), state], dim=1)
        return self.encode(obs)

    def encode(self, image: torch.Tensor) -> torch.Tensor:
        """(B, views * C, S, S) -> (B, passes * obs_dim): each camera's stack (per_frame: each frame) through the
        shared encoder. An image larger than the model's crop is centre-cropped (training windows come cropped at
        random by the loader)."""
        crop = self.cfg.crop
        if crop and image.shape[-1] > crop:
            top, left = (image.shape[-2] - crop) // 2, (image.shape[-1] - crop) // 2
            image = image[..., top:top + crop, left:left + crop]
        passes = self.cfg.encoder_passes
        if passes == 1:
            return self.encoder(image)
        b, c, h, w = image.shape
        return self.encoder(image.reshape(b * passes, c // passes, h, w)).reshape(b, -1)

    def loss(self, obs: Observation, action: torch.Tensor, noise: Noise | None = None,
             gen: torch.Generator | None = None) -> torch.Tensor:
        """The objective's loss; noise: the batch's per-sample training noise (drawn from gen when None)."""
        noise = noise or draw_noise(tuple(action.shape), gen, action.device)
        return self.objective.loss(self.net, action, self.condition(obs), noise)

    def forward(self, obs: Observation, action: torch.Tensor, noise: Noise) -> torch.Tensor:
        """The training loss: forward is what DistributedDataParallel wraps to synchronise the gradients."""
        return self.loss(obs, action, noise)

    def compile_for_inference(self) -> Policy:
        """torch.compile the encoder and the network (the samplers' Python loop stays eager)."""
        self.encoder = self.encoder if self.encoder is None else torch.compile(self.encoder)
        self.net = torch.compile(self.net)
        return self

    @torch.no_grad()
    def predict(self, obs: Observation, steps: int = 1, method: str | None = None,
                gen: torch.Generator | None = None) -> torch.Tensor:
        return self.sample(self.condition(obs), steps, method, gen)

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, steps: int = 1, method: str | None = None,
               gen: torch.Generator | None = None) -> torch.Tensor:
        """The plan from the observation's features (condition): the sampler's `steps` network evaluations."""
        shape = (cond.shape[0], self.cfg.horizon, self.cfg.action_dim)
        out = self.objective.sample(self.net, cond, shape, steps, method or self.default_method, gen)
        return out.float()  # under bf16 autocast the last network output is bfloat16
