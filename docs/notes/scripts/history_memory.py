"""Memory of the policy history as a run grows: the store's own ``nbytes`` after 100k, 300k and 1M environment steps.

The history is filled exactly as PPOPeVFA fills it (one record per update of the model's real actor, the rollout's
samples), with the model's default settings; only the environment interaction is skipped, since the footprint depends
on the counts and shapes alone.

    python docs/notes/scripts/history_memory.py --env Hopper-v5 \
        --out docs/results/notes/history-memory/history_memory_hopper.json
"""

import argparse
import json
import pathlib

import numpy as np
import torch as th

from sb3_pevfa import PPOPeVFA


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--representation", default="opr")
    parser.add_argument("--steps", type=int, nargs="+", default=[100_000, 300_000, 1_000_000])
    parser.add_argument("--out", type=pathlib.Path, default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    model = PPOPeVFA("MlpPolicy", args.env, representation=args.representation, seed=0)
    history, policy = model.history, model.policy
    rollout = model.n_steps * model.n_envs
    rng = np.random.default_rng(0)
    observations = np.stack([model.observation_space.sample() for _ in range(rollout)]).astype(np.float32)
    rows, steps = [], 0
    for checkpoint in sorted(args.steps):
        while steps < checkpoint:
            with th.no_grad():
                next(policy.action_net.parameters()).add_(1e-3)  # another policy: the recorder skips unchanged ones
            policy_id = model.recorder.record(policy, observations)
            history.add_samples(observations, rng.normal(size=rollout), policy_id)
            steps += rollout
        rows.append(
            {"steps": steps, "policies": history.n_policies, "samples": history.n_samples, "mb": history.nbytes / 2**20}
        )
        print(
            f"{steps:>9} steps: {history.n_policies} policies, {history.n_samples} samples, {history.nbytes / 2**20:.1f} MiB"
        )
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"env": args.env, "representation": args.representation, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
