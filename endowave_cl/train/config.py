"""Every training default, in sections by what reads them, and loading them from a TOML file.

TrainConfig is made of frozen sections (SECTIONS: schedule, data, init, optim, densify, losses,
wavelet, flow, between), each documented with the code that reads it.  Every setting also has one
flat key (FLAT, made from SECTIONS: between_prob is between.prob): --set KEY=VALUE, a TOML file's
``key = value`` pairs (an optional ``[train]`` table is accepted too) and a run's config.json use
the flat keys.  Defaults follow DESIGN.md (3DGS / 4DGS optimiser and density-control values); the
ones the paper leaves open are chosen here and commented.
"""
from __future__ import annotations

import difflib
import inspect
import math
import re
import sys
from dataclasses import dataclass, fields, replace
from typing import Any, Dict, Mapping, Optional

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib  # setup.cfg requires it below 3.11

from ..data.flow import METHODS, MIN_ESTIMATION_PIXELS
from ..data.scene import SPLITS
from ..errors import EndowaveError
from ..wavelet.config import WaveletConfig

_WAVELET = WaveletConfig()   # the wavelet loss's defaults, defined once in wavelet/config.py


# Density relative to the image, so that one default suits 160x128 and 640x512: initial Gaussians
# (init_points = 0) and the densification cap (max_gaussians = 0) per pixel of one frame.  On the
# pulling frames more Gaussians than ~1 per pixel cost steps without paying back (research/QUALITY.md);
# the demo's tuned 40k cap at 160x128 is 2 per pixel.
INIT_POINTS_PER_PIXEL = 1.0
MAX_GAUSSIANS_PER_PIXEL = 2.0
# What fits a frame, and what a step costs, is the Gaussians alive at its time, not all of them: a
# 4D Gaussian lives for part of the sequence (its temporal coverage, motion.temporal_coverage).
# With the same motion, a sequence twice as long has half as many alive at any time under the same
# cap.  So the default cap is also at least this many Gaussians alive per pixel at a time, given
# the initial Gaussians' mean coverage (TrainConfig.resolve_cap_for_lifetimes; research/QUALITY.md
# findings 13, 24): longer sequences, and faster or less regular motion, get a higher cap.
ALIVE_PER_PIXEL = 0.4
MAX_GAUSSIANS_PER_PIXEL_LIMIT = 16.0   # the raised cap's bound: memory (about 1 KB per Gaussian with
                                       # its gradient and Adam's moments) for very long sequences
# what sh_degree = -1 becomes (TrainConfig.resolve_sh_degree): 3DGS's degree where the training
# cameras move, 1 where every frame is seen from one camera centre (research/QUALITY.md finding 12)
SH_DEGREE_MOVING = 3
SH_DEGREE_ONE_VIEWPOINT = 1
# The default schedule (iterations = 0) gives every training frame about STEPS_PER_TRAINING_FRAME
# visits, and is never shorter than BASE_ITERATIONS: a longer sequence needs as many visits per frame
# as a short one to fit them (research/QUALITY.md finding 14).  The schedule keys (SCALED_FIELDS) are
# step numbers of the BASE_ITERATIONS-step schedule and stretch with it, as --minutes stretches them.
BASE_ITERATIONS = 6000
STEPS_PER_TRAINING_FRAME = 109   # 6000 steps over the 55 training frames of the pulling sequence
# The flow estimators see at most this many pixels (flow_max_pixels' default, data/flow.py
# estimation_size): their patches and windows have fixed sizes in pixels, and on the 640x512 pulling
# frames flows estimated at 320x256 and scaled up are the better teacher (research/QUALITY.md finding 26)
FLOW_MAX_PIXELS = 320 * 256
# densify_grad_threshold = 0 resolves to DENSIFY_GRAD_THRESHOLD for frames of up to
# DENSIFY_GRAD_PIXELS pixels, and to DENSIFY_GRAD_THRESHOLD x sqrt(DENSIFY_GRAD_PIXELS / pixels) for
# larger ones (TrainConfig.resolve_density).  The gradient it is compared with is in NDC units: for a
# Gaussian of a given size in pixels it falls as 1 / frame height, and the initial Gaussians are one
# per pixel at every size, so the same threshold densifies larger frames less (research/QUALITY.md
# finding 27).  1.4e-4 (3DGS: 2e-4) densifies sooner: higher validation PSNR and lower LPIPS on every
# shared scene at two seeds, also at equal training time (finding 42).
DENSIFY_GRAD_THRESHOLD = 1.4e-4
DENSIFY_GRAD_PIXELS = 320 * 256
# The in-between modes (train/between.py implements them; validate_config checks the values)
# how the hypotheses are combined (between_fuse): weighted by their warps' agreement, or averaged
FUSE_MODES = ("agree", "mean")
# where in the pair an in-between step's time falls (between_s): "uniform" over (0, 1);
# "triangular", the mean of two uniform draws (density 4 s up to 1/2, 4 (1 - s) above): twice the
# uniform's share at the middle of the pair, furthest from both training frames, where the target
# is least certain and only these steps supervise the model, and none at the frames themselves,
# which their own steps supervise
S_DISTRIBUTIONS = ("uniform", "triangular")
# how a pixel moves between a pair's frames (between_path): at constant velocity along the pair's
# flow, or along the parabola through its positions in the pair's frames and the training frame
# beyond the pair on its own side (Bend)
PATHS = ("linear", "quadratic")

SCALED_FIELDS = ("densify_from", "densify_until", "opacity_reset_every", "lr_position_steps",
                 "between_motion_refresh")


