"""Float32 denormals: whole runs from scratch of SB3 PPO and PPOPeVFA, each with and without them flushed to zero.

ReLU units that stop receiving gradient leave Adam's moments decaying through the denormal range, where the CPU
computes in microcode (``sb3_pevfa.pevfa.denormals``). PPOPeVFA flushes them in its update by default
(``flush_denormal=True``); SB3 PPO as shipped does not, and a user can make it (``torch.set_flush_denormal(True)``,
for the whole run here). Each run: CPU time (``time.process_time``) and wall-clock of construction plus ``learn``,
one torch thread, the variants of a seed one after the other in this process, and at the end the fraction of
Adam's moment entries that are denormal (with flushing: 0).

    # rl-zoo3's tuned entries (256x256 ReLU networks, VecNormalize), 60k steps, and SB3's defaults (64x64 Tanh)
    python docs/notes/scripts/denormals.py --conf benchmarks/hyperparams/zoo_tuned.yml --env Hopper-v5 \
        --timesteps 60000 --seeds 0 1 --out docs/results/notes/denormals/tuned_hopper.json
    python docs/notes/scripts/denormals.py --env Hopper-v5 --timesteps 100000 --seeds 0 1 \
        --out docs/results/notes/denormals/default_hopper.json
    # one table of several files
    python docs/notes/scripts/denormals.py --report docs/results/notes/denormals/*.json
"""

import argparse
import json
import pathlib
import sys
import time

import numpy as np
import torch as th
from stable_baselines3 import PPO

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.pevfa.denormals import flush_denormals

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[3] / "benchmarks"))
from profile_iteration import zoo_entry  # benchmarks/profile_iteration.py: an rl-zoo3 entry, built as the zoo does

#: name -> (algorithm, its extra arguments, denormals flushed for the whole run)
VARIANTS = {
    "ppo": (PPO, {}, False),
    "ppo-flush-denormal": (PPO, {}, True),
    "pevfa": (PPOPeVFA, {}, False),  # its default: flushed in its update only
    "pevfa-no-flush-denormal": (PPOPeVFA, {"flush_denormal": False}, False),
}


def denormal_fraction(optimizer: th.optim.Optimizer) -> float:
    """Fraction of the optimizer state's float32 entries (Adam's moments) that are denormal."""
    tiny = th.finfo(th.float32).tiny
    denormal, total = 0, 0
    for state in optimizer.state.values():
        for value in state.values():
            if isinstance(value, th.Tensor) and value.dtype == th.float32 and value.dim() > 0:
                denormal += int(((value != 0) & (value.abs() < tiny)).sum())
                total += value.numel()
    return denormal / max(total, 1)


def run(variant: str, env_id: str, conf: pathlib.Path | None, timesteps: int, seed: int) -> dict:
    algo, extra, flushed = VARIANTS[variant]
    cpu, wall = time.process_time(), time.perf_counter()
    with flush_denormals(flushed):
        env, kwargs = zoo_entry(conf, env_id)
        model = algo("MlpPolicy", env, seed=seed, **kwargs, **extra)
        model.learn(timesteps)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    returns = [info["r"] for info in model.ep_info_buffer]
    return {
        "variant": variant, "env": env_id, "conf": str(conf) if conf else None, "seed": seed, "timesteps": timesteps,
        "cpu_s": cpu, "wall_s": wall,
        "steps_per_cpu_s": timesteps / cpu, "steps_per_s": timesteps / wall,
        "denormal_fraction": denormal_fraction(model.policy.optimizer),
        "last_100_episodes_return": float(np.mean(returns)) if returns else None,
    }  # fmt: skip


def settings(row: dict) -> str:
    """What a row's runs are compared within: its settings, env and steps."""
    conf = pathlib.Path(row["conf"]).stem if row.get("conf") else "SB3 defaults"
    return f"{conf}, {row['env']}, {row['timesteps'] // 1000}k"


