"""Attacks: collaborators that lie in the messages they send (docs/attacks.md).

The stage kind ``attack`` (scenario section ``attack``, :mod:`roco_env.stages`):
``attack.kind`` names the attack, ``attack.agents`` / ``attack.count`` who attacks,
``attack.params`` its parameters (checked by the attack's own dataclass). Built in:
``none`` (default), ``pose_spoof``, ``ghost``, ``erase``. The pipeline calls
:meth:`Attack.tamper` once per step on the messages every ego receives.
"""

from collections.abc import Sequence

from roco_env.attacks.attack_stage import Attack, NoAttack, StepContext, attack_truth
from roco_env.scenario import ScenarioConfig
from roco_env.stages import checked_params, stage

__all__ = ["Attack", "NoAttack", "StepContext", "attack_truth", "make_attack"]


def make_attack(config: ScenarioConfig, agent_ids: Sequence[str]) -> Attack:
    """The attack ``config.attack.kind`` names, for an env of ``agent_ids`` (its parameters
    and attackers checked: a ConfigError names the scenario field and the allowed values)."""
    attack = config.attack
    checked_params("attack", attack.kind, attack.params, where="attack")
    return stage("attack", attack.kind).load_factory()(config, tuple(agent_ids))
