"""Tune PPOPeVFA with Optuna's own API: TPE sampling, median pruning on periodic evaluations.

One process:

    python examples/optuna_search.py --env CartPole-v1 --n-trials 20 --timesteps 50000

Several workers sharing one study (run the same command in several shells or on several machines):

    # one machine: a journal file (or sqlite:///study.db)
    python examples/optuna_search.py --storage study.log --study-name pevfa-cartpole --n-trials 10
    # many machines: a PostgreSQL server they all reach
    python examples/optuna_search.py --storage postgresql://user:password@host/db --study-name pevfa --n-trials 10

The search space is rl-zoo3's PPO space plus PeVFA's (``sb3_pevfa.rl_zoo.hyperparams_opt``); the trials are
evaluated and pruned by rl-zoo3's ``TrialEvalCallback``.
"""

import argparse
import os

import optuna
import torch as th
from rl_zoo3.callbacks import TrialEvalCallback
from stable_baselines3.common.env_util import make_vec_env

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.rl_zoo.hyperparams_opt import SEARCH_SPACE, sample_ppo_pevfa_params


def make_storage(storage: str | None) -> optuna.storages.BaseStorage | str | None:
    """A path ending in ``.log`` is a journal file (safe for several local processes); anything else is an
    RDB URL (``sqlite:///study.db``, ``postgresql://...``)."""
    if storage is not None and storage.endswith(".log"):
        return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
    return storage


def objective(trial: optuna.Trial, args: argparse.Namespace) -> float:
    env = make_vec_env(args.env, n_envs=1, seed=args.seed + trial.number)
    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 10_000 + trial.number)
    n_actions = env.action_space.shape[0] if env.action_space.shape else 1
    params = sample_ppo_pevfa_params(trial, n_actions, env.num_envs, {})
    trial.set_user_attr("worker", os.getpid())
    model = PPOPeVFA("MlpPolicy", env, seed=args.seed, **params)
    eval_freq = max(args.timesteps // args.n_evaluations, 1)
    callback = TrialEvalCallback(eval_env, trial, n_eval_episodes=args.eval_episodes, eval_freq=eval_freq)
    try:
        model.learn(args.timesteps, callback=callback)
    except (AssertionError, ValueError) as error:  # e.g. NaN losses: report the trial as pruned
        raise optuna.TrialPruned(str(error)) from error
    if callback.is_pruned:
        raise optuna.TrialPruned()
    return callback.last_mean_reward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--n-trials", type=int, default=20)
    parser.add_argument("--timesteps", type=int, default=50_000)
    parser.add_argument("--n-evaluations", type=int, default=5)
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--storage", default=None, help="journal file (*.log), sqlite:///file.db or postgresql://...")
    parser.add_argument("--study-name", default="ppo_pevfa")
    parser.add_argument("--search-space", choices=["full", "small"], default="full")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tiny", action="store_true", help="2 trials of 1k steps, the small space (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.tiny:
        args.n_trials, args.timesteps, args.n_evaluations, args.eval_episodes, args.search_space = 2, 1024, 2, 2, "small"
    SEARCH_SPACE["name"] = args.search_space

    study = optuna.create_study(
        storage=make_storage(args.storage),
        study_name=args.study_name,
        direction="maximize",
        load_if_exists=True,
        sampler=optuna.samplers.TPESampler(n_startup_trials=5),
        pruner=optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=args.n_evaluations // 3),
    )
    study.optimize(lambda trial: objective(trial, args), n_trials=args.n_trials)
    completed = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if completed:
        print(f"best of {len(study.trials)} trials: {study.best_value:.1f} with {study.best_params}")


if __name__ == "__main__":
    main()
