"""One batch of ablations of the authors'-protocol PPO on Hopper-v5: which of its mechanics holds it below the paper
protocol's PPO in the first 200k env steps?

Each variant is the authors'-protocol PPO (``sb3_pevfa.protocols.authors_protocol("ppo")``) with one thing changed,
trained by the campaign engine's own ``train`` (the same envs, seeds and evaluations as the grid ``table1-authors``):

- ``std``: SB3's log-std (initial 0, the actor's learning rate) in place of theirs (initial -0.5, 6.5x the rate);
- ``minibatch``: the actor in minibatches of 128 (the protocol's ``batch_size``), 10 epochs, in place of 10 full-batch
  steps;
- ``std+minibatch``: both;
- ``deterministic-eval``: unchanged training, evaluated with the deterministic policy (the paper protocol's
  evaluation) in place of sampled actions (its evaluations draw no random numbers, so its training differs from the
  stored run's from the first evaluation on).

The unchanged PPO is the grid's stored runs (their curves up to the same step). Each run is written to ``--out`` as
JSON as soon as it ends, and skipped when its file is there. ``--report`` prints the best evaluation so far per
variant (mean and each seed's) beside the stored runs of both protocols' PPO on the same seeds.

    python docs/notes/scripts/ppo_authors_ablation.py --seeds 0 1 2 --steps 200000 \
        --out docs/results/notes/ppo-two-protocols/ablation
    python docs/notes/scripts/ppo_authors_ablation.py --report --out docs/results/notes/ppo-two-protocols/ablation
"""

import argparse
import json
import pathlib
import sys

import numpy as np

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


def best_by(curve: dict, steps: int) -> float:
    """The best evaluation made at or before ``steps`` env steps."""
    return max(m for s, m in zip(curve["steps"], curve["mean"]) if s <= steps)


def report(out: pathlib.Path, task: str, checkpoints: tuple[int, ...] = (100_000, 200_000)) -> None:
    """Per variant: its best evaluation by each checkpoint, mean over seeds and per seed, and its CPU minutes; the
    stored PPO runs of both protocols on the same seeds beside."""
    from engine.results import collect

    made: dict[str, dict[int, dict]] = {}
    for path in sorted(out.glob("*.json")):
        run = json.loads(path.read_text())
        made.setdefault(run["variant"], {})[run["seed"]] = run
    seeds = sorted({seed for runs in made.values() for seed in runs})
    rows = {}
    for label, campaign in (("authors' PPO (stored)", "table1-authors"), ("paper protocol's PPO (stored)", "table1")):
        runs, *_ = collect([campaign], None)
        rows[label] = {r["seed"]: r for r in runs[task]["ppo"] if r["seed"] in seeds}
    rows.update({f"authors' PPO, {variant}": runs for variant, runs in made.items()})
    head = " | ".join(f"by {c // 1000}k: mean (seeds {', '.join(map(str, seeds))})" for c in checkpoints)
    print(f"| {task} | {head} | CPU-min (wall-min) per 100k |\n|---" + "|---" * (len(checkpoints) + 1) + "|")
    for label, runs in rows.items():
        cells = []
        for c in checkpoints:
            best = {seed: best_by(run["curve"], c) for seed, run in runs.items()}
            each = ", ".join(f"{best[s]:.0f}" if s in best else "—" for s in seeds)
            cells.append(f"{np.mean(list(best.values())):.0f} ({each})")
        cpu, wall = (np.mean([run[key] / run["timesteps"] * 100_000 / 60 for run in runs.values()])
                     for key in ("cpu_seconds", "wall_seconds"))  # fmt: skip
        print(f"| {label} | " + " | ".join(cells) + f" | {cpu:.1f} ({wall:.1f}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="Hopper-v5")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--report", action="store_true", help="only print the table of the runs in --out")
    args = parser.parse_args()
    if args.report:
        return report(args.out, args.task)
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