@dataclass(frozen=True)
class ScheduleSettings:
    """How long training runs and what it writes on the way (train/trainer.py's loop, train/budget.py)."""
    iterations: int = 0             # 0: STEPS_PER_TRAINING_FRAME per training frame, at least
                                    # BASE_ITERATIONS (6000: about 10-15 minutes for the 63 pulling
                                    # frames at 320x256 on 2 CPU cores, research/QUALITY.md), with the
                                    # schedule keys stretched alike; 4DGS trains 30000 on a GPU.
                                    # --minutes plans it from a time budget
    minutes: float = 0.0            # > 0: plan the schedule to end within this many minutes of
                                    # training on this device (train/budget.py); 0: `iterations`
    seed: int = 0
    deterministic: bool = False     # force bit-identical gradients on GPUs too (CPU devices always
                                    # use that mode: it is the faster one there)
    log_every: int = 50
    eval_every: int = 500
    checkpoint_every: int = 1000


@dataclass(frozen=True)
class DataSettings:
    """Which frames are read and how (data/scene.py: load_scene, apply_split)."""
    downscale: float = 1.0          # image downscale factor (2 = half size)
    split: str = "test"             # "test": train on every non-test frame, score the test frames
                                    # ((i - 1) % 8 == 0); "validation": also hold out the validation
                                    # frames ((i - 5) % 8 == 0) and score those, for choosing settings
                                    # without reading a test frame (data/scene.py apply_split)


@dataclass(frozen=True)
class InitSettings:
    """The initial Gaussians (train/init.py init_gaussians, train/motion.py)."""
    init_points: int = 0            # Gaussians created by init_gaussians; 0: INIT_POINTS_PER_PIXEL per
                                    # pixel of one frame, at most half of max_gaussians
    init_time_scale: float = 0.2    # longest initial temporal std (normalised time; 0: 2 training-
                                    # frame spacings).  Without flow every Gaussian gets it; with
                                    # init_velocity a Gaussian lives as long as its constant velocity
                                    # follows the flow's curvature, from 2 spacings up to this
                                    # (train/motion.py linear_lifetime; research/QUALITY.md)
    init_velocity: bool = True      # initial Gaussians move with the pseudo ground-truth flow under
                                    # their pixel (train/motion.py) instead of starting still
    sh_degree: int = -1             # view-dependent colour: degree 0..3 of the spherical harmonics in
                                    # every TEASH frequency; -1: chosen per scene (resolve_sh_degree):
                                    # 1 when every training frame is seen from one camera centre (a
                                    # fixed endoscope), else 3 (3DGS)
    temporal_freqs: int = 2


@dataclass(frozen=True)
class OptimSettings:
    """Adam's learning rates per parameter group (eps 1e-15; Trainer.group_lrs, ops/adam.py)."""
    lr_position_init: float = 6.4e-4   # x scene extent, decays log-linearly ...
    lr_position_final: float = 6.4e-6  # ... to this (x extent) at lr_position_steps; both 4x
                                        # 3DGS's 1.6e-4 / 1.6e-6: the Gaussians of a deforming
                                        # scene move further (research/QUALITY.md finding 15)
    lr_position_steps: int = 0          # 0: decay over `iterations`
    lr_time: float = 1.6e-4             # t column of the means: 3DGS's initial position lr, not
                                        # decayed and NOT times the extent (time is normalised to
                                        # [0, 1] whatever the scene's size)
    lr_features: float = 2.5e-3         # TEASH DC term sh[:, 0, 0, :]
    lr_features_rest_divisor: float = 20.0  # every other TEASH coefficient: lr_features / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3             # log-stds of the principal axes labelled x, y, z
    lr_scales_t: float = 5e-3           # log-std of the axis labelled t (a lifetime before rotation)
    lr_rotation: float = 1e-3           # both quaternions q_l, q_r
    lr_phase: float = 2.5e-3            # TEASH phases (radians); not in the paper: the feature lr,
                                        # since the phase is part of the appearance model
    lr_anneal_final: float = 0.3        # every group but the spatial means (already decayed) has its
                                        # lr multiplied by a factor that falls log-linearly from 1 at
                                        # densify_until to this at the last step; 1: constant rates
    adam_skip_culled: bool = True       # Adam leaves the Gaussians culled at the step's time alone
                                        # (parameters and moments), as gsplat's SelectiveAdam: a 4D
                                        # Gaussian outside its lifetime does not drift on momentum,
                                        # and Adam reads only the live rows (ops/adam.py)
    average_last: float = 0.1           # the model saved at the end is the mean of the parameters
                                        # over this last fraction of the steps (never before
                                        # densify_until: the rows must be fixed), a snapshot every
                                        # train/average.py AVERAGE_EVERY steps; 0: the last step's
                                        # (research/QUALITY.md finding 51)


@dataclass(frozen=True)
class DensifySettings:
    """Adaptive density control, 3DGS's (train/densify.py, Trainer.densify / reset_opacity)."""
    max_gaussians: int = 0          # densification stops adding Gaussians beyond this count; 0:
                                    # MAX_GAUSSIANS_PER_PIXEL per pixel of one frame, or more where
                                    # the initial Gaussians live short parts of a long sequence
                                    # (ALIVE_PER_PIXEL alive per pixel at a time)
    densify_from: int = 500
    densify_every: int = 100
    densify_until: int = 3000           # half of training, as 3DGS (15000 of 30000); like every
                                        # schedule key a step number: --iterations does not scale
                                        # them (--minutes and iterations = 0 do)
    densify_grad_threshold: float = 0.0  # mean |d loss / d mean2d| in NDC units; 0: 1.4e-4, less for
                                        # frames larger than 320x256 (DENSIFY_GRAD_THRESHOLD)
    percent_dense: float = 0.01         # clone if max spatial scale <= this x extent, else split
    split_children: int = 2
    split_scale_divisor: float = 1.6    # children's spatial scales = parent's / 1.6
    cap_turnover: float = 0.02          # at the cap, up to this fraction of it may be replaced per
                                        # densification: the least opaque non-candidates make room
                                        # for the candidates with the largest gradient (densify.py;
                                        # 0: 3DGS, nothing added at the cap).  Every scene sits at
                                        # its cap for most of a run, where 3DGS's rules add nothing
    prune_opacity: float = 0.005        # prune sigmoid(opacity) below this
    prune_screen_size: float = 20.0     # pixels: prune larger max screen radius (after 1st reset)
    prune_world_size: float = 0.1       # x extent: prune larger max spatial scale (after 1st reset)
    opacity_reset_every: int = 3000     # resets happen only before densify_until (3DGS): none by default
    opacity_reset_value: float = 0.01


