"""The paper's CVAE human action model, one configurable implementation of the four variants of
the paper's Fig. 3 and of ``cvae-hold`` (the CVAE with a hold-aware output, see docs/model.md).

Shapes: ``B`` exemplars, ``L`` history steps, ``N = 15`` future steps, ``S`` latent samples per
exemplar, ``Z = K_z^N_z`` joint latent values. Every tensor here is *standardised*: the model owns its
standardisation (buffers ``feature_mean``, ``feature_std``, ``label_mean``, ``label_std``, set by
:meth:`CVAE.set_standardisation`) and is the one place that converts physical units
(:meth:`CVAE.states_to_standard`, :meth:`CVAE.actions_to_standard`, :meth:`CVAE.actions_to_physical`).
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..scenario import HORIZON, STATE_NAMES
from .gmm import GMM, GMMHead, HoldHead, HoldMixture
from .lstm import LSTMCell, SequenceSummary, StateProjection, dropout_masks

STATE_DIM = len(STATE_NAMES)
"""Components of a car state (m, m/s, m/s²)."""
ACCEL = slice(STATE_NAMES.index("xdd"), STATE_NAMES.index("ydd") + 1)
"""The accelerations within a car state: the human's actions (paper §II-C, ``u_h = [s̈_h, τ̈_h]``)."""
ACTION_DIM = ACCEL.stop - ACCEL.start
"""Components of a human action (m/s²)."""

VARIANTS = {  # name: (latent_vars N_z, latent_classes K_z, components M, hold)
    "cvae": (2, 5, 16, False),  # the paper's Fig. 3 ...
    "no-latent": (1, 1, 16, False),
    "mixture-lstm": (2, 5, 1, False),
    "lstm": (1, 1, 1, False),
    "cvae-hold": (2, 5, 16, True),  # ... and ours: the CVAE with the hold-aware output (gmm.HoldMixture)
}


ROBOT_FUTURES = ("recorded", "guess")
"""What a model takes as the other car's future (:attr:`CVAEConfig.robot_future`)."""


@dataclass(frozen=True)
class CVAEConfig:
    """Architecture. Defaults are the paper's CVAE; :meth:`variant` builds the Fig. 3 ablations
    and ``cvae-hold``. ``has_q`` is False for a model without the recognition network q(z|x,y)
    (the authors' published weights only hold what prediction needs); ``hold`` mixes "hold the
    previous action" modes into each step's output (:class:`~trafficweaving.model.gmm.HoldMixture`).
    ``robot_future`` is what the model is conditioned on as the other car's future (one of
    :data:`ROBOT_FUTURES`): ``recorded``, the paper's (its recorded or candidate future, for
    planning), or ``guess``, the other car holding its present acceleration
    (:func:`~trafficweaving.dynamics.constant_acceleration_future`), all a driver can know: such a
    model drives a car (docs/realism.md) but cannot tell candidate futures apart."""

    latent_vars: int = 2
    latent_classes: int = 5
    components: int = 16
    history_units: int = 32
    future_units: int = 32
    decoder_units: int = 128
    p_z_hidden: int = 16
    has_q: bool = True
    hold: bool = False
    robot_future: str = "recorded"

    def __post_init__(self):
        if self.robot_future not in ROBOT_FUTURES:
            raise ValueError(f"robot_future must be one of {', '.join(ROBOT_FUTURES)}, got {self.robot_future!r}")

    @staticmethod
    def variant(name: str, **overrides) -> "CVAEConfig":
        if name not in VARIANTS:
            raise ValueError(f"unknown variant {name!r} (expected one of {', '.join(VARIANTS)})")
        n_z, k_z, m, hold = VARIANTS[name]
        return CVAEConfig(latent_vars=n_z, latent_classes=k_z, components=m, hold=hold, **overrides)

    @property
    def name(self) -> str:
        """The variant name of this configuration (or ``custom``)."""
        key = (self.latent_vars, self.latent_classes, self.components, self.hold)
        return next((n for n, v in VARIANTS.items() if v == key), "custom")

    @property
    def latent_size(self) -> int:
        return self.latent_vars * self.latent_classes

    @property
    def latent_values(self) -> int:
        return self.latent_classes ** self.latent_vars

    @property
    def x_size(self) -> int:
        return self.history_units + 4 * self.future_units

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Batch:
    """Standardised model inputs for ``B`` exemplars.

    ``history [B, L, 12]``: robot then human state for steps 0..L-1 (padded past each ``t``);
    ``t [B]``: the present step (index into ``history``); ``robot_present [B, 6]``;
    ``robot_future [B, N, 6]`` (steps t+1..t+N); ``human_present [B, 6]``;
    ``human_present_action [B, 2]`` (label-standardised); ``y [B, N, 2]`` the human's future
    actions (None when sampling).
    """

    history: torch.Tensor
    t: torch.Tensor
    robot_present: torch.Tensor
    robot_future: torch.Tensor
    human_present: torch.Tensor
    human_present_action: torch.Tensor
    y: torch.Tensor | None = None

    def to(self, device) -> "Batch":
        return Batch(**{k: (None if v is None else v.to(device)) for k, v in vars(self).items()})

    def __len__(self) -> int:
        return self.t.shape[0]


