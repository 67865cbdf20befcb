"""Reinforcement learning of alignment decisions (``roco-env train-policy``).

``config`` (the settings and the command line's options), ``curriculum`` (the conditions
and the training env), ``evaluate`` (held-out scores of the policy and the baselines),
``ppo`` (the Stable-Baselines3 loop), ``checkpoint`` (pickle-free resumable state),
``export`` (the actor as a :mod:`roco_env.policies.learned` weights file), ``report``.
Needs ``stable-baselines3`` (the ``rl`` extra).
"""
