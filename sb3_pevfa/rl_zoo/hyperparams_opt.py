"""Optuna samplers and trial converters of ``ppo_pevfa``, ``a2c_pevfa``, ``sac_pevfa`` and ``td3_pevfa`` for
rl-zoo3: the base algorithm's parameters (rl-zoo3's own space) plus PeVFA's."""

import math
from typing import Any

import optuna
from rl_zoo3.hyperparams_opt import (
    convert_offpolicy_params,
    convert_onpolicy_params,
    sample_a2c_params,
    sample_ppo_params,
    sample_sac_params,
    sample_td3_params,
)

#: Raw (trial) parameters that belong to PeVFA; the rest are rl-zoo3's PPO parameters.
PEVFA_PARAMS = (
    "representation",
    "objectives",
    "embedding_dim",
    "history_buffer_size_pow",
    "history_train_freq",
    "critic_learning_rate",
)

#: Name of the search space used by :func:`sample_ppo_pevfa_params` (``"full"`` or ``"small"``, for tests).
SEARCH_SPACE = {"name": "full"}


def convert_pevfa_params(sampled: dict[str, Any]) -> dict[str, Any]:
    """Raw PeVFA trial parameters -> PPOPeVFA constructor arguments."""
    params: dict[str, Any] = {}
    if "representation" in sampled:
        params["representation"] = sampled["representation"]
    objectives = sampled.get("objectives", "e2e")
    params["representation_objectives"] = () if objectives == "e2e" else tuple(objectives.split("+"))
    if "embedding_dim" in sampled:
        params["embedding_dim"] = sampled["embedding_dim"]
    if "history_buffer_size_pow" in sampled:
        params["history_buffer_size"] = 2 ** sampled["history_buffer_size_pow"]
    for name in ("history_train_freq", "critic_learning_rate"):
        if name in sampled:
            params[name] = sampled[name]
    return params


def _with_fixed_params(params: dict[str, Any]) -> dict[str, Any]:
    """Settings the search space fixes rather than samples."""
    if SEARCH_SPACE["name"] == "small":  # historical updates and objectives from the first iteration
        params["history_learning_starts"] = 0
        params["objective_kwargs"] = {name: {"learning_starts": 0} for name in params["representation_objectives"]}
    return params


def convert_ppo_pevfa_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Converter of ``ppo_pevfa`` and ``a2c_pevfa`` (``HYPERPARAMS_CONVERTER``): used by ``--trial-id`` to rebuild a
    trial."""
    ppo = {key: value for key, value in sampled_params.items() if key not in PEVFA_PARAMS}
    pevfa = {key: value for key, value in sampled_params.items() if key in PEVFA_PARAMS}
    return _with_fixed_params({**convert_onpolicy_params(ppo), **convert_pevfa_params(pevfa)})


def _sample_small_ppo_params(trial: optuna.Trial) -> dict[str, Any]:
    """A tiny PPO space (tests): small rollouts and networks."""
    sampled = {
        "n_steps_pow": trial.suggest_int("n_steps_pow", 5, 6),
        "batch_size_pow": trial.suggest_int("batch_size_pow", 4, 5),
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 0.01, 0.03, log=True),
        "one_minus_gae_lambda": trial.suggest_float("one_minus_gae_lambda", 0.02, 0.1, log=True),
        "learning_rate": trial.suggest_float("learning_rate", 1e-4, 1e-3, log=True),
        "ent_coef": trial.suggest_float("ent_coef", 1e-8, 1e-2, log=True),
        "clip_range": trial.suggest_categorical("clip_range", [0.1, 0.2]),
        "n_epochs": trial.suggest_categorical("n_epochs", [1, 2]),
        "max_grad_norm": trial.suggest_float("max_grad_norm", 0.3, 2),
        "net_arch": trial.suggest_categorical("net_arch", ["tiny"]),
        "activation_fn": trial.suggest_categorical("activation_fn", ["tanh", "relu"]),
    }
    return convert_onpolicy_params(sampled)


def _sample_pevfa_params(trial: optuna.Trial, small: bool, rollout_size: int) -> dict[str, Any]:
    """Representation, objectives (of ``opr`` and ``spr``), embedding size, history size and update frequency, and critic
    learning rate.

    :param rollout_size: ``n_steps * n_envs`` of the trial: the history is sampled larger (PeVFA refuses a history
        that holds no more than one rollout)"""
    learned = ["opr", "spr", "fingerprint"]
    representation = trial.suggest_categorical("representation", learned if small else [*learned, "none"])
    sampled: dict[str, Any] = {"representation": representation}
    if representation in ("opr", "spr"):  # the objectives train these encoders only
        sampled["objectives"] = trial.suggest_categorical("objectives", ["e2e", "cl", "aux", "cl+aux"])
    if representation != "none":
        sampled["embedding_dim"] = trial.suggest_categorical("embedding_dim", [8, 16] if small else [16, 32, 64, 128])
    low, high = (10, 12) if small else (14, 19)
    low = min(max(low, math.floor(math.log2(rollout_size)) + 1), high)  # 2**low > one rollout
    sampled["history_buffer_size_pow"] = trial.suggest_int("history_buffer_size_pow", low, high)
    # 1.6 to 12.8 historical samples per env step with the default 256-sample batches (the paper: 6.4); the CL
    # objective steps on the same cadence (its train_freq=None)
    sampled["history_train_freq"] = trial.suggest_categorical("history_train_freq", [20, 40, 80, 160])
    sampled["critic_learning_rate"] = trial.suggest_float("critic_learning_rate", 1e-5, 3e-3, log=True)
    return convert_pevfa_params(sampled)


def sample_ppo_pevfa_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sampler of ``ppo_pevfa`` (``HYPERPARAMS_SAMPLER``): rl-zoo3's PPO space plus PeVFA's."""
    small = SEARCH_SPACE["name"] == "small"
    ppo = _sample_small_ppo_params(trial) if small else sample_ppo_params(trial, n_actions, n_envs, additional_args)
    return _with_fixed_params({**ppo, **_sample_pevfa_params(trial, small, ppo.get("n_steps", 2048) * n_envs)})