@dataclass(frozen=True)
class LossSettings:
    """The loss terms and their weights (train/device_losses.py, reference/losses.py)."""
    lambda_rgb: float = 1.0
    lambda_dssim: float = 0.4           # L_rgb = (1 - 0.4) L1 + 0.4 D-SSIM; 3DGS's 0.2 gives the
                                        # same validation PSNR on the real scenes and 1-15 % worse
                                        # LPIPS on every shared scene (research/QUALITY.md finding 44)
    lambda_depth: float = 0.1           # L1 of the depth in scene units (data/scene.py: the median
                                        # depth is 4); DESIGN.md's 1 holds the depth to 0.25 % for
                                        # 0.8-1.5 dB of image PSNR and a worse rendered flow, 0.1 to
                                        # 0.5 % (research/QUALITY.md finding 18)
    lambda_flow: float = 0.01           # not in the paper: flow loss is a mean squared endpoint
                                        # error in pixels (see reference/losses.py); 1 px of error
                                        # costs 0.01, below a typical late L1 of ~0.02-0.05
    flow_huber_delta: float = 4.0       # px: beyond this endpoint error the flow loss grows linearly
                                        # (bounded gradient; see reference/losses.py); inf: pure squared
    lambda_wavelet: float = 1.0         # not in the paper: the wavelet term is a mean squared
                                        # error per sub-band coefficient (MSE scale), weight 1
    use_depth: bool = True
    use_flow: bool = True
    use_wavelet: bool = True


@dataclass(frozen=True)
class WaveletSettings:
    """The rational-wavelet loss (wavelet/config.py WaveletConfig documents each; defaults from there)."""
    q: int = _WAVELET.q                             # rational factor a = (q + 1) / q
    levels: int = _WAVELET.levels                   # decomposition depth
    weight_ll: float = _WAVELET.weights[0]          # weight of each band's mean squared coefficient
    weight_lh: float = _WAVELET.weights[1]          # error, the same at every level
    weight_hl: float = _WAVELET.weights[2]
    weight_hh: float = _WAVELET.weights[3]


@dataclass(frozen=True)
class FlowSettings:
    """The pseudo ground-truth optical flow (data/flow.py flow_for_scene)."""
    method: str = "dis_fine"        # pseudo ground-truth optical flow (OpenCV, data/flow.py METHODS):
                                    # the flow loss's target and the initial velocities; DIS down to
                                    # its finest level, closer to exact flow than DIS's default preset
                                    # (research/QUALITY.md finding 23); "dis" is 4x faster
    max_pixels: int = FLOW_MAX_PIXELS       # the estimators see frames larger than this many
                                    # pixels area-averaged to at most this many, and their flows are
                                    # scaled back up (data/flow.py estimation_size; 320x256 for
                                    # the 640x512 EndoNeRF frames); 0: the training size


@dataclass(frozen=True)
class BetweenSettings:
    """The in-between steps and their targets (train/between.py BetweenSampler, Trainer.between_prob)."""
    prob: float = 0.7               # fraction of steps spent at a random time between two training
                                    # frames, supervised by the frame the pair's flow predicts there
                                    # (train/between.py); 0: training frames only; 0.7: chosen on the
                                    # validation frames of every shared scene (research/QUALITY.md
                                    # finding 37)
    anneal_final: float = 0.5          # between_prob is multiplied by a factor that falls linearly
                                    # from 1 at densify_until to this at the last step (0: the run
                                    # ends on the training frames alone; 1: constant; 0.5: what
                                    # suits the real and the synthetic scenes, QUALITY.md finding 11)
    s: str = "uniform"              # where in the pair an in-between step's time falls
                                    # (train/between.py S_DISTRIBUTIONS): "uniform" over it, or
                                    # "triangular", twice as often at its middle and falling to
                                    # none at its two frames; it moves quality towards the
                                    # middle, not up (research/QUALITY.md finding 30)
    path: str = "quadratic"          # how the in-between target moves a pixel between the pair's
                                    # frames (train/between.py PATHS): "quadratic", along the
                                    # parabola through its positions in the pair's frames and in
                                    # the training frame beyond the pair on each side (tissue that
                                    # speeds up or slows down); "linear", at constant velocity
                                    # along the pair's flows (research/QUALITY.md finding 31)
    levels: int = 8                 # an in-between step's fraction s is moved onto the grid j / K
                                    # (j = 1 .. K - 1) and each pair's flow prediction at a grid
                                    # point is built once and kept (float16, up to 2 GiB:
                                    # train/between.py TARGET_CACHE_BYTES), so that later in-between
                                    # steps cost little more than plain ones; 8: the validation
                                    # figures of the continuous draw, in 6-15 % less time
                                    # (research/QUALITY.md finding 41); 0: s drawn from a
                                    # continuous distribution, its target built at every step
    flows: str = "dis,farneback"          # further flow estimators (comma-separated,
                                    # data/flow.py METHODS) whose interpolations are fused with
                                    # flow_method's in the in-between target, per pixel by how well
                                    # each one's two warps agree (train/between.py
                                    # fused_interpolation; research/QUALITY.md finding 20); "":
                                    # flow_method's alone
    fuse: str = "agree"             # how between_flows' hypotheses are combined: "agree" weighs each
                                    # pixel's by how well its two warps agree, "mean" averages them
                                    # (research/QUALITY.md findings 20, 21)
    flow_splat: bool = True          # the flows push the two frames forward (a reversed splat,
                                    # once per direction along the estimators' flows fused by
                                    # forward-backward consistency: train/between.py
                                    # consistent_flows) instead of sampling them backward, the
                                    # backward prediction filling the pixels that no source pixel
                                    # reaches (research/QUALITY.md findings 21, 22)
    model: float = 0.5              # from densify_until on, the in-between target is this blend of
                                    # the pair's frames warped along the motion the model itself
                                    # renders there and the flow interpolation (train/between.py;
                                    # 0: the flow's alone; 1: the model's alone; research/QUALITY.md
                                    # finding 19)
    model_splat: bool = True          # the model's prediction in the in-between target pushes the
                                    # two frames forward along the motion the model renders at
                                    # their own times (two more renders per such step) instead of
                                    # sampling them along the motion it renders at s (train/
                                    # between.py reversed_splat_interpolation; research/QUALITY.md
                                    # findings 20, 21)
    motion_refresh: int = 500          # with between_model_splat: the motion the model renders at
                                    # a pair's two frames is rendered over the whole pair, scaled to
                                    # each step's time and kept this many steps (two renders fewer
                                    # in most late in-between steps); 0: rendered to the step's time
                                    # in every such step (train/between.py BetweenSampler;
                                    # research/QUALITY.md finding 22)