def ratio(runs: list[dict], baseline: list[dict], key: str) -> float:
    """Mean of ``key`` over ``runs`` / over ``baseline``, both over the seeds they share (nan if none)."""
    seeds = {r["seed"] for r in runs} & {r["seed"] for r in baseline}
    if not seeds:
        return float("nan")
    return float(
        np.mean([r[key] for r in runs if r["seed"] in seeds]) / np.mean([r[key] for r in baseline if r["seed"] in seeds])
    )


def table(rows: list[dict]) -> str:
    """Per (settings, env, steps) and variant: mean ± std over seeds of steps per CPU-second and per wall-clock second,
    as ratios to SB3 PPO as shipped (and CPU to PPO flushed) over the seeds both ran, and the denormal fraction of
    Adam's moments at the end."""
    lines = [
        "| settings, env, steps | variant | seeds | steps/CPU-s | vs ppo (CPU) | vs flushed ppo (CPU) | steps/s (wall) "
        "| vs ppo (wall) | denormal moments, end |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for task in dict.fromkeys(settings(r) for r in rows):
        runs = {v: [r for r in rows if settings(r) == task and r["variant"] == v] for v in VARIANTS}
        for variant, done in runs.items():
            if not done:
                continue
            cpu, wall = np.array([r["steps_per_cpu_s"] for r in done]), np.array([r["steps_per_s"] for r in done])
            seeds = ", ".join(str(r["seed"]) for r in done)
            lines.append(
                f"| {task} | {variant} | {seeds} | {cpu.mean():.0f} ± {cpu.std():.0f} | "
                f"{ratio(done, runs['ppo'], 'steps_per_cpu_s'):.2f}x | "
                f"{ratio(done, runs['ppo-flush-denormal'], 'steps_per_cpu_s'):.2f}x | {wall.mean():.0f} ± {wall.std():.0f} | "
                f"{ratio(done, runs['ppo'], 'steps_per_s'):.2f}x | {np.mean([r['denormal_fraction'] for r in done]):.2%} |"
            )
    returns = {(r["variant"], settings(r), r["seed"]): r["last_100_episodes_return"] for r in rows}
    pairs = [
        (returns[(plain, *rest)], returns[(flushed, *rest)])
        for plain, flushed in (("ppo", "ppo-flush-denormal"), ("pevfa-no-flush-denormal", "pevfa"))
        for variant, *rest in returns
        if variant == plain and (flushed, *rest) in returns
    ]
    same = sum(a == b for a, b in pairs)
    lines += ["", "Runs with and without flushing (same algorithm, settings, env, steps and seed) that ended with the "
              f"same mean return of their last 100 training episodes: {same} of {len(pairs)}."]  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Hopper-v5"])
    parser.add_argument("--conf", type=pathlib.Path, default=None, help="rl-zoo3 hyperparameters (each env's entry)")
    parser.add_argument("--timesteps", type=int, default=60_000)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", type=pathlib.Path, help="JSON file of every run (appended to)")
    parser.add_argument("--report", nargs="*", type=pathlib.Path, help="only print the table of these JSON files")
    args = parser.parse_args()
    if args.report is not None:
        print(table([row for path in args.report for row in json.loads(path.read_text())]))
        return
    if args.out is None:
        parser.error("--out is required unless --report is given")
    th.set_num_threads(1)
    PPO("MlpPolicy", args.env[0], n_steps=64, batch_size=64).learn(64)  # untimed: the process's one-time costs
    rows = json.loads(args.out.read_text()) if args.out.exists() else []
    for seed in args.seeds:
        for env_id in args.env:
            for variant in args.variants:
                rows.append(run(variant, env_id, args.conf, args.timesteps, seed))
                args.out.write_text(json.dumps(rows, indent=1))
                print(f"{variant} {env_id} seed {seed}: {rows[-1]['steps_per_cpu_s']:.0f} steps/CPU-s", flush=True)
    print(table(rows))


if __name__ == "__main__":
    main()
