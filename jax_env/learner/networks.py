"""The learner's networks: Gaussian policy, asymmetric critic, RMA encoder and adaptation module.

Built from brax's parts (`brax.training.networks.MLP`, `brax.training.distribution`,
`brax.training.acme.running_statistics`) in brax's functional style: parameters are plain
nested dicts, one per module, and every network is a pure `apply(params, inputs)`.

Module layout (docs/contracts.md, "Checkpoint directory"):
  policy     MLP over [normalized obs, z] -> action mean; `policy/log_std` is a state-independent
             parameter (no tanh: the environment clips actions).
  value      MLP over [normalized obs, normalized privileged] -> V (asymmetric critic).
  encoder    MLP over normalized privileged -> z (RMA environment-factor encoder).
  adaptation 1-D convolution over the last `history_len` normalized observations -> z_hat.

Why the layout matters for network growth between stages: every input feature enters a network
only through the rows of a first-layer kernel, and every action leaves the policy only through
one column of the output kernel and one bias entry. Zero rows for new features (with normalizer
mean 0, std 1) leave every old output unchanged whatever values the new features take, and zero
columns plus a zero bias make the mean of a new action exactly 0. The Rust CLI expands
checkpoints with nothing but these facts (see checkpoint.py for the annotations).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import jax
import jax.numpy as jnp
from brax.training import distribution
from brax.training import networks as brax_networks
from brax.training.acme import running_statistics
from flax import linen

Params = dict[str, Any]

ACTIVATIONS = {
    "elu": linen.elu,
    "swish": linen.swish,
    "tanh": linen.tanh,
    "relu": linen.relu,
}

# Channels of the adaptation module's convolutions (Kumar et al. 2022 use 32).
ADAPTATION_CHANNELS = 32


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
  """Sizes of every network; a pure function of the stage and its feature lists."""

  obs_size: int
  privileged_size: int
  action_size: int
  policy_hidden: tuple[int, ...]
  value_hidden: tuple[int, ...]
  activation: str
  rma: bool
  latent_dim: int
  encoder_hidden: tuple[int, ...]
  history_len: int
  initial_action_std: float

  def __post_init__(self):
    if self.activation not in ACTIVATIONS:
      raise ValueError(f"unknown activation {self.activation!r}; valid: "
                       f"{', '.join(ACTIVATIONS)}")

  @property
  def policy_latent(self) -> int:
    """Width of the latent appended to the policy's observation input (0 without RMA)."""
    return self.latent_dim if self.rma else 0

  def meta(self) -> dict:
    """The `network` section of checkpoint.json (what expansion must keep unchanged)."""
    return {"policy_hidden": list(self.policy_hidden), "value_hidden": list(self.value_hidden),
            "activation": self.activation, "latent_dim": self.latent_dim,
            "encoder_hidden": list(self.encoder_hidden), "history_len": self.history_len,
            "rma": self.rma}

  @classmethod
  def from_meta(cls, network: Mapping[str, Any], obs_size: int, privileged_size: int,
                action_size: int, initial_action_std: float = 1.0) -> "NetworkConfig":
    return cls(obs_size=obs_size, privileged_size=privileged_size, action_size=action_size,
               policy_hidden=tuple(int(x) for x in network["policy_hidden"]),
               value_hidden=tuple(int(x) for x in network["value_hidden"]),
               activation=str(network["activation"]), rma=bool(network["rma"]),
               latent_dim=int(network["latent_dim"]),
               encoder_hidden=tuple(int(x) for x in network["encoder_hidden"]),
               history_len=int(network["history_len"]),
               initial_action_std=initial_action_std)


class Conv1D(linen.Module):
  """1-D 'VALID' convolution over time as unfolded windows × one matrix (im2col).

  Parameters are those of `linen.Conv` (kernel [k, in, out], bias [out], same initializers).
  Inside `lax.scan` (where the learner runs it) XLA's CPU convolution and its gradient ran
  ~7× slower than this matrix product at the adaptation module's shapes; on a GPU both are
  matrix products anyway.
  """

  features: int
  kernel_size: int
  stride: int = 1

  @linen.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    k, s = self.kernel_size, self.stride
    length, channels = x.shape[-2], x.shape[-1]
    kernel = self.param("kernel", linen.linear.default_kernel_init,
                        (k, channels, self.features))
    bias = self.param("bias", linen.initializers.zeros_init(), (self.features,))
    n_out = (length - k) // s + 1
    patches = jnp.stack([x[..., i * s:i * s + k, :] for i in range(n_out)], axis=-3)
    patches = patches.reshape(patches.shape[:-2] + (k * channels,))
    return patches @ kernel.reshape(k * channels, self.features) + bias


