"""What the fast path saves: CPU time of each piece of ``sb3_pevfa.pevfa.fast_path`` against SB3's own loop.

For each env a PeVFA model is warmed up (``--warmup`` steps, seed 0), then the two code paths are timed
alternately (A B A B, ``--repeats`` times) on the same model: a whole rollout (``collect_rollouts``: SB3's acts with
the actor and the critic at every step; the fast path acts with the actor alone and evaluates the critic once,
batched, afterwards) and a whole actor-critic update on that rollout (``_train_actor_critic``: SB3's own update on
both paths since the lean PPO update was removed, so these columns show the measurement's noise; the results of
commit 083bf99 in docs/results/notes/fast-path-redesign/fast_path.json timed the lean update). Times are
``time.process_time`` of this process, one torch thread, reported per environment step (median and spread over the
repeats).

    python docs/notes/scripts/fast_path.py --algo ppo_pevfa a2c_pevfa --env Hopper-v5 CartPole-v1 \
        --out docs/results/notes/fast-path-redesign/fast_path.json
"""

import argparse
import json
import pathlib
import time

import numpy as np
import torch as th

from sb3_pevfa import A2CPeVFA, PPOPeVFA

ALGORITHMS = {"ppo_pevfa": PPOPeVFA, "a2c_pevfa": A2CPeVFA}


def timed(function) -> float:
    start = time.process_time()
    function()
    return time.process_time() - start


def measure(algo: str, env_id: str, warmup: int, repeats: int, rollouts: int) -> dict:
    """Per-step CPU milliseconds of rollout and update on both paths, ``rollouts`` rollouts per measurement."""
    model = ALGORITHMS[algo]("MlpPolicy", env_id, seed=0)
    model.learn(warmup)
    _, callback = model._setup_learn(10**9, reset_num_timesteps=False)
    steps = model.n_steps * model.n_envs * rollouts
    times: dict[str, list[float]] = {f"{piece}_{path}": [] for piece in ("rollout", "update") for path in ("sb3", "fast")}
    for _ in range(repeats):
        for path in ("sb3", "fast"):
            model.fast_path = path == "fast"
            rollout = update = 0.0
            for _ in range(rollouts):
                rollout += timed(lambda: model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps))
                model.policy.set_training_mode(True)
                update += timed(model._train_actor_critic)
            times[f"rollout_{path}"].append(1e3 * rollout / steps)
            times[f"update_{path}"].append(1e3 * update / steps)
    result = {"algo": algo, "env": env_id, "warmup": warmup, "repeats": repeats, "steps_per_measurement": steps}
    for key, values in times.items():
        result[f"{key}_ms_per_step"] = {"median": float(np.median(values)), "min": min(values), "max": max(values)}
    for piece in ("rollout", "update"):
        sb3, fast = (result[f"{piece}_{path}_ms_per_step"]["median"] for path in ("sb3", "fast"))
        result[f"{piece}_saved_ms_per_step"] = sb3 - fast
    return result


def table(results: list[dict]) -> str:
    lines = [
        "| algo | env | rollout SB3 | rollout fast | saved | update SB3 | update fast | saved |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        cells = [r["algo"], r["env"]]
        for piece in ("rollout", "update"):
            sb3, fast = (r[f"{piece}_{path}_ms_per_step"] for path in ("sb3", "fast"))
            saved = r[f"{piece}_saved_ms_per_step"]
            cells += [
                f"{sb3['median']:.3f} [{sb3['min']:.3f}, {sb3['max']:.3f}]",
                f"{fast['median']:.3f} [{fast['min']:.3f}, {fast['max']:.3f}]",
                f"{saved:.3f} ({saved / sb3['median']:.0%})",
            ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", nargs="+", default=["ppo_pevfa"], choices=list(ALGORITHMS))
    parser.add_argument("--env", nargs="+", default=["Hopper-v5"])
    parser.add_argument("--warmup", type=int, default=6144, help="untimed steps first (history training running)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rollouts", type=int, default=0, help="rollouts per measurement (0: ~2048 steps' worth)")
    parser.add_argument("--out", type=pathlib.Path, default=None, help="write the results as JSON")
    args = parser.parse_args()
    th.set_num_threads(1)
    results = []
    for algo in args.algo:
        for env_id in args.env:
            n_steps = ALGORITHMS[algo]("MlpPolicy", env_id).n_steps
            rollouts = args.rollouts or max(1, 2048 // n_steps)
            results.append(measure(algo, env_id, args.warmup, args.repeats, rollouts))
            print(table(results[-1:]), flush=True)
    print(table(results))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
