"""SAC with a policy-extended critic Q(s, a, chi_pi) and critic updates for snapshots of its actor."""

from typing import ClassVar

import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN

from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord
from sb3_pevfa.sac_pevfa.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, SACPeVFAPolicy


class SACPeVFA(OffPolicyPeVFA, SAC):
    """SAC whose twin critics read an embedding chi of the policy, Q(s, a, chi), and also learn the values of
    snapshots of the actor (:mod:`sb3_pevfa.pevfa.off_policy`). SB3's SAC update runs unchanged, its critics reading
    chi of the live actor (held fixed: no gradient reaches the actor through it); the target critics keep a Polyak
    copy of the encoder too.

    Parameters not listed are SAC's (:class:`~stable_baselines3.SAC`, passed by keyword).

    :param representation: ``opr``, ``spr``, ``fingerprint``, ``random`` or ``none``
    :param embedding_dim: Size of chi
    :param representation_kwargs: Keyword arguments of the representation
    :param n_state_action_pairs: State-action pairs of each snapshot (``spr``): its deterministic actions at replay
        states drawn when it is recorded
    :param snapshot_freq: Gradient steps between two snapshots of the actor
    :param history_max_policies: Snapshots kept (the oldest go first)
    :param history_train_freq: Gradient steps per critic update on the snapshots; 0 turns them off
    :param history_batch_size: Replay transitions per such update, ``history_batch_size / history_batch_policies`` for
        each of ``history_batch_policies`` snapshots drawn uniformly
    :param history_batch_policies: Snapshots per update
    :param history_learning_starts: Env steps before the snapshots' updates start
    :param live_encoder_gradient: The critic's loss on the live actor trains the encoder too (default: end to end,
        as the paper's E2E); False: only the snapshots' updates train it and chi of the live actor is computed once
        per move of the actor or encoder without gradient (cheaper; unstable at a high learning rate: the encoder
        then grew chi without bound in SB3's infinite-horizon test, lr 0.01)
    :param flush_denormal: Denormal numbers flushed to zero during ``train`` with one torch thread (as
        :class:`~sb3_pevfa.PPOPeVFA`'s update: Adam's moments of units without gradient decay through the denormal
        range, where the CPU is tens of times slower); False: IEEE denormals, and SB3's SAC bit for bit where the
        representation is ``none`` and ``history_train_freq`` 0
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: SACPeVFAPolicy
    added_policy_kwargs = (*OffPolicyPeVFA.added_policy_kwargs, "use_sde")  # SB3's SAC adds use_sde too
    critic_loss_scale = 0.5
    critic_norm_stats = ("batch_norm_stats", "batch_norm_stats_target")

    def _snapshot_actions(self, records: PolicyRecord, features: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
        """Each snapshot's squashed Gaussian at its inputs, sampled as SB3's actor samples (with its log-probability)."""
        layout = self.policy.critic.layout
        _, outputs = layout.evaluate(records.params, features)
        mean, log_std = outputs.reshape(-1, outputs.shape[-1]).chunk(2, dim=-1)
        log_std = th.clamp(log_std, LOG_STD_MIN, LOG_STD_MAX)
        distribution = SquashedDiagGaussianDistribution(mean.shape[-1])
        return distribution.log_prob_from_params(mean, log_std)

    def _live_next_actions(self, observations: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """SAC's target action: sampled from the live actor, with its log-probability."""
        return self.actor.action_log_prob(observations)

    def _entropy_term(self) -> th.Tensor:
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            return th.exp(self.log_ent_coef.detach())
        return self.ent_coef_tensor