class AdaptationModule(linen.Module):
  """RMA adaptation module: 1-D convolutions over time, then a linear map to z_hat.

  Input [B, history_len, n_obs] (oldest first). The first convolution's kernel
  [k, n_obs, C] reads the observation features as input channels, so growing the observation
  list adds zero input channels and changes nothing. Kernel sizes and strides follow Kumar et
  al. (8/4, then 5/1) and shrink to fit short histories, so any history_len >= 1 works.
  """

  history_len: int
  latent_dim: int
  activation: Any = linen.elu
  channels: int = ADAPTATION_CHANNELS

  @staticmethod
  def conv_shapes(history_len: int) -> list[tuple[int, int]]:
    """(kernel size, stride) of each convolution for a history length."""
    k0 = min(8, history_len)
    s0 = min(4, k0)
    length = (history_len - k0) // s0 + 1
    k1 = min(5, length)
    return [(k0, s0), (k1, 1)]

  @linen.compact
  def __call__(self, window: jax.Array) -> jax.Array:
    x = window
    for i, (k, s) in enumerate(self.conv_shapes(self.history_len)):
      x = Conv1D(self.channels, kernel_size=k, stride=s, name=f"conv_{i}")(x)
      x = self.activation(x)
    x = x.reshape(x.shape[:-2] + (-1,))
    return linen.Dense(self.latent_dim, name="output")(x)


def _mlp(layer_sizes, activation, small_output=False) -> brax_networks.MLP:
  # A small output layer starts the policy near a zero mean (stable early PPO updates).
  out_init = (jax.nn.initializers.variance_scaling(0.01, "fan_in", "uniform")
              if small_output else None)
  return brax_networks.MLP(layer_sizes=list(layer_sizes), activation=activation,
                           kernel_init=jax.nn.initializers.lecun_uniform(),
                           output_kernel_init=out_init)


@dataclasses.dataclass(frozen=True)
class Networks:
  """The learner's networks as pure functions of (params, inputs)."""

  config: NetworkConfig

  @property
  def _act(self):
    return ACTIVATIONS[self.config.activation]

  @property
  def policy_mlp(self):
    return _mlp(self.config.policy_hidden + (self.config.action_size,), self._act, True)

  @property
  def value_mlp(self):
    return _mlp(self.config.value_hidden + (1,), self._act)

  @property
  def encoder_mlp(self):
    return _mlp(self.config.encoder_hidden + (self.config.latent_dim,), self._act)

  @property
  def adaptation_module(self):
    return AdaptationModule(self.config.history_len, self.config.latent_dim, self._act)

  @property
  def action_distribution(self):
    return distribution.NormalDistribution(self.config.action_size)

  # -- init ------------------------------------------------------------------------------------

  def init(self, key: jax.Array) -> Params:
    c = self.config
    k_pol, k_val, k_enc, k_ada = jax.random.split(key, 4)
    policy = self.policy_mlp.init(k_pol, jnp.zeros((1, c.obs_size + c.policy_latent)))["params"]
    policy = dict(policy)
    policy["log_std"] = jnp.full((c.action_size,), jnp.log(c.initial_action_std), jnp.float32)
    params = {
        "policy": policy,
        "value": dict(self.value_mlp.init(
            k_val, jnp.zeros((1, c.obs_size + c.privileged_size)))["params"]),
    }
    if c.rma:
      params["encoder"] = dict(self.encoder_mlp.init(
          k_enc, jnp.zeros((1, c.privileged_size)))["params"])
      params["adaptation"] = dict(self.adaptation_module.init(
          k_ada, jnp.zeros((1, c.history_len, c.obs_size)))["params"])
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), params)

  # -- apply -----------------------------------------------------------------------------------

  def policy_mean(self, policy_params: Params, obs_n: jax.Array,
                  z: jax.Array | None) -> jax.Array:
    """Action mean from normalized obs and the latent (None without RMA)."""
    x = obs_n if z is None else jnp.concatenate([obs_n, z], axis=-1)
    weights = {k: v for k, v in policy_params.items() if k != "log_std"}
    return self.policy_mlp.apply({"params": weights}, x)

  def value(self, value_params: Params, obs_n: jax.Array, priv_n: jax.Array) -> jax.Array:
    x = jnp.concatenate([obs_n, priv_n], axis=-1)
    return self.value_mlp.apply({"params": value_params}, x)[..., 0]

  def encode(self, encoder_params: Params, priv_n: jax.Array) -> jax.Array:
    return self.encoder_mlp.apply({"params": encoder_params}, priv_n)

  def adapt(self, adaptation_params: Params, window_n: jax.Array) -> jax.Array:
    return self.adaptation_module.apply({"params": adaptation_params}, window_n)


# ---------------------------------------------------------------------------------------------
# Observation normalization: one brax running-statistics state over {"obs", "privileged"}.


def init_normalizer(config: NetworkConfig) -> running_statistics.RunningStatisticsState:
  return running_statistics.init_state({
      "obs": jnp.zeros((config.obs_size,), jnp.float32),
      "privileged": jnp.zeros((config.privileged_size,), jnp.float32)})


# Normalized inputs are clipped to ±NORMALIZED_CLIP. A feature that was (nearly) constant so
# far has a std at brax's floor (1e-6); when it starts to vary (a new stage turns pushes, delay
# or slopes on) its normalized value would be ~1e4–1e8 and wreck every network that reads it.
NORMALIZED_CLIP = 10.0