def sample_a2c_pevfa_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sampler of ``a2c_pevfa`` (``HYPERPARAMS_SAMPLER``): rl-zoo3's A2C space plus PeVFA's."""
    small = SEARCH_SPACE["name"] == "small"
    a2c = sample_a2c_params(trial, n_actions, n_envs, additional_args)
    return _with_fixed_params({**a2c, **_sample_pevfa_params(trial, small, a2c.get("n_steps", 5) * n_envs)})


#: Raw (trial) parameters of the off-policy PeVFA algorithms' snapshots; the rest are rl-zoo3's SAC / TD3 parameters.
OFF_POLICY_PEVFA_PARAMS = ("representation", "embedding_dim", "snapshot_freq", "history_train_freq")


def convert_off_policy_pevfa_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Converter of ``sac_pevfa`` and ``td3_pevfa`` (``HYPERPARAMS_CONVERTER``): rl-zoo3's off-policy conversion, the
    PeVFA parameters as they are (they are the constructor's)."""
    base = {key: value for key, value in sampled_params.items() if key not in OFF_POLICY_PEVFA_PARAMS}
    return {**convert_offpolicy_params(base), **{k: v for k, v in sampled_params.items() if k in OFF_POLICY_PEVFA_PARAMS}}


def _sample_off_policy_pevfa_params(trial: optuna.Trial) -> dict[str, Any]:
    """Representation (OPR, SPR, the fingerprint, the random-code control, or none), embedding size, snapshot
    interval and the gradient steps per snapshot update."""
    small = SEARCH_SPACE["name"] == "small"
    choices = ["opr", "random"] if small else ["opr", "spr", "fingerprint", "random", "none"]
    representation = trial.suggest_categorical("representation", choices)
    sampled: dict[str, Any] = {"representation": representation}
    if representation != "none":
        sampled["embedding_dim"] = trial.suggest_categorical("embedding_dim", [8, 16] if small else [16, 32, 64, 128])
    sampled["snapshot_freq"] = trial.suggest_categorical("snapshot_freq", [10, 20] if small else [250, 500, 1000, 2000])
    sampled["history_train_freq"] = trial.suggest_categorical("history_train_freq", [1, 2, 4, 8])
    return sampled


def sample_sac_pevfa_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sampler of ``sac_pevfa`` (``HYPERPARAMS_SAMPLER``): rl-zoo3's SAC space plus the snapshots'."""
    return {**sample_sac_params(trial, n_actions, n_envs, additional_args), **_sample_off_policy_pevfa_params(trial)}


def sample_td3_pevfa_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Sampler of ``td3_pevfa`` (``HYPERPARAMS_SAMPLER``): rl-zoo3's TD3 space plus the snapshots'."""
    return {**sample_td3_params(trial, n_actions, n_envs, additional_args), **_sample_off_policy_pevfa_params(trial)}


#: Sampler and converter of each PeVFA algorithm, by rl-zoo3 name.
SAMPLERS = {
    "ppo_pevfa": sample_ppo_pevfa_params,
    "a2c_pevfa": sample_a2c_pevfa_params,
    "sac_pevfa": sample_sac_pevfa_params,
    "td3_pevfa": sample_td3_pevfa_params,
}
CONVERTERS = {
    "ppo_pevfa": convert_ppo_pevfa_params,
    "a2c_pevfa": convert_ppo_pevfa_params,
    "sac_pevfa": convert_off_policy_pevfa_params,
    "td3_pevfa": convert_off_policy_pevfa_params,
}