# The sections, in the order --list-settings shows them: {name: (class, the prefix its keys carry)}.
# A flat key (--set KEY=VALUE, a TOML file, config.json) is the prefix and a section's field name:
# between_prob is between.prob, lr_time is optim.lr_time.  FLAT, made from this, is the one map.
SECTIONS = {
    "schedule": (ScheduleSettings, ""),
    "data": (DataSettings, ""),
    "init": (InitSettings, ""),
    "optim": (OptimSettings, ""),
    "densify": (DensifySettings, ""),
    "losses": (LossSettings, ""),
    "wavelet": (WaveletSettings, "wavelet_"),
    "flow": (FlowSettings, "flow_"),
    "between": (BetweenSettings, "between_"),
}
FLAT = {prefix + f.name: (name, f.name) for name, (cls, prefix) in SECTIONS.items() for f in fields(cls)}


@dataclass(frozen=True, init=False)
class TrainConfig:
    """Every training setting, in sections (SECTIONS: cfg.between.prob, cfg.optim.lr_time); each
    flat key reads as an attribute too (cfg.between_prob), and TrainConfig(between_prob=0.3) or
    cfg.replace(between_prob=0.3) take flat keys or whole sections.  Frozen: the resolve_* steps
    and the other changes return a new one, so a config handed to a trainer, a plan or a loss is
    never changed under it."""
    recipe: str                     # the named set of values the others start from (RECIPES):
                                    # "default", or "paper" (EndoWave as published)
    schedule: ScheduleSettings
    data: DataSettings
    init: InitSettings
    optim: OptimSettings
    densify: DensifySettings
    losses: LossSettings
    wavelet: WaveletSettings
    flow: FlowSettings
    between: BetweenSettings

    def __init__(self, recipe: str = "default", **values):
        parts = {name: values.pop(name, None) or cls() for name, (cls, _) in SECTIONS.items()}
        changes: Dict[str, Dict[str, Any]] = {}
        for key, value in values.items():
            if key not in FLAT:
                raise TypeError(f"TrainConfig: unknown key {key!r}")
            name, field_name = FLAT[key]
            changes.setdefault(name, {})[field_name] = value
        object.__setattr__(self, "recipe", recipe)
        for name, part in parts.items():
            object.__setattr__(self, name, replace(part, **changes[name]) if name in changes else part)

    def __getattr__(self, key: str):
        """A flat key's value (FLAT): cfg.between_prob is cfg.between.prob."""
        where = FLAT.get(key)
        section = None if where is None else self.__dict__.get(where[0])
        if section is None:
            raise AttributeError(f"'TrainConfig' object has no attribute {key!r}")
        return getattr(section, where[1])

    def replace(self, **changes) -> "TrainConfig":
        """This config with ``changes`` (flat key: value, or section name: section; not checked:
        with_values checks them)."""
        return TrainConfig(**{"recipe": self.recipe, **{name: getattr(self, name) for name in SECTIONS}, **changes})

    def resolve_iterations(self, n_train: int) -> "TrainConfig":
        """This config with iterations = 0 replaced by STEPS_PER_TRAINING_FRAME x n_train steps, at
        least BASE_ITERATIONS, and the schedule keys (SCALED_FIELDS, given for BASE_ITERATIONS
        steps) stretched by the same factor.  An iterations > 0 is kept, and the keys with it."""
        if self.iterations > 0:
            return self
        total = max(BASE_ITERATIONS, STEPS_PER_TRAINING_FRAME * int(n_train))
        r = total / BASE_ITERATIONS
        # lr_position_steps = 0 means "all of them" already: a key at 0 stays 0
        scaled = {f: max(1, int(round(getattr(self, f) * r))) for f in SCALED_FIELDS if getattr(self, f) > 0}
        return self.replace(iterations=total, **scaled)

    def resolve_density(self, width: int, height: int) -> "TrainConfig":
        """This config with init_points = 0 and max_gaussians = 0 replaced by their per-pixel
        defaults for width x height frames, and densify_grad_threshold = 0 by
        densify_threshold_for(width, height) (the run's config.json then records the numbers used)."""
        cap = self.max_gaussians if self.max_gaussians > 0 else max(1, int(MAX_GAUSSIANS_PER_PIXEL * width * height))
        points = (self.init_points if self.init_points > 0
                  else max(1, min(int(INIT_POINTS_PER_PIXEL * width * height), cap // 2)))
        threshold = (self.densify_grad_threshold if self.densify_grad_threshold > 0
                     else densify_threshold_for(width, height))
        return self.replace(max_gaussians=cap, init_points=points, densify_grad_threshold=threshold)

    def resolve_cap_for_lifetimes(self, width: int, height: int, coverage: float) -> "TrainConfig":
        """This config with the per-pixel default cap (max_gaussians = 0 given, resolve_density
        applied) raised to ALIVE_PER_PIXEL Gaussians per pixel alive at a time, for initial
        Gaussians that are each alive for the fraction ``coverage`` (their mean) of the sequence."""
        alive_cap = ALIVE_PER_PIXEL * width * height / max(float(coverage), 1e-6)
        alive_cap = int(min(alive_cap, MAX_GAUSSIANS_PER_PIXEL_LIMIT * width * height))
        return self.replace(max_gaussians=max(self.max_gaussians, alive_cap))

    def resolve_sh_degree(self, one_viewpoint: bool) -> "TrainConfig":
        """Replace sh_degree = -1 by SH_DEGREE_ONE_VIEWPOINT when every training frame is seen from
        one camera centre, else by SH_DEGREE_MOVING.  From one centre a Gaussian is seen along a
        direction that changes only as far as the Gaussian itself moves, a few degrees: degree 1 (a
        colour that changes linearly with that direction) is all the data can constrain, and
        degrees 2 and 3 would add 108 of the 144 colour coefficients per Gaussian, and the time to
        project and update them, without changing the test frames (research/QUALITY.md finding 12)."""
        if self.sh_degree >= 0:
            return self
        return self.replace(sh_degree=SH_DEGREE_ONE_VIEWPOINT if one_viewpoint else SH_DEGREE_MOVING)

    def wavelet_config(self):
        """The wavelet_* keys as the WaveletConfig the device loss takes."""
        return WaveletConfig(q=self.wavelet_q, levels=self.wavelet_levels,
                             weights=(self.wavelet_weight_ll, self.wavelet_weight_lh, self.wavelet_weight_hl,
                                      self.wavelet_weight_hh))

    def to_dict(self) -> Dict[str, Any]:
        """{flat key: value}, as config.json records it."""
        return {"recipe": self.recipe, **{key: getattr(getattr(self, name), f) for key, (name, f) in FLAT.items()}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "config dictionary") -> "TrainConfig":
        return with_values(cls(), d, source)


KEYS = ("recipe", *FLAT)     # every flat key, in the order --list-settings shows them

# Named starting points (--recipe): the values that differ from the defaults above (and 3DGS's values
# of keys whose default may move).  "paper" is EndoWave as the paper trains it: 3DGS's learning rates
# and density control (threshold 2e-4 at every frame size, opacity reset every 3000 steps, nothing
# replaced at the cap), 4DGS's schedule (30000 steps, densification from 500 to 15000), spherical harmonics
# of degree 3, the RGB, depth (weight 1, DESIGN.md), flow and wavelet losses, no in-between steps,
# Gaussians that start still, plain Adam (every Gaussian updated every step) and constant rates but
# the positions'.  What the paper leaves open (flow and wavelet weights, the flow estimator:
# OpenCV's in place of GMFlow) keeps this version's defaults, and so does the 2D low-pass
# (gaussians.LOWPASS, 0.1 px^2 against 3DGS's 0.3), which is a constant of the renderer, not a key.
RECIPES: Dict[str, Dict[str, Any]] = {
    "default": {},
    "paper": {
        "iterations": 30000, "densify_from": 500, "densify_every": 100, "densify_until": 15000,
        "opacity_reset_every": 3000, "lr_position_init": 1.6e-4, "lr_position_final": 1.6e-6,
        "lr_position_steps": 30000, "lr_anneal_final": 1.0, "adam_skip_culled": False,
        "sh_degree": 3, "lambda_depth": 1.0, "lambda_dssim": 0.2, "between_prob": 0.0, "init_velocity": False,
        "densify_grad_threshold": 2e-4, "cap_turnover": 0.0, "lr_features": 2.5e-3, "average_last": 0.0,
        "use_depth": True, "use_flow": True, "use_wavelet": True,
    },
}


def _coerce(name: str, value: Any, source: str, from_text: bool) -> Any:
    kind = type(getattr(TrainConfig(), name))  # the default's type: int, float, bool or str
    if kind is str:
        if not isinstance(value, str):
            raise EndowaveError(f"{source}: key '{name}' expects str, got {type(value).__name__} {value!r}")
        return value
    if from_text and isinstance(value, str):
        text = value.strip()
        try:
            if kind is bool:
                if text.lower() in ("1", "true", "yes", "on"):
                    return True
                if text.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(text)
            return kind(float(text)) if kind is int and float(text).is_integer() else kind(text)
        except ValueError:
            raise EndowaveError(f"{source}: key '{name}' expects {kind.__name__}, got {value!r}") from None
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:  # float accepts an int
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok:
        raise EndowaveError(f"{source}: key '{name}' expects {kind.__name__}, "
                            f"got {type(value).__name__} {value!r}")
    return kind(value)


# Keys of earlier versions, removed with their code: each one's other values reproduced a finding
# that did not become a default (research/README.md lists them).  {key: (the value this version
# always behaves as: "off", or the mode that is the default, the finding)}.  A saved run's
# config.json or checkpoint names them all: opening the run ignores them, with a note where the run
# had another value; --set, a TOML file or a batch manifest that names one is refused.
REMOVED = {
    "between_two_flow": (False, "finding 9"),
    "between_by_time": (False, "finding 16"),
    "flow_photo_max": (0.0, "finding 17"),
    "flow_anneal_final": (1.0, "finding 17"),
    "lambda_flow_gaussian": (0.0, "finding 5"),
    "between_sampler": ("cubic", "finding 10"),
    "between_splat": ("reverse", "finding 21"),
    "between_push": ("fused", "finding 22"),
    "between_confidence": (0.0, "finding 39"),
}


def removed_key_text(key: str) -> str:
    """Why a REMOVED key is no longer a setting, for messages."""
    off, finding = REMOVED[key]
    return (f"key '{key}' was removed in this version with its code (its values other than {off!r}, "
            f"now the only behaviour, served {finding} of research/QUALITY.md and did not become defaults)")


def drop_removed(values: Mapping[str, Any], source: str, note=None) -> Dict[str, Any]:
    """values without the REMOVED keys (a saved run's config); note(line) is told of each one whose
    value was not the one REMOVED gives, since the run was trained with a behaviour this version lacks."""
    out = {}
    for key, value in values.items():
        if key in REMOVED:
            if note is not None and value != REMOVED[key][0]:
                note(f"{source}: {key} = {value!r} ignored: {removed_key_text(key)}; the run opens without it")
            continue
        out[key] = value
    return out


def with_values(cfg: TrainConfig, values: Mapping[str, Any], source: str, from_text: bool = False) -> TrainConfig:
    """cfg with ``values`` ({key: value}; from_text: values may be the text of one, as --set gives
    them), each key checked (known, its type, its range); one-line EndowaveError naming ``source``
    and the key otherwise."""
    changes = {}
    for key, value in values.items():
        if key in REMOVED:
            raise EndowaveError(f"{source}: {removed_key_text(key)}; an older commit has it")
        if key not in KEYS:
            raise EndowaveError(f"{source}: unknown key '{key}'{did_you_mean(key)}")
        changes[key] = _coerce(key, value, source, from_text)
    cfg = cfg.replace(**changes)
    validate_config(cfg, source)
    return cfg


# The range every numeric key must lie in: (low, high, low inclusive, high inclusive); None = open.
# Learning rates and loss weights are >= 0 (a negative learning rate climbs the loss: a negative
# lr_opacity prunes every Gaussian); counts of steps or items are at least 1 where they divide or
# size something; inf is refused everywhere except flow_huber_delta (inf: pure squared error).
_AT_LEAST_1 = (1, None, True, False)
_NON_NEGATIVE = (0, None, True, False)
_POSITIVE = (0, None, False, False)
_UNIT = (0, 1, True, True)
RANGES = {
    "iterations": _NON_NEGATIVE, "minutes": _NON_NEGATIVE, "seed": (0, 2 ** 63 - 1, True, True), "log_every": _AT_LEAST_1,
    "eval_every": _NON_NEGATIVE, "checkpoint_every": _NON_NEGATIVE,
    "downscale": (1, None, True, False), "init_points": _NON_NEGATIVE, "init_time_scale": _NON_NEGATIVE,
    "max_gaussians": _NON_NEGATIVE, "between_prob": _UNIT, "between_model": _UNIT, "between_motion_refresh": _NON_NEGATIVE, "between_levels": (0, 1024, True, True), "between_anneal_final": _UNIT,
    "lr_position_init": _NON_NEGATIVE, "lr_position_final": _NON_NEGATIVE, "lr_position_steps": _NON_NEGATIVE,
    "lr_time": _NON_NEGATIVE, "lr_features": _NON_NEGATIVE, "lr_features_rest_divisor": _POSITIVE,
    "lr_opacity": _NON_NEGATIVE, "lr_scales": _NON_NEGATIVE, "lr_scales_t": _NON_NEGATIVE, "lr_rotation": _NON_NEGATIVE,
    "lr_phase": _NON_NEGATIVE, "lr_anneal_final": _POSITIVE, "average_last": _UNIT,
    "densify_from": _NON_NEGATIVE, "densify_every": _AT_LEAST_1, "densify_until": _NON_NEGATIVE,
    "densify_grad_threshold": _NON_NEGATIVE, "percent_dense": _NON_NEGATIVE, "split_children": _AT_LEAST_1,
    "split_scale_divisor": _POSITIVE, "cap_turnover": _UNIT, "prune_opacity": (0, 1, True, False), "prune_screen_size": _POSITIVE,
    "prune_world_size": _POSITIVE, "opacity_reset_every": _AT_LEAST_1, "opacity_reset_value": (0, 1, False, False),
    "lambda_rgb": _NON_NEGATIVE, "lambda_dssim": _UNIT, "lambda_depth": _NON_NEGATIVE,
    "lambda_flow": _NON_NEGATIVE, "flow_huber_delta": _POSITIVE, "lambda_wavelet": _NON_NEGATIVE,
    "sh_degree": (-1, 3, True, True), "flow_max_pixels": _NON_NEGATIVE,
    # q >= 1 (q = 1: dyadic); at least one level; band weights like loss weights
    "wavelet_q": _AT_LEAST_1, "wavelet_levels": _AT_LEAST_1, "wavelet_weight_ll": _NON_NEGATIVE,
    "wavelet_weight_lh": _NON_NEGATIVE, "wavelet_weight_hl": _NON_NEGATIVE, "wavelet_weight_hh": _NON_NEGATIVE,
}
# keys whose value is fixed in this version: the number of TEASH frequencies (gaussians.py
# TEMPORAL_FREQS) is what the initialisation builds; any other value would be recorded in
# config.json and silently ignored
FIXED = {"temporal_freqs": 2}
INF_ALLOWED = {"flow_huber_delta"}


def _range_text(low, high, low_in, high_in) -> str:
    if high is None:
        return f"{'at least' if low_in else '>'} {low:g}"
    return f"in {'[' if low_in else '('}{low:g}, {high:g}{']' if high_in else ')'}"


def densify_threshold_for(width: int, height: int) -> float:
    """The default densify_grad_threshold for width x height frames (DENSIFY_GRAD_THRESHOLD)."""
    pixels = max(1, int(width) * int(height))
    return DENSIFY_GRAD_THRESHOLD * min(1.0, math.sqrt(DENSIFY_GRAD_PIXELS / pixels))


def between_flow_methods(cfg: TrainConfig):
    """The estimators named by between_flows, in order, without flow_method and repeats."""
    out = []
    for m in (x.strip() for x in str(cfg.between_flows).split(",")):
        if m and m != cfg.flow_method and m not in out:
            out.append(m)
    return out


def validate_config(cfg: TrainConfig, source: str) -> None:
    """Every key in its range; one-line EndowaveError naming the source and the key otherwise."""
    for name, (low, high, low_in, high_in) in RANGES.items():
        v = getattr(cfg, name)
        if isinstance(v, float) and math.isnan(v):
            raise EndowaveError(f"{source}: key '{name}' is NaN")
        if isinstance(v, float) and math.isinf(v) and name not in INF_ALLOWED:
            raise EndowaveError(f"{source}: key '{name}' must be finite, got {v}")
        ok = (v >= low if low_in else v > low) and (high is None or (v <= high if high_in else v < high))
        if not ok:
            how = ("must be " + _range_text(low, high, low_in, high_in)
                   + (" (inf: pure squared error)" if name in INF_ALLOWED else ""))
            raise EndowaveError(f"{source}: key '{name}' {how}, got {v:g}")
    for name, want in FIXED.items():
        if getattr(cfg, name) != want:
            raise EndowaveError(f"{source}: key '{name}' must be {want} (the model layout is fixed in this "
                                f"version; other values are not implemented), got {getattr(cfg, name)}")
    if 0 < cfg.flow_max_pixels < MIN_ESTIMATION_PIXELS:     # the estimators fail on smaller frames (issue 57)
        raise EndowaveError(f"{source}: key 'flow_max_pixels' must be 0 (the frame's size) or at least "
                            f"{MIN_ESTIMATION_PIXELS}, got {cfg.flow_max_pixels}")
    if cfg.between_levels == 1:
        raise EndowaveError(f"{source}: key 'between_levels' must be 0 (continuous) or at least 2 (a grid of "
                            f"fractions), got 1")
    for key, allowed in (("recipe", RECIPES), ("split", SPLITS), ("between_path", PATHS),
                         ("between_s", S_DISTRIBUTIONS), ("between_fuse", FUSE_MODES)):
        value = getattr(cfg, key)
        if value not in allowed:
            raise EndowaveError(f"{source}: key '{key}' must be one of {', '.join(allowed)}, got {value!r}")
    for m in between_flow_methods(cfg):
        if m not in METHODS:
            raise EndowaveError(f"{source}: key 'between_flows' must list flow methods from "
                                f"{', '.join(METHODS)} separated by commas, got {cfg.between_flows!r}")
    if cfg.flow_method not in METHODS:
        raise EndowaveError(f"{source}: key 'flow_method' must be one of {', '.join(METHODS)}, "
                            f"got {cfg.flow_method!r}")


def read_toml(path, what: str) -> Dict[str, Any]:
    """The TOML file at ``path`` as a dict; one-line EndowaveError naming the file otherwise.
    ``what`` names the kind of file in the messages ("config file", "manifest")."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise EndowaveError(f"{path}: {what} does not exist") from None
    except IsADirectoryError:
        raise EndowaveError(f"{path}: is a folder, not a TOML {what}") from None
    except OSError as e:
        raise EndowaveError(f"{path}: cannot read the {what} ({e.strerror or e})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise EndowaveError(f"{path}: not valid TOML: {e}") from None


def recipe_config(name: str, source: str = "--recipe") -> TrainConfig:
    """The TrainConfig a recipe (RECIPES) starts from."""
    if name not in RECIPES:
        raise EndowaveError(f"{source}: unknown recipe {name!r} (choose from {', '.join(RECIPES)})")
    return with_values(TrainConfig(), {**RECIPES[name], "recipe": name}, f"recipe {name!r}")


def load_config(path: Optional[str], overrides: Optional[Mapping[str, Any]] = None,
                recipe: Optional[str] = None) -> TrainConfig:
    """The recipe's values (RECIPES: ``recipe``, else a "recipe" key of the overrides or of the
    file, else "default"), then the TOML file at ``path`` (if any), then ``overrides`` (values or
    strings)."""
    data = {}
    if path is not None:
        data = read_toml(path, "config file")
        if "train" in data and isinstance(data["train"], dict):
            rest = {k: v for k, v in data.items() if k != "train"}
            data = {**data["train"], **rest}
    overrides = dict(overrides or {})
    name = recipe or overrides.get("recipe") or data.get("recipe") or "default"
    if not isinstance(name, str):
        raise EndowaveError(f"{path}: key 'recipe' expects str, got {name!r}")
    cfg = recipe_config(name.strip(), "--recipe" if recipe else ("override" if "recipe" in overrides else str(path)))
    data.pop("recipe", None)
    overrides.pop("recipe", None)
    if data:
        cfg = with_values(cfg, data, str(path))
    if overrides:
        cfg = with_values(cfg, overrides, "override", from_text=True)
    return cfg


# ------------------------------------------------------------------ the keys, for people (train --list-settings)
# what the keys without a comment of their own in TrainConfig mean
_MEANINGS = {
    "recipe": "the named set of values the others start from: \"default\", or \"paper\" (EndoWave as published)",
    "seed": "random seed of the initialisation and of the steps' frame order",
    "log_every": "steps between log lines (and train_curves.csv rows)",
    "eval_every": "steps between test-frame evaluations during training (0: only at the end)",
    "checkpoint_every": "steps between checkpoints (0: only at the end)",
    "temporal_freqs": "TEASH temporal frequencies of the colour (fixed by the model layout)",
    "lr_opacity": "learning rate of the opacities",
    "densify_from": "first step of density control (a step of the BASE_ITERATIONS schedule)",
    "densify_every": "steps between density-control passes",
    "split_children": "Gaussians a split makes of one",
    "opacity_reset_value": "the opacity an opacity reset caps every Gaussian at",
    "lambda_rgb": "weight of the L1 colour loss",
    "use_depth": "the depth loss on (where the scene has depth maps)",
    "use_flow": "the optical-flow loss on",
    "use_wavelet": "the rational-wavelet loss on",
    "wavelet_weight_ll": "wavelet loss weight of the LL band (each band's mean squared coefficient error)",
    "wavelet_weight_lh": "wavelet loss weight of the LH band (wavelet/config.py)",
    "wavelet_weight_hl": "wavelet loss weight of the HL band (wavelet/config.py)",
    "wavelet_weight_hh": "wavelet loss weight of the HH band (wavelet/config.py)",
}


def did_you_mean(key: str) -> str:
    """" (did you mean 'x'?)" for the TrainConfig key nearest to a mistyped one, else ""."""
    near = difflib.get_close_matches(str(key), sorted(KEYS), n=1, cutoff=0.6)
    return f" (did you mean '{near[0]}'?)" if near else ""


def _field_comments() -> Dict[str, str]:
    """{flat key: the comment beside its field in its section's source, the lines joined} (empty
    when the source cannot be read)."""
    out: Dict[str, str] = {}
    for name, (cls, prefix) in SECTIONS.items():
        try:
            lines = inspect.getsource(cls).splitlines()
        except (OSError, TypeError):
            return {}
        names = {f.name for f in fields(cls)}
        cur = None
        for line in lines[1:]:
            m = re.match(r"^    (\w+)\s*:", line)
            if m and m.group(1) in names:
                cur = prefix + m.group(1)
                out[cur] = _comment_of(line)
            elif cur is not None and re.match(r"^ {5,}#", line):
                more = line.strip()[1:].strip()
                out[cur] = out[cur] + more if out[cur].endswith("-") else (out[cur] + " " + more).strip()
            else:
                cur = None
    return out


def _comment_of(line: str) -> str:
    """The text after a line's first # outside quotes."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#":
            return line[i + 1:].strip()
    return ""


def _one_line(text: str, width: int = 110) -> str:
    """The first sentence of a comment (up to a ". " or "; " outside brackets), at most width
    characters."""
    depth, end = 0, len(text)
    for i, ch in enumerate(text):
        depth += (ch in "([") - (ch in ")]")
        if (depth == 0 and text[i:i + 2] in (". ", "; ") and text[:i].strip(". ")
                and (ch == ";" or not text[i - 1:i].isupper())):
            end = i
            break
    first = text[:end].strip().rstrip(".")
    if len(first) > width:
        first = first[:width - 3].rsplit(" ", 1)[0] + "..."
    return first


def _values_text(name: str, default: Any) -> str:
    """The range (RANGES) or the values a key accepts."""
    if name in RANGES:
        low, high, low_in, high_in = RANGES[name]
        if isinstance(high, int) and high > 2 ** 31:
            return f"in [{low}, 2^63 - 1]"
        return _range_text(low, high, low_in, high_in)
    if name in FIXED:
        return f"fixed: {FIXED[name]}"
    if isinstance(default, bool):
        return "true | false"
    choices = {"recipe": tuple(RECIPES), "split": SPLITS, "between_path": PATHS,
               "between_s": S_DISTRIBUTIONS, "between_fuse": FUSE_MODES, "flow_method": METHODS}
    if name in choices:
        return " | ".join(choices[name])
    if name == "between_flows":
        return "comma-separated: " + ", ".join(METHODS)
    return ""


def settings_table():
    """[(section, key, default, range or values, one-line meaning)] for every TrainConfig key, in
    order (section "" for recipe)."""
    comments = _field_comments()
    default_cfg = TrainConfig()
    rows = []
    for key in KEYS:
        default = getattr(default_cfg, key)
        shown = str(default).lower() if isinstance(default, bool) else (
            repr(default) if isinstance(default, str) else f"{default:g}" if isinstance(default, float) else str(default))
        meaning = _MEANINGS.get(key) or _one_line(comments.get(key, ""))
        rows.append((FLAT[key][0] if key in FLAT else "", key, shown, _values_text(key, default), meaning))
    return rows


def settings_text() -> str:
    """What ``endowave-cl train --list-settings`` prints: the keys by section (SECTIONS), each
    section headed by what reads it."""
    rows = settings_table()
    w = [max(len(r[i]) for r in rows) for i in range(1, 4)]
    head = ("Training settings: --set KEY=VALUE (repeatable) or KEY = VALUE lines in a --config TOML "
            "file.\nDefaults of the 'default' recipe; --recipe paper starts from: "
            + ", ".join(f"{k}={v}" for k, v in RECIPES["paper"].items()) + ".\n")
    lines = [f"{'key':<{w[0]}}  {'default':<{w[1]}}  {'range / values':<{w[2]}}  meaning"]
    section = None
    for sec, k, d, v, m in rows:
        if sec != section and sec:
            doc = (SECTIONS[sec][0].__doc__ or "").strip().splitlines()[0]
            lines.append(f"\n[{sec}]  {doc}")
        section = sec
        lines.append(f"{k:<{w[0]}}  {d:<{w[1]}}  {v:<{w[2]}}  {m}".rstrip())
    return head + "\n" + "\n".join(lines) + "\n"
