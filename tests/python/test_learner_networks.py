"""Network details that the checkpoint contract and the RMA module rely on."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen

from jax_env.learner import networks as nets_lib


@pytest.mark.parametrize("kernel,stride", [(8, 4), (5, 1), (1, 1)])
def test_conv1d_equals_flax_conv(kernel, stride):
  x = jax.random.normal(jax.random.PRNGKey(0), (3, 50, 7))
  ours = nets_lib.Conv1D(4, kernel, stride)
  params = ours.init(jax.random.PRNGKey(1), x)
  ref = linen.Conv(4, kernel_size=(kernel,), strides=(stride,), padding="VALID")
  assert jax.tree_util.tree_map(jnp.shape, params) == jax.tree_util.tree_map(
      jnp.shape, ref.init(jax.random.PRNGKey(1), x))
  np.testing.assert_allclose(ours.apply(params, x), ref.apply(params, x), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("history_len", [1, 4, 8, 10, 25, 50])
def test_adaptation_module_fits_any_history(history_len):
  module = nets_lib.AdaptationModule(history_len, latent_dim=3)
  window = jnp.ones((2, history_len, 5))
  params = module.init(jax.random.PRNGKey(0), window)
  assert params["params"]["conv_0"]["kernel"].shape[1] == 5  # obs features = input channels
  assert module.apply(params, window).shape == (2, 3)


def test_history_window_and_push():
  hist = jnp.arange(2 * 3 * 1, dtype=jnp.float32).reshape(2, 3, 1)
  obs = jnp.array([[10.0], [20.0]])
  np.testing.assert_array_equal(nets_lib.history_window(hist, obs)[:, :, 0],
                                [[1, 2, 10], [4, 5, 20]])
  pushed = nets_lib.push_history(hist, obs, jnp.array([0.0, 1.0]))
  np.testing.assert_array_equal(pushed[:, :, 0], [[1, 2, 10], [0, 0, 0]])
