"""One training of the zoo protocol: a process of rl-zoo3's entry point (``python -m sb3_pevfa.train``) on one
hyperparameter file per base algorithm, the variant's PeVFA options added (``--hyperparams``); rl-zoo3's EvalCallback
evaluates it, and its ``evaluations.npz`` becomes one JSON record per run (``<out>/<env>_<variant>_seed<seed>.json``)."""

import argparse
import inspect
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

import numpy as np
import yaml
from stable_baselines3 import A2C, PPO

from .definitions import CONFS, ZOO_VARIANTS, base_algorithm


def run_name(env_id: str, variant: str, seed: int) -> str:
    return f"{env_id}_{variant}_seed{seed}"


def conf_file(variant: str, args: argparse.Namespace) -> pathlib.Path:
    return args.conf or CONFS[base_algorithm(variant)]


def variant_options(variant: str, env_id: str, conf: pathlib.Path) -> dict | None:
    """The variant's rl-zoo3 ``--hyperparams`` for ``env_id``'s entry of ``conf``: ``critic_learning_rate_scale``
    resolved into a ``critic_learning_rate`` of that multiple of the entry's constant ``learning_rate`` (the base
    algorithm's default if it has none), and ``policy_kwargs`` added to the entry's own (which rl-zoo3 would replace)."""
    options = ZOO_VARIANTS[variant]
    if not options or not {"critic_learning_rate_scale", "policy_kwargs"} & set(options):
        return options
    options = dict(options)
    entry = yaml.safe_load(conf.read_text())[env_id]
    if "critic_learning_rate_scale" in options:
        scale = options.pop("critic_learning_rate_scale")
        default = inspect.signature({"ppo": PPO, "a2c": A2C}[base_algorithm(variant)]).parameters["learning_rate"].default
        learning_rate = entry.get("learning_rate", default)
        if not isinstance(learning_rate, (int, float)):
            raise ValueError(f"{variant} needs a constant learning_rate in {conf} for {env_id}, got {learning_rate!r}")
        options["critic_learning_rate"] = float(f"{scale * learning_rate:.6g}")
    if "policy_kwargs" in options and "policy_kwargs" in entry:
        options["policy_kwargs"] = f"{{**{entry['policy_kwargs']}, **{options['policy_kwargs']}}}"  # rl-zoo3 evals it
    return options


def zoo_command(env_id: str, variant: str, seed: int, timesteps: int, args: argparse.Namespace, folder: pathlib.Path) -> list:
    options = variant_options(variant, env_id, conf_file(variant, args))
    base = base_algorithm(variant)
    command = [
        sys.executable, "-m", "sb3_pevfa.train",
        "--algo", base if options is None else f"{base}_pevfa",
        "--env", env_id, "--seed", str(seed), "-n", str(timesteps), "-conf", str(conf_file(variant, args)),
        "--eval-freq", str(args.eval_freq), "--eval-episodes", str(args.eval_episodes), "--n-eval-envs", "1",
        "--num-threads", "1", "-f", str(folder), "--log-interval", "-1",
    ]  # fmt: skip
    if options:
        command += ["--hyperparams", *(f"{key}:{value!r}" for key, value in options.items())]
    return command


def run(env_id: str, variant: str, seed: int, timesteps: int, args: argparse.Namespace) -> str:
    """One rl-zoo3 training; its evaluation curve becomes ``<out>/<env>_<variant>_seed<seed>.json``."""
    name = run_name(env_id, variant, seed)
    folder = args.out / "runs" / name
    shutil.rmtree(folder, ignore_errors=True)  # a half-finished earlier attempt
    command = zoo_command(env_id, variant, seed, timesteps, args, folder)
    conf = conf_file(variant, args)
    start = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    folder.mkdir(parents=True)
    with open(folder / "output.log", "w") as log:  # a file, not a pipe: wait4 below must not block on output
        process = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)  # this child's own CPU time, whatever else runs beside it
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        shutil.copy(folder / "output.log", args.out / f"{name}.err")
        return f"{name}: FAILED (see {name}.err)"
    evaluations = np.load(next(folder.rglob("evaluations.npz")))
    returns = evaluations["results"]
    result = {
        "variant": variant,
        "options": variant_options(variant, env_id, conf),
        "env": env_id,
        "seed": seed,
        "timesteps": timesteps,
        "wall_time_s": wall,
        "cpu_time_s": usage.ru_utime + usage.ru_stime,
        "command": " ".join(os.path.relpath(c) if c in (str(conf), str(folder)) else c for c in command[1:]),
        "curve": [
            {"timesteps": int(t), "mean_return": float(r.mean()), "std_return": float(r.std())}
            for t, r in zip(evaluations["timesteps"], returns)
        ],
        "episode_returns": returns.tolist(),
    }
    add_wall_clock(result, folder)
    (args.out / f"{name}.json").write_text(json.dumps(result, indent=1))
    return f"{name}: max {returns.mean(axis=1).max():.0f} ({wall:.0f} s)"


def add_wall_clock(result: dict, folder: pathlib.Path) -> None:
    """Each evaluation's wall-clock time since the start of its run (``curve[i]["wall_s"]``), read from the
    training env's Monitor file (episode ends: cumulative steps and their times), interpolated at the evaluation's
    step. Evaluation time is inside it, as it is inside the run's."""
    monitor = next(folder.rglob("*.monitor.csv"))
    episodes = np.loadtxt(monitor, delimiter=",", skiprows=2, ndmin=2)  # r, l, t
    steps, seconds = np.concatenate([[0], np.cumsum(episodes[:, 1])]), np.concatenate([[0], episodes[:, 2]])
    for point in result["curve"]:
        point["wall_s"] = float(np.interp(point["timesteps"], steps, seconds))


def cpu_seconds(run: dict, point: dict) -> float:
    """The training process's CPU seconds at evaluation ``point``: the run's CPU time prorated by its steps (only the
    whole run's is recorded; a run's CPU per step is about constant, the history's cost being bounded from its first
    5k steps)."""
    return run["cpu_time_s"] * (point["timesteps"] / run["timesteps"])  # exactly the run's at its last step
