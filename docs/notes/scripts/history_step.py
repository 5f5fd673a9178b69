"""CPU time of one historical critic update, by batch size and policies per batch (``history_batch_policies``).

A PPOPeVFA model on ``--env`` gets a history of ``--policies`` recorded policies (the live actor, perturbed
between records) with 2048 samples each; then each ``(batch size, policies per batch)`` setting times
``--steps`` historical updates (``PeVFAAlgorithm._train_on_history``: sample, encode, value loss, critic step)
after 5 untimed ones. "uniform" is the paper's sampling (a batch of 64 from ~47 distinct policies at the
steady state). Per env step, a setting costs ``ms per update / history_train_freq``.

    python docs/notes/scripts/history_step.py --env Hopper-v5 --arch 64 64
    python docs/notes/scripts/history_step.py --env Hopper-v5 --arch 256 256
"""

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch as th

from sb3_pevfa import PPOPeVFA

#: (history_batch_size, history_batch_policies) settings timed; None: uniform samples (the paper's)
SETTINGS = [(64, None), (64, 8), (256, None), (256, 8), (256, 4), (512, 8)]


def history_model(env_id: str, arch: list[int], n_policies: int, **kwargs) -> PPOPeVFA:
    """A model (PPOPeVFA's ``kwargs``) whose history holds ``n_policies`` distinct records of 2048 samples each."""
    policy_kwargs = dict(net_arch=dict(pi=arch, vf=arch))
    model = PPOPeVFA("MlpPolicy", env_id, seed=0, policy_kwargs=policy_kwargs, **kwargs)
    model._last_obs = model.env.reset()
    rng = np.random.default_rng(0)
    obs_shape = model.observation_space.shape
    for _ in range(n_policies):
        with th.no_grad():
            for param in model.policy.action_net.parameters():
                param.add_(0.01 * th.randn_like(param))  # a new policy: the recorder skips unchanged actors
        policy_id = model.recorder.record(model.policy, model._last_obs, n_updates=0, num_timesteps=0)
        observations = rng.normal(size=(2048, *obs_shape)).astype(np.float32)
        model.history.add_samples(observations, rng.normal(size=2048).astype(np.float32), policy_id)
    model.num_timesteps = model.history_learning_starts
    return model


def cpu_ms_per_step(model: PPOPeVFA, run: Callable[[int], int], steps: int) -> float:
    """CPU milliseconds per step of ``run(n)`` (takes exactly ``n`` steps, returns how many it took), timed over
    ``steps`` after 5 untimed ones."""
    model.policy.set_training_mode(True)
    for n in (5, steps):
        start = time.process_time()
        assert run(n) == n
    return (time.process_time() - start) / steps * 1e3


def time_updates(model: PPOPeVFA, batch_size: int, batch_policies: int | None, steps: int) -> float:
    """CPU milliseconds per historical update."""
    model.history_batch_size, model.history_batch_policies = batch_size, batch_policies

    def run(n: int) -> int:
        model._history_credit = n * model.history_train_freq - model.n_steps * model.n_envs  # exactly n updates
        return len(model._train_on_history())

    return cpu_ms_per_step(model, run, steps)


def parse_arguments(doc: str, policies: int, policies_help: str) -> argparse.Namespace:
    """The step benchmarks' command line (``--env``, ``--arch``, ``--policies``, ``--steps``); one torch thread."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--arch", nargs="+", type=int, default=[64, 64], help="actor (and state stream) layers")
    parser.add_argument("--policies", type=int, default=policies, help=policies_help)
    parser.add_argument("--steps", type=int, default=100)
    th.set_num_threads(1)
    return parser.parse_args()


def main() -> None:
    args = parse_arguments(__doc__, 98, "policies in the history (200k samples: ~98)")
    model = history_model(args.env, args.arch, args.policies)
    print(f"| {args.env}, actor {args.arch}, {args.policies} policies | ms per update | us per sample |")
    print("|---|---|---|")
    for batch_size, batch_policies in SETTINGS:
        ms = time_updates(model, batch_size, batch_policies, args.steps)
        label = f"{batch_size} samples, " + ("uniform" if batch_policies is None else f"{batch_policies} policies")
        print(f"| {label} | {ms:.2f} | {ms / batch_size * 1e3:.1f} |", flush=True)


if __name__ == "__main__":
    main()
