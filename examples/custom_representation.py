"""Custom PeVFA settings: representation sizes, SPR with both extra objectives, the critic's shape, the paper's
update order and learning rates. Each configuration trains briefly and prints what it built and logged.

    python examples/custom_representation.py                 # Pendulum-v1, 10k steps each
    python examples/custom_representation.py --tiny          # seconds (CI)
"""

import argparse
import csv
import pathlib

import torch as th
from stable_baselines3.common.logger import configure

from sb3_pevfa import PPOPeVFA

CONFIGURATIONS = {
    # OPR with a smaller row encoder and a 32-d chi
    "opr-small": dict(
        representation="opr",
        embedding_dim=32,
        representation_kwargs=dict(layer_arch=(16, 16, 8), log_std_arch=(16, 8)),
    ),
    # SPR on 100 recorded state-action pairs (60 % kept per training call), plus the contrastive (CL) and
    # action-prediction (AUX) objectives with their own schedules
    "spr-cl-aux": dict(
        representation="spr",
        n_state_action_pairs=100,
        representation_kwargs=dict(pair_arch=(64, 64), subsample=0.6),
        representation_objectives=("cl", "aux"),
        objective_kwargs=dict(
            cl=dict(batch_policies=16, momentum=0.05, train_freq=20, learning_starts=0),
            aux=dict(batch_policies=8, pairs_per_policy=16, train_freq=20, learning_starts=0),
        ),
    ),
    # the paper's order and rates: critic first, Monte-Carlo value targets, actor 1e-4 / critic 1e-3
    "paper-order": dict(update_order="critic_first", value_target_lambda=1.0, learning_rate=1e-4, critic_learning_rate=1e-3),
    # the critic: element-wise product of the state stream and the chi stream, a wider head
    "product-critic": dict(
        policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[64]), critic_combine="product", critic_head_arch=[256]),
    ),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--timesteps", type=int, default=10_000)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/custom_representation"))
    parser.add_argument("--tiny", action="store_true", help="512 steps each with 128-step rollouts (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    small = dict(n_steps=128, batch_size=64, history_learning_starts=0) if args.tiny else {}
    for name, options in CONFIGURATIONS.items():
        model = PPOPeVFA("MlpPolicy", args.env, seed=0, **small, **options)
        model.set_logger(configure(str(args.out / name), ["csv"]))  # SB3's train/* and PeVFA's pevfa/* logs
        model.learn(512 if args.tiny else args.timesteps)
        encoder = model.policy.representation
        n_params = sum(p.numel() for p in encoder.parameters())
        print(f"{name}: {type(encoder).__name__} ({n_params} parameters, chi of size {encoder.embedding_dim}), "
              f"{model.history.n_policies} policies recorded")  # fmt: skip
        with open(args.out / name / "progress.csv") as handle:
            last = list(csv.DictReader(handle))[-1]
        print("   " + ", ".join(f"{k}={float(v):.3g}" for k, v in sorted(last.items()) if k.startswith("pevfa/") and v))


if __name__ == "__main__":
    main()
