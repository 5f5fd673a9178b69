"""One batch of ablations of the authors'-protocol PPO on Hopper-v5: which of its mechanics holds it below the paper
protocol's PPO in the first 200k env steps?

Each variant is the authors'-protocol PPO (``sb3_pevfa.protocols.authors_protocol("ppo")``) with one thing changed,
trained by the campaign engine's own ``train`` (the same envs, seeds and evaluations as the grid ``table1-authors``):

- ``std``: SB3's log-std (initial 0, the actor's learning rate) in place of theirs (initial -0.5, 6.5x the rate);
- ``minibatch``: the actor in minibatches of the critic's size (about 15 per epoch, 10 epochs) in place of 10
  full-batch steps;
- ``std+minibatch``: both;
- ``deterministic-eval``: unchanged training, evaluated with the deterministic policy (the paper protocol's
  evaluation) in place of sampled actions (its evaluations draw no random numbers, so its training differs from the
  stored run's from the first evaluation on).

The unchanged PPO is the grid's stored runs (their curves up to the same step). Each run is written to ``--out`` as
JSON as soon as it ends, and skipped when its file is there.

    python docs/notes/scripts/ppo_authors_ablation.py --seeds 0 1 2 --steps 200000 \
        --out docs/results/notes/ppo-two-protocols/ablation
"""

import argparse
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "benchmarks"))

from engine import definitions, training  # noqa: E402

from sb3_pevfa.protocols import authors_protocol  # noqa: E402

VARIANTS = {
    "std": authors_protocol("ppo", policy_kwargs=dict(log_std_init=0.0, log_std_lr_scale=1.0)),
    "minibatch": authors_protocol("ppo", actor_batch_size=None),
    "std+minibatch": authors_protocol(
        "ppo", actor_batch_size=None, policy_kwargs=dict(log_std_init=0.0, log_std_lr_scale=1.0)
    ),
    "deterministic-eval": authors_protocol("ppo"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="Hopper-v5")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    grid = definitions.CAMPAIGNS["table1-authors"]
    for seed in args.seeds:
        for variant in args.variants:
            path = args.out / f"{variant}-seed{seed}.json"
            if path.exists():
                continue
            definitions.VARIANTS["authors"][variant] = VARIANTS[variant]
            training.STOCHASTIC_EVALUATION = set() if variant == "deterministic-eval" else {"authors"}
            campaign = definitions.Campaign(
                "authors", (args.task,), (variant,), (seed,), args.steps, grid.eval_freq, grid.eval_episodes
            )
            result = training.train(campaign, args.task, variant, seed)
            keep = ("curve", "max_average_return", "cpu_seconds", "wall_seconds", "timesteps", "commit")
            path.write_text(json.dumps({"variant": variant, "seed": seed, **{k: result[k] for k in keep}}))
            print(variant, seed, round(result["max_average_return"]), flush=True)


if __name__ == "__main__":
    main()