def normalize(normalizer, obs: jax.Array, privileged: jax.Array | None = None):
  """(obs_n, priv_n) normalized with the running statistics and clipped to ±NORMALIZED_CLIP
  (priv_n None if not given)."""
  obs_n = _clipped(obs, normalizer.mean["obs"], normalizer.std["obs"])
  if privileged is None:
    return obs_n, None
  return obs_n, normalize_privileged(normalizer, privileged)


def normalize_privileged(normalizer, privileged: jax.Array) -> jax.Array:
  return _clipped(privileged, normalizer.mean["privileged"], normalizer.std["privileged"])


def _clipped(x, mean, std):
  return jnp.clip((x - mean) / std, -NORMALIZED_CLIP, NORMALIZED_CLIP)


def update_normalizer(normalizer, obs: jax.Array, privileged: jax.Array,
                      axis_name: str | None = None):
  """Welford update with every row of obs/privileged ([..., n]), summed over devices."""
  return running_statistics.update(normalizer, _rows(obs, privileged), pmap_axis_name=axis_name)


def _rows(obs: jax.Array, privileged: jax.Array) -> dict:
  """The normalizer's batch: {"obs", "privileged"} as rows [N, n]."""
  return {"obs": obs.reshape(-1, obs.shape[-1]),
          "privileged": privileged.reshape(-1, privileged.shape[-1])}


# brax's running_statistics.update bounds every std to these.
NORMALIZER_STD_MIN, NORMALIZER_STD_MAX = 1e-6, 1e6


def calibrate_normalizer(normalizer, obs: jax.Array, privileged: jax.Array, mask,
                         axis_name: str | None = None):
  """The statistics with every feature where `mask` ({"obs", "privileged"}: [n], > 0 = yes)
  replaced by this batch's mean and std (over devices), its summed_variance consistent with
  the count (std² · count): a feature the statistics never saw vary (checkpoint.py,
  `unseen_features`) takes its scale from the first batch of the stage instead of being
  clipped at ±NORMALIZED_CLIP for as long as a whole stage's count takes to absorb it.
  A zero mask changes nothing."""
  count = (jnp.float32(normalizer.count.hi) * jnp.float32(2.0 ** 32)
           + jnp.float32(normalizer.count.lo))
  mean, std, summed = {}, {}, {}
  for kind, x in _rows(obs, privileged).items():
    m = jnp.mean(x, axis=0)
    sq = jnp.mean(jnp.square(x), axis=0)
    if axis_name is not None:
      m, sq = jax.lax.pmean(m, axis_name), jax.lax.pmean(sq, axis_name)
    s = jnp.clip(jnp.sqrt(jnp.maximum(sq - jnp.square(m), 0.0)), NORMALIZER_STD_MIN,
                 NORMALIZER_STD_MAX)
    on = mask[kind] > 0
    mean[kind] = jnp.where(on, m, normalizer.mean[kind])
    std[kind] = jnp.where(on, s, normalizer.std[kind])
    summed[kind] = jnp.where(on, jnp.square(s) * count, normalizer.summed_variance[kind])
  return normalizer.replace(mean=mean, std=std, summed_variance=summed)


# ---------------------------------------------------------------------------------------------
# The deployable actor and the training-time policy.


def history_window(history: jax.Array, obs: jax.Array) -> jax.Array:
  """The adaptation module's input: the last history_len observations ending with `obs`.

  `history` [B, H, n_obs] holds the previous H observations, oldest first (zeros at an episode
  start); its oldest row falls out of the window as the current observation enters.
  """
  return jnp.concatenate([history[:, 1:], obs[:, None]], axis=1)


def push_history(history: jax.Array, obs: jax.Array, done: jax.Array) -> jax.Array:
  """History after acting on `obs`; zeros where the step ended the episode (auto-reset)."""
  nxt = jnp.concatenate([history[:, 1:], obs[:, None]], axis=1)
  return jnp.where(done[:, None, None] > 0, 0.0, nxt)


def estimate_latent(nets: Networks, adaptation_params: Params, normalizer,
                    window: jax.Array) -> jax.Array:
  """z_hat: the adaptation module's estimate of the latent from a raw observation window."""
  window_n, _ = normalize(normalizer, window)
  return nets.adapt(adaptation_params, window_n)


def deployable_mean(nets: Networks, params: Params, normalizer, obs: jax.Array,
                    history: jax.Array | None) -> jax.Array:
  """Deterministic action of the deployable actor: adaptation module + base policy.

  Reads only what the robot measures (obs and the observation history); without RMA the base
  policy alone.
  """
  obs_n, _ = normalize(normalizer, obs)
  z = None
  if nets.config.rma:
    z = estimate_latent(nets, params["adaptation"], normalizer, history_window(history, obs))
  return nets.policy_mean(params["policy"], obs_n, z)


def privileged_mean(nets: Networks, params: Params, normalizer, obs: jax.Array,
                    privileged: jax.Array) -> jax.Array:
  """Action mean of the training-time policy, which reads z from the privileged encoder."""
  obs_n, priv_n = normalize(normalizer, obs, privileged)
  z = nets.encode(params["encoder"], priv_n) if nets.config.rma else None
  return nets.policy_mean(params["policy"], obs_n, z)