class CVAE(nn.Module):
    """Encoders, latent distributions p(z|x) and q(z|x,y), and the GMM-output LSTM decoder."""

    def __init__(self, config: CVAEConfig = CVAEConfig()):
        super().__init__()
        self.config = c = config
        self.history_encoder = LSTMCell(2 * STATE_DIM, c.history_units)
        self.robot_future_encoder = SequenceSummary(STATE_DIM, STATE_DIM, c.future_units)
        self.p_z_hidden = nn.Linear(c.x_size, c.p_z_hidden)
        self.p_z_out = nn.Linear(c.p_z_hidden, c.latent_size)
        if c.has_q:
            self.human_future_encoder = SequenceSummary(ACTION_DIM, STATE_DIM, c.future_units)
            self.q_z = nn.Linear(c.x_size + 4 * c.future_units, c.latent_size)
        zx_size = c.latent_size + c.x_size
        self.decoder_initial_state = StateProjection(zx_size, c.decoder_units)
        self.decoder = LSTMCell(zx_size + STATE_DIM + ACTION_DIM, c.decoder_units)
        self.gmm = GMMHead(c.decoder_units, c.components)
        self.hold = HoldHead(c.decoder_units) if c.hold else None

        classes = torch.tensor(list(itertools.product(range(c.latent_classes), repeat=c.latent_vars)))
        self.register_buffer("latent_classes", classes, persistent=False)  # [Z, N_z], first variable slowest
        self.register_buffer("latent_onehots", F.one_hot(classes, c.latent_classes).flatten(1).float(),
                             persistent=False)  # [Z, N_z·K_z]
        for name, size in (("feature_mean", STATE_DIM), ("feature_std", STATE_DIM),
                           ("label_mean", ACTION_DIM), ("label_std", ACTION_DIM)):
            self.register_buffer(name, torch.zeros(size) if "mean" in name else torch.ones(size))
        # calibration, set after training (model/calibrate.py); 1 and 1 leave the trained model as it is
        self.register_buffer("latent_temperature", torch.tensor(1.0))  # divides the p(z|x) logits
        self.register_buffer("output_scale", torch.ones(2))  # multiplies the GMM widths in x, y (not the hold modes')

    def with_hold_modes(self) -> "CVAE":
        """A ``cvae-hold`` copy of this paper-variant model (``cvae``): every paper part (encoders,
        latent, GMM decoder), the standardisation and the calibration carry this model's weights, and
        the hold modes start switched off (:meth:`~trafficweaving.model.gmm.HoldHead.switch_off`), so
        the copy has this model's density until fine-tuning turns them on."""
        if self.hold is not None or self.config.name != "cvae":
            raise ValueError(f"only a cvae model can be given hold modes (this one is {self.config.name})")
        upgraded = CVAE(CVAEConfig.variant("cvae-hold", has_q=self.config.has_q)).to(self.feature_mean.device)
        missing, unexpected = upgraded.load_state_dict(self.state_dict(), strict=False)
        assert not unexpected and all(name.startswith("hold.") for name in missing), (missing, unexpected)
        upgraded.hold.switch_off()
        return upgraded.train(self.training)

    def states_to_standard(self, states: torch.Tensor) -> torch.Tensor:
        """Car states ``[..., 6]`` (m, m/s, m/s²) in the model's standardised units."""
        return (states - self.feature_mean) / self.feature_std

    def actions_to_standard(self, actions: torch.Tensor) -> torch.Tensor:
        """Human actions ``[..., 2]`` (accelerations, m/s²) in the model's standardised units."""
        return (actions - self.label_mean) / self.label_std

    def actions_to_physical(self, actions: torch.Tensor) -> torch.Tensor:
        """Standardised human actions ``[..., 2]`` back in m/s² (inverse of :meth:`actions_to_standard`)."""
        return actions * self.label_std + self.label_mean

    def set_standardisation(self, state_mean: np.ndarray | torch.Tensor, state_std: np.ndarray | torch.Tensor) -> "CVAE":
        """Set the standardisation buffers in place from the mean and std ``[6]`` of car states
        (m, m/s, m/s²; :func:`~trafficweaving.model.exemplars.state_statistics`): the features use
        them as they are, the labels their acceleration components (the human's actions are its
        accelerations); returns the model."""
        mean, std = torch.as_tensor(state_mean), torch.as_tensor(state_std)
        if mean.shape != (STATE_DIM,) or std.shape != (STATE_DIM,) or not (mean.isfinite().all() and (std > 0).all() and std.isfinite().all()):
            raise ValueError(f"standardisation must be a finite mean and a positive finite std of shape [{STATE_DIM}], "
                             f"got {mean.tolist()} and {std.tolist()}")
        with torch.no_grad():
            self.feature_mean.copy_(mean)
            self.feature_std.copy_(std)
            self.label_mean.copy_(self.feature_mean[ACCEL])
            self.label_std.copy_(self.feature_std[ACCEL])
        return self

    def set_calibration(self, latent_temperature: float, output_scale: float | tuple[float, float]) -> "CVAE":
        """Set the calibration buffers in place: the latent temperature and the output scale of the
        GMM widths, one for both directions or ``(x, y)`` (all positive; 1 and 1: the trained model
        as it is; chosen by :mod:`trafficweaving.model.calibrate`); returns the model."""
        scale = torch.as_tensor(output_scale, dtype=torch.float64).expand(2)
        if not (latent_temperature > 0 and bool((scale > 0).all())):
            raise ValueError(f"calibration must be positive, got temperature {latent_temperature}, scale {output_scale}")
        with torch.no_grad():
            self.latent_temperature.fill_(latent_temperature)
            self.output_scale.copy_(scale)
        return self

    # -- encoders ---------------------------------------------------------------------------
    def encode(self, batch: Batch, dropout: float = 0.0) -> torch.Tensor:
        """``x = concat(history h at t, robot-future summary)``, ``[B, x_size]``."""
        history_h = self.encode_history(batch.history, batch.t, dropout)
        return torch.cat([history_h, self.encode_robot_future(batch.robot_future, batch.robot_present, dropout)], dim=-1)

    def encode_history(self, history: torch.Tensor, t: torch.Tensor, dropout: float = 0.0) -> torch.Tensor:
        """History LSTM output at step ``t [B]`` of ``history [B, L, 12]``, ``[B, history_units]``."""
        outputs, _ = self.history_encoder.run(history[:, : int(t.max()) + 1], dropout=dropout)
        index = t.view(-1, 1, 1).expand(-1, 1, outputs.shape[-1])
        return torch.gather(outputs, 1, index).squeeze(1)

    def encode_robot_future(self, robot_future: torch.Tensor, robot_present: torch.Tensor, dropout: float = 0.0) -> torch.Tensor:
        """Summary ``[B, 4·future_units]`` of ``robot_future [B, N, 6]`` from ``robot_present [B, 6]``."""
        return self.robot_future_encoder(robot_future, robot_present, dropout)

    def p_z_logits(self, x: torch.Tensor, hidden_dropout: float = 0.0) -> torch.Tensor:
        """Prior logits ``[B, N_z, K_z]``, mean-subtracted per variable."""
        hidden = F.dropout(F.relu(self.p_z_hidden(x)), hidden_dropout, training=hidden_dropout > 0)
        return self._latent_logits(self.p_z_out(hidden) / self.latent_temperature)

    def q_z_logits(self, x: torch.Tensor, batch: Batch, dropout: float = 0.0) -> torch.Tensor:
        """Recognition logits ``[B, N_z, K_z]`` from ``x`` and the human's future actions."""
        if not self.config.has_q:
            raise ValueError("this model has no recognition network q(z|x,y)")
        summary = self.human_future_encoder(batch.y, batch.human_present, dropout)
        return self._latent_logits(self.q_z(torch.cat([x, summary], dim=-1)))

    def _latent_logits(self, flat: torch.Tensor) -> torch.Tensor:
        logits = flat.view(*flat.shape[:-1], self.config.latent_vars, self.config.latent_classes)
        return logits - logits.mean(dim=-1, keepdim=True)

    def joint_log_prob(self, logits: torch.Tensor) -> torch.Tensor:
        """Log probability of each of the ``Z`` joint latent values, ``[B, Z]``, from ``[B, N_z, K_z]``."""
        log_p = F.log_softmax(logits, dim=-1)  # [B, N_z, K_z]
        per_var = log_p[:, torch.arange(self.config.latent_vars, device=logits.device), self.latent_classes]  # [B, Z, N_z]
        return per_var.sum(-1)

    # -- decoder ----------------------------------------------------------------------------
    def output(self, h: torch.Tensor, previous: torch.Tensor) -> GMM | HoldMixture:
        """Per-step output distribution from decoder outputs ``h [..., units]`` and the action fed
        at that step, ``previous [..., 2]`` (broadcastable; only the hold variant uses it). The
        output scale widens the GMM only: a hold mode's width is the resolution of a held control,
        and widening it would cost likelihood without adding spread (model/calibrate.py)."""
        gmm = self.gmm(h, torch.log(self.output_scale))
        return gmm if self.hold is None else self.hold(h, gmm, previous)

    def _decoder_parts(self, zx: torch.Tensor, robot_inputs: torch.Tensor, action_inputs: torch.Tensor | None):
        """Split the decoder's input projection: the ``zx`` part (constant over the horizon)
        ``[S, B, 4u]``, the robot-state part ``[B, N, 4u]`` and the action weights."""
        w = self.decoder.weight_input
        n_zx = zx.shape[-1]
        w_zx, w_robot, w_action = w[:n_zx], w[n_zx:n_zx + STATE_DIM], w[n_zx + STATE_DIM:]
        constant = torch.matmul(zx, w_zx) + self.decoder.bias
        per_step = torch.matmul(robot_inputs, w_robot)
        if action_inputs is not None:
            per_step = per_step + torch.matmul(action_inputs, w_action)
        return constant, per_step, w_action

    @staticmethod
    def decoder_robot_inputs(batch: Batch) -> torch.Tensor:
        """Robot state fed at decoder step j: present for j = 0, then ``robot_future[j-1]``; ``[B, N, 6]``."""
        return torch.cat([batch.robot_present.unsqueeze(1), batch.robot_future[:, :-1]], dim=1)

    def decode(self, zx: torch.Tensor, batch: Batch, dropout: float = 0.0, feed_own: float = 0.0,
               generator: torch.Generator | None = None) -> tuple[torch.Tensor, GMM | HoldMixture]:
        """Teacher-forced decoding of ``batch.y`` for latent-and-context inputs ``zx [S, B, zx_size]``.

        Returns ``log p(y|x,z)`` ``[S, B]`` (sum over the horizon of per-step log densities capped
        at 50) and the per-step output distributions (batch dims ``[S, B, N]``; their ``log_prob``
        and ``marginal_log_prob`` take ``y [S or 1, B, N, 2]``). In training, ``feed_own`` is the
        probability that a step is fed the decoder's own sample of the previous action instead of
        the recorded one (scheduled sampling); the hold modes stay centred on the recorded one.
        """
        s, b = zx.shape[:2]
        action_inputs = torch.cat([batch.human_present_action.unsqueeze(1), batch.y[:, :-1]], dim=1)
        constant, per_step, w_action = self._decoder_parts(zx, self.decoder_robot_inputs(batch), action_inputs)
        c, h = self.decoder_initial_state(zx)
        state = (c.reshape(s * b, -1), h.reshape(s * b, -1))
        keep = dropout_masks(HORIZON, s * b, self.config.decoder_units, dropout, zx)
        if feed_own > 0.0:  # which (step, row) pairs are fed the decoder's own previous sample
            swap = torch.rand(HORIZON, s * b, device=zx.device, generator=generator) < feed_own
        outputs = []
        for k in range(HORIZON):
            gates = (constant + per_step[:, k]).reshape(s * b, -1)
            if feed_own > 0.0 and k > 0:
                rows = swap[k].nonzero().squeeze(1)
                if len(rows):
                    previous = action_inputs[:, k - 1].repeat(s, 1)[rows]
                    own = self.output(outputs[-1][rows].detach(), previous).sample(generator)
                    true = action_inputs[:, k].repeat(s, 1)[rows]
                    gates = gates.index_add(0, rows, torch.matmul(own - true, w_action))
            state = self.decoder.step(gates, state, None if keep is None else keep[k])
            outputs.append(state[1])
        dist = self.output(torch.stack(outputs, dim=1).view(s, b, HORIZON, -1), action_inputs)
        return dist.log_prob(batch.y.unsqueeze(0)).sum(-1), dist

    def sample_actions(self, zx: torch.Tensor, robot_inputs: torch.Tensor, present_action: torch.Tensor,
                       generator: torch.Generator | None = None,
                       noise: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Autoregressive samples of the human's future actions ``[S, B, N, 2]`` for
        ``zx [S, B, zx_size]``, ``robot_inputs [B, N, 6]`` (see :meth:`decoder_robot_inputs`) and
        ``present_action [B, 2]``; each sampled action is fed back as the next input. ``noise``
        optionally gives the random numbers: uniforms ``[S, B, N]`` for the mixture component and
        standard normals ``[S, B, N, 2]`` (otherwise drawn from ``generator``)."""
        s, b = zx.shape[:2]
        constant, per_step, w_action = self._decoder_parts(zx, robot_inputs, None)
        c, h = self.decoder_initial_state(zx)
        state = (c.reshape(s * b, -1), h.reshape(s * b, -1))
        action = present_action.repeat(s, 1)
        samples = []
        for k in range(HORIZON):
            gates = (constant + per_step[:, k]).reshape(s * b, -1) + torch.matmul(action, w_action)
            state = self.decoder.step(gates, state)
            dist = self.output(state[1], action)
            if noise is None:
                action = dist.sample(generator)
            else:
                action = dist.sample(uniform=noise[0][:, :, k].reshape(-1), normal=noise[1][:, :, k].reshape(-1, 2))
            samples.append(action)
        return torch.stack(samples, dim=1).view(s, b, HORIZON, ACTION_DIM)

    def situations(self, histories: torch.Tensor, robot_futures: torch.Tensor) -> Batch:
        """The :class:`Batch` (standardised, no ``y``) of ``B`` situations at one present step t:
        ``histories [B, t+1, 2, 6]`` physical states (m, m/s, m/s²) of the robot (index 0) and the
        human at steps 0..t, ``robot_futures [B, 15, 6]`` the robot's states at steps t+1..t+15.
        Tensors in the model's dtype and on its device."""
        b, steps = histories.shape[:2]
        standard = self.states_to_standard(histories).reshape(b, steps, 2 * STATE_DIM)
        return Batch(history=standard, t=torch.full((b,), steps - 1, device=histories.device),
                     robot_present=standard[:, -1, :STATE_DIM], robot_future=self.states_to_standard(robot_futures),
                     human_present=standard[:, -1, STATE_DIM:],
                     human_present_action=self.actions_to_standard(histories[:, -1, 1, ACCEL]))

    @torch.no_grad()
    def sample_futures(self, batch: Batch, samples: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``samples`` futures of the human's actions per situation of ``batch`` (its ``y`` is not
        used), ``[S, B, 15, 2]`` standardised: each draws its latent value from p(z|x), then its
        actions from the decoder (:meth:`sample_actions`)."""
        x = self.encode(batch)
        p_z = self.joint_log_prob(self.p_z_logits(x)).exp()  # [B, Z]
        z = torch.multinomial(p_z, samples, replacement=True, generator=generator).T  # [S, B]
        return self.sample_actions(self.zx(self.latent_onehots[z], x), self.decoder_robot_inputs(batch),
                                   batch.human_present_action, generator)

    def zx(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``concat(z, x)`` for latents ``z [S, B, N_z·K_z]`` (or ``[S, 1, ·]``) and ``x [B, x_size]``."""
        z = z.expand(-1, x.shape[0], -1)
        return torch.cat([z, x.unsqueeze(0).expand(z.shape[0], -1, -1)], dim=-1)

    # -- likelihoods ------------------------------------------------------------------------
    def log_likelihoods(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """``log p(z|x)`` and ``log p(y|x,z)`` for every joint latent value, each ``[B, Z]``
        (standardised units)."""
        x = self.encode(batch)
        log_p_z = self.joint_log_prob(self.p_z_logits(x))
        log_p_y, _ = self.decode(self.zx(self.latent_onehots.unsqueeze(1), x), batch)
        return log_p_z, log_p_y.T
