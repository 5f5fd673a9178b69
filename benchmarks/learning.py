"""Learning comparison: SB3 PPO vs PPOPeVFA variants at identical PPO hyperparameters.

Every (variant, seed) run is a separate process (one torch thread each, ``--workers`` at a time) that writes its own
JSON file (evaluation curve, wall time), so an interrupted sweep loses at most the runs in flight. Runs whose file
already exists are skipped. Summarise with ``python benchmarks/learning.py --report``.

Example (the numbers in docs/benchmarks.md)::

    python benchmarks/learning.py --env Hopper-v5 --variants ppo pevfa-opr --seeds 0 1 2 3 4 \\
        --timesteps 150000 --out docs/results/learning
"""

import argparse
import json
import multiprocessing as mp
import pathlib
import time

import numpy as np

#: PeVFA options of each variant; "ppo" is SB3's PPO. PPO hyperparameters are SB3's defaults for all.
VARIANTS: dict[str, dict | None] = {
    "ppo": None,
    "pevfa-none": dict(representation="none"),
    "pevfa-random": dict(representation="random"),
    "pevfa-opr": dict(representation="opr"),
    "pevfa-spr": dict(representation="spr"),
    "pevfa-opr-critic-first": dict(representation="opr", update_order="critic_first"),
    "pevfa-opr-cl": dict(representation="opr", representation_objectives=("cl",)),
    "pevfa-spr-aux": dict(representation="spr", representation_objectives=("aux",)),
    "pevfa-opr-paper": dict(
        representation="opr",
        update_order="critic_first",
        value_target_lambda=1.0,
        learning_rate=1e-4,
        critic_learning_rate=1e-3,
    ),
}


def run(variant: str, env_id: str, seed: int, timesteps: int, eval_freq: int, eval_episodes: int, out: pathlib.Path) -> None:
    import torch as th
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.logger import configure

    from sb3_pevfa import PPOPeVFA

    th.set_num_threads(1)
    env = make_vec_env(env_id, n_envs=1, seed=seed)
    eval_env = make_vec_env(env_id, n_envs=1, seed=seed + 10_000)
    options = VARIANTS[variant]
    model = PPO("MlpPolicy", env, seed=seed) if options is None else PPOPeVFA("MlpPolicy", env, seed=seed, **options)
    # SB3's train/* and PeVFA's pevfa/* logs of every run, for diagnostics
    model.set_logger(configure(str(out / "logs" / f"{env_id}_{variant}_seed{seed}"), ["csv"]))
    curve, start = [], time.perf_counter()
    for _ in range(timesteps // eval_freq):
        model.learn(eval_freq, reset_num_timesteps=False)
        mean, std = evaluate_policy(model, eval_env, n_eval_episodes=eval_episodes, deterministic=True)
        curve.append({"timesteps": model.num_timesteps, "mean_return": float(mean), "std_return": float(std)})
    result = {
        "variant": variant,
        "options": options,
        "env": env_id,
        "seed": seed,
        "timesteps": timesteps,
        "wall_time_s": time.perf_counter() - start,
        "curve": curve,
    }
    (out / f"{env_id}_{variant}_seed{seed}.json").write_text(json.dumps(result, indent=1))
    print(f"{env_id} {variant} seed {seed}: max {max(c['mean_return'] for c in curve):.0f}", flush=True)


def report(out: pathlib.Path) -> str:
    """Markdown table: max / final average return, mean and std over seeds, and the wall time per run."""
    results: dict[tuple[str, str], list[dict]] = {}
    for path in sorted(out.glob("*.json")):
        result = json.loads(path.read_text())
        results.setdefault((result["env"], result["variant"]), []).append(result)
    lines = [
        "| env | variant | seeds | max avg return | final avg return | wall time / run (s) |",
        "|---|---|---|---|---|---|",
    ]
    for (env_id, variant), runs in sorted(results.items()):
        best = np.array([max(c["mean_return"] for c in r["curve"]) for r in runs])
        final = np.array([r["curve"][-1]["mean_return"] for r in runs])
        wall = np.mean([r["wall_time_s"] for r in runs])
        seeds = ",".join(str(r["seed"]) for r in sorted(runs, key=lambda r: r["seed"]))
        lines.append(
            f"| {env_id} | {variant} | {seeds} | {best.mean():.0f} ± {best.std():.0f} | "
            f"{final.mean():.0f} ± {final.std():.0f} | {wall:.0f} |"
        )
    return "\n".join(lines)


def plot(out: pathlib.Path, png: pathlib.Path) -> None:
    """Learning curves per env: mean over seeds with a band of one std, every variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results: dict[str, dict[str, list[dict]]] = {}
    for path in sorted(out.glob("*.json")):
        result = json.loads(path.read_text())
        results.setdefault(result["env"], {}).setdefault(result["variant"], []).append(result)
    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4), squeeze=False)
    colors = {variant: f"C{i}" for i, variant in enumerate(sorted({v for variants in results.values() for v in variants}))}
    for ax, (env_id, variants) in zip(axes[0], sorted(results.items())):
        for variant, runs in sorted(variants.items()):
            n = min(len(r["curve"]) for r in runs)
            steps = np.array([c["timesteps"] for c in runs[0]["curve"][:n]])
            returns = np.array([[c["mean_return"] for c in r["curve"][:n]] for r in runs])
            mean, std = returns.mean(axis=0), returns.std(axis=0)
            ax.plot(steps, mean, color=colors[variant], label=f"{variant} ({len(runs)} seeds)")
            ax.fill_between(steps, mean - std, mean + std, color=colors[variant], alpha=0.2)
        ax.set(title=env_id, xlabel="environment steps", ylabel="average return (10 episodes)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--variants", nargs="+", default=["ppo", "pevfa-opr"], choices=sorted(VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--timesteps", type=int, default=150_000)
    parser.add_argument("--eval-freq", type=int, default=10_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/learning"))
    parser.add_argument("--report", action="store_true", help="only print the table of the results in --out")
    parser.add_argument("--plot", type=pathlib.Path, default=None, help="also write learning curves to this PNG")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report:
        jobs = [
            (variant, args.env, seed, args.timesteps, args.eval_freq, args.eval_episodes, args.out)
            for seed in args.seeds
            for variant in args.variants
            if not (args.out / f"{args.env}_{variant}_seed{seed}.json").exists()
        ]
        with mp.get_context("spawn").Pool(args.workers, maxtasksperchild=1) as pool:
            pool.starmap(run, jobs, chunksize=1)
    print(report(args.out))
    if args.plot is not None:
        plot(args.out, args.plot)


if __name__ == "__main__":
    main()
