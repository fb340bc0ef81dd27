"""Booster T1 fall-recovery environment (MuJoCo MJX and C MuJoCo) and its PPO learner.

The Rust CLI `hifar` reaches this package only through `jax_env.facade`.
"""

__version__ = "0.1.0"
