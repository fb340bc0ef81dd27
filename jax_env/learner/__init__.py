"""The PPO learner of hifar, built from brax's training components.

networks    policy, asymmetric critic, RMA encoder and adaptation module; normalization
ppo         losses, GAE, minibatch epochs, gradient clipping, fixed / adaptive-KL learning rate
mirror      the mirror (symmetry) loss
rma         the RMA adaptation phase
checkpoint  annotated, atomic, pickle-free checkpoints (docs/contracts.md)
train       `train_stage`: one curriculum stage, data-parallel and exactly resumable
bench       update throughput: `python -m jax_env.learner.bench`
"""
