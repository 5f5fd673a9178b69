"""TD3 with a policy-extended critic Q(s, a, chi_pi) and critic updates for snapshots of its actor."""

from typing import ClassVar

import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.policies import BasePolicy

from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord
from sb3_pevfa.td3_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, TD3PeVFAPolicy


class TD3PeVFA(OffPolicyPeVFA, TD3):
    """TD3 whose twin critics read an embedding chi of the policy, Q(s, a, chi), and also learn the values of
    snapshots of the actor (:mod:`sb3_pevfa.pevfa.off_policy`). SB3's TD3 update runs unchanged, its critics reading
    chi of the live actor (held fixed: no gradient reaches the actor through it); a snapshot's target uses its own
    smoothed action, clip(mu_k(s') + clip(noise), -1, 1), with TD3's ``target_policy_noise`` and
    ``target_noise_clip``.

    Parameters not listed are TD3's (:class:`~stable_baselines3.TD3`, passed by keyword); the PeVFA parameters are
    :class:`~sb3_pevfa.SACPeVFA`'s.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: TD3PeVFAPolicy

    def _snapshot_actions(self, records: PolicyRecord, features: th.Tensor) -> tuple[th.Tensor, None]:
        """Each snapshot's deterministic action at its inputs with TD3's clipped target noise."""
        _, outputs = self.policy.critic.layout.evaluate(records.params, features)
        return self._smoothed(outputs.reshape(-1, outputs.shape[-1])), None

    def _live_next_actions(self, observations: th.Tensor) -> tuple[th.Tensor, None]:
        """TD3's target action: the target actor's, smoothed."""
        return self._smoothed(self.actor_target(observations)), None

    def _smoothed(self, actions: th.Tensor) -> th.Tensor:
        """``clip(actions + clip(noise), -1, 1)``, TD3's target policy smoothing."""
        noise = th.randn_like(actions).mul_(self.target_policy_noise).clamp_(-self.target_noise_clip, self.target_noise_clip)
        return (actions + noise).clamp(-1, 1)
