"""One training of a grid point, as a trial runs it: its evaluation curve with the training's CPU and wall-clock time
(evaluations and checkpoints apart), its checkpoints, and what the trial stores (the curve, the times, the resolved
arguments and the provenance). Protocol zoo trains through rl-zoo3 instead (``zoo.run``, a process of its own)."""

import argparse
import contextlib
import functools
import inspect
import json
import os
import pathlib
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import optuna
import stable_baselines3 as sb3
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.diagnostics.local_generalization import LocalGeneralizationCallback, ResumableDiagnostic
from sb3_pevfa.diagnostics.q_local_generalization import QLocalGeneralizationCallback

from . import zoo
from .definitions import ENV_MAKERS, LOCAL_GENERALIZATION, OFF_POLICY, ROOT, STOCHASTIC_EVALUATION, VARIANTS, Campaign
from .training_logs import parse_log

#: Env steps between two checkpoints of a running trial
CHECKPOINT_FREQ = 100_000
#: The evaluation env of seed s is seeded with s + this (the training env with s)
EVAL_SEED_OFFSET = 10_000


class Stop:
    """A stop asked of a worker (SIGINT, SIGTERM, the deadline). A training that keeps checkpoints takes it at its next
    iteration boundary, after a checkpoint saved there (``CurveCallback``), so that the next run goes on from the
    moment it stopped; anything else stops at once."""

    def __init__(self) -> None:
        self.asked = False
        self.deferrable = False

    def ask(self) -> bool:
        """The stop asked; whether a training takes it at its next iteration boundary (else the caller stops now)."""
        self.asked = True
        return self.deferrable

    @contextlib.contextmanager
    def deferred(self, deferrable: bool = True) -> Iterator[None]:
        """Inside, where ``deferrable``, a stop is only recorded: a training takes it at its next iteration boundary,
        a worker after the trial it runs is stored."""
        before, self.deferrable = self.deferrable, deferrable or self.deferrable
        try:
            yield
        finally:
            self.deferrable = before


#: This process's stop (a worker's signal handlers ask it)
STOP = Stop()


class CurveCallback(BaseCallback):
    """Evaluates every ``eval_freq`` env steps over ``n_eval_episodes`` episodes (SB3's ``evaluate_policy``;
    deterministic actions unless ``deterministic=False``), records the training's CPU and wall-clock seconds so far
    (evaluations and checkpoints apart), and reports the mean return to the Optuna trial, with a heartbeat. With a
    ``checkpoint`` folder, it saves the model, its history, the ``diagnostic``'s state (if any) and its own state
    there at the first iteration boundary after every ``checkpoint_freq`` env steps, and at the first one after a
    ``STOP`` is asked, then raises ``KeyboardInterrupt``; ``state`` is such a saved state, to go on from."""

    def __init__(
        self,
        eval_env: VecEnv,
        trial: optuna.Trial | None,
        eval_freq: int,
        n_eval_episodes: int,
        checkpoint: pathlib.Path | None = None,
        checkpoint_freq: int = 0,
        state: dict[str, Any] | None = None,
        deterministic: bool = True,
        diagnostic: ResumableDiagnostic | None = None,
    ):
        super().__init__()
        self.deterministic, self.diagnostic = deterministic, diagnostic
        self.eval_env, self.trial, self.eval_freq, self.n_eval_episodes = eval_env, trial, eval_freq, n_eval_episodes
        self.checkpoint, self.checkpoint_freq = checkpoint, checkpoint_freq
        state = state or {}
        self.curve: dict[str, list[float]] = state.get("curve", {k: [] for k in ("steps", "mean", "std", "cpu_s", "wall_s")})
        self.before = {key: state.get(key, 0.0) for key in ("cpu", "wall", "eval_cpu", "eval_wall")}
        self.segment_eval_cpu = self.segment_eval_wall = 0.0
        self.start_cpu, self.start_wall = time.process_time(), time.perf_counter()
        self.saved_at = state.get("timesteps", 0)
        self.next_checkpoint = (self.saved_at // checkpoint_freq + 1) * checkpoint_freq if checkpoint_freq else 0

    @property
    def eval_cpu(self) -> float:
        return self.before["eval_cpu"] + self.segment_eval_cpu

    @property
    def eval_wall(self) -> float:
        return self.before["eval_wall"] + self.segment_eval_wall

    def training_time(self) -> tuple[float, float]:
        """CPU and wall-clock seconds of training so far, over every segment of the run."""
        cpu = self.before["cpu"] + time.process_time() - self.start_cpu - self.segment_eval_cpu
        return cpu, self.before["wall"] + time.perf_counter() - self.start_wall - self.segment_eval_wall

    @contextlib.contextmanager
    def apart(self) -> Iterator[None]:
        """Time spent inside is not training time."""
        cpu, wall = time.process_time(), time.perf_counter()
        yield
        self.segment_eval_cpu += time.process_time() - cpu
        self.segment_eval_wall += time.perf_counter() - wall

    def _on_step(self) -> bool:
        if self.num_timesteps % self.eval_freq:
            return True
        train_cpu, train_wall = self.training_time()
        with self.apart():
            returns, _ = evaluate_policy(
                self.model, self.eval_env, self.n_eval_episodes, deterministic=self.deterministic, return_episode_rewards=True
            )
        returns = np.asarray(returns, dtype=float)
        point = (self.num_timesteps, float(returns.mean()), float(returns.std()), train_cpu, train_wall)
        for key, value in zip(self.curve, point):
            self.curve[key].append(value)
        if self.trial is not None:
            self.trial.report(point[1], self.num_timesteps)
            self.trial.set_user_attr("heartbeat", time.time())
            self.trial.set_user_attr("progress", {"steps": self.num_timesteps, "cpu_s": train_cpu, "wall_s": train_wall})
        return True

    def _on_rollout_start(self) -> None:
        due = bool(self.checkpoint_freq) and self.num_timesteps >= self.next_checkpoint
        if self.checkpoint is not None and (due or STOP.asked) and self.num_timesteps > self.saved_at:
            with self.apart():
                save_checkpoint(self.checkpoint, self.model, self.state(), self.diagnostic)
            self.saved_at = self.num_timesteps
            if self.trial is not None:  # a later trial of the grid point on another machine says what it misses
                self.trial.set_user_attr("checkpoint", {"steps": self.num_timesteps, "host": socket.gethostname()})
            if self.checkpoint_freq:
                self.next_checkpoint = (self.num_timesteps // self.checkpoint_freq + 1) * self.checkpoint_freq
        if STOP.asked and STOP.deferrable:
            raise KeyboardInterrupt

    def state(self) -> dict[str, Any]:
        cpu, wall = self.training_time()
        return {"timesteps": self.num_timesteps, "curve": self.curve, "cpu": cpu, "wall": wall,
                "eval_cpu": self.eval_cpu, "eval_wall": self.eval_wall}  # fmt: skip


#: The files of a checkpoint saved before their names held its env steps
UNNAMED_FILES = {"model": "model.zip", "history": "history.npz", "replay_buffer": "replay_buffer.pkl",
                 "diagnostic": "diagnostic.pt"}  # fmt: skip


def save_checkpoint(
    folder: pathlib.Path, model: PPO, state: dict[str, Any], diagnostic: ResumableDiagnostic | None = None
) -> None:
    """The model, its history, its replay buffer, the diagnostic's state and ``state``, as one set: each file named by
    the env steps, ``state.json`` written last names them (a kill at any moment leaves the previous set or the new
    one whole), then the previous set removed."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {}

    def written(key: str, suffix: str, write: Callable[[pathlib.Path], None]) -> None:
        files[key] = f"{key}-{model.num_timesteps}{suffix}"
        write(folder / f"{key}.tmp{suffix}")
        os.replace(folder / f"{key}.tmp{suffix}", folder / files[key])

    if diagnostic is not None:
        written("diagnostic", ".pt", lambda path: th.save({**diagnostic.state_dict(), "timesteps": model.num_timesteps}, path))
    written("model", ".zip", model.save)
    if hasattr(model, "save_history"):  # a PeVFA: its policy history or snapshots
        written("history", ".npz", model.save_history)
        state = {**state, "n_policies": model.history.n_policies}
    if isinstance(model, OffPolicyAlgorithm):  # its replay buffer, to go on from
        written("replay_buffer", ".pkl", model.save_replay_buffer)
    (folder / "state.tmp.json").write_text(json.dumps({**state, "files": files}))
    os.replace(folder / "state.tmp.json", folder / "state.json")
    for path in folder.iterdir():
        if path.name not in (*files.values(), "state.json"):
            path.unlink()


def checkpoint_file(folder: pathlib.Path, state: dict[str, Any], key: str) -> pathlib.Path:
    """The file ``key`` (model, history, replay_buffer, diagnostic) of the checkpoint whose state is ``state``."""
    return folder / state.get("files", UNNAMED_FILES)[key]


def load_checkpoint(folder: pathlib.Path | None, protocol: str, variant: str, env) -> tuple[PPO, dict[str, Any]] | None:
    """The model and state saved in ``folder``, or None where there is none or its files do not belong together (or
    one is missing). A diagnostic variant's state holds its diagnostic's under ``"diagnostic"``."""
    if folder is None or not (folder / "state.json").exists():
        return None
    state = json.loads((folder / "state.json").read_text())
    needed = ["model"] + ["history"] * (VARIANTS[protocol][variant] is not None)
    needed += ["replay_buffer"] * (protocol in OFF_POLICY) + ["diagnostic"] * (variant in LOCAL_GENERALIZATION)
    if not all(checkpoint_file(folder, state, key).exists() for key in needed):
        return None
    if variant in LOCAL_GENERALIZATION:
        state["diagnostic"] = th.load(checkpoint_file(folder, state, "diagnostic"))
        if state["diagnostic"].pop("timesteps") != state["timesteps"]:
            return None
    model = algorithm_of(protocol, variant).load(checkpoint_file(folder, state, "model"), env=env)
    if hasattr(model, "load_history"):
        model.load_history(checkpoint_file(folder, state, "history"))
        if model.history.n_policies != state["n_policies"]:
            return None
    if isinstance(model, OffPolicyAlgorithm):
        model.load_replay_buffer(checkpoint_file(folder, state, "replay_buffer"))
    return (model, state) if model.num_timesteps == state["timesteps"] else None


def remove_checkpoint(folder: pathlib.Path) -> None:
    """The folder removed, its ``state.json`` first (a kill leaves no checkpoint to go on from, or a whole one)."""
    with contextlib.suppress(FileNotFoundError):
        (folder / "state.json").unlink()
    shutil.rmtree(folder, ignore_errors=True)


def algorithm_of(protocol: str, variant: str) -> type:
    """The class of a grid point: SB3's algorithm for a variant of None, else its PeVFA class (PPO and PPOPeVFA, or
    an off-policy protocol's, ``OFF_POLICY``)."""
    base, pevfa, _ = OFF_POLICY.get(protocol, (PPO, PPOPeVFA, {}))
    return base if VARIANTS[protocol][variant] is None else pevfa


def make_model(protocol: str, variant: str, env, seed: int) -> PPO:
    """The model of one grid point (``VARIANTS``, with an off-policy protocol's shared arguments)."""
    shared = OFF_POLICY[protocol][2] if protocol in OFF_POLICY else {}
    return algorithm_of(protocol, variant)("MlpPolicy", env, seed=seed, **shared, **(VARIANTS[protocol][variant] or {}))


def train(campaign: Campaign, task: str, variant: str, seed: int, trial: optuna.Trial | None = None,
          checkpoint: pathlib.Path | None = None, checkpoint_freq: int = CHECKPOINT_FREQ,
          started: Callable[[int], None] | None = None) -> dict[str, Any]:  # fmt: skip
    """Train one grid point with evaluations; returns what the trial stores. With a ``checkpoint`` folder, the run
    goes on from the checkpoint there (if any; its env starts a new episode; ``started`` is told its env steps, 0 for
    none) and saves one every ``checkpoint_freq`` env steps; the folder is removed when the run is complete. A run
    with a diagnostic (``LOCAL_GENERALIZATION``) goes on with its conventional critic and its series (what was not
    scored when the checkpoint was taken is not)."""
    if campaign.protocol == "zoo":
        return train_through_the_zoo(campaign, task, variant, seed, trial)
    th.set_num_threads(1)
    make_env = ENV_MAKERS.get(campaign.protocol, functools.partial(make_vec_env, n_envs=1))
    env = make_env(task, seed=seed)
    eval_env = make_env(task, seed=seed + EVAL_SEED_OFFSET)
    with warnings.catch_warnings():  # the paper's 2000-step rollouts in minibatches of 128 (the last one of 80)
        warnings.filterwarnings("ignore", message="You have specified a mini-batch size")
        resumed = load_checkpoint(checkpoint, campaign.protocol, variant, env)
        model, state = resumed or (make_model(campaign.protocol, variant, env, seed), {})
    if started is not None:
        started(state.get("timesteps", 0))
    deterministic = campaign.protocol not in STOCHASTIC_EVALUATION
    diagnostic = None
    if variant in LOCAL_GENERALIZATION:
        kind = QLocalGeneralizationCallback if campaign.protocol in OFF_POLICY else LocalGeneralizationCallback
        diagnostic = kind(**LOCAL_GENERALIZATION[variant])
        if "diagnostic" in state:
            diagnostic.load_state_dict(state.pop("diagnostic"))
    callback = CurveCallback(eval_env, trial, campaign.eval_freq, campaign.eval_episodes, checkpoint, checkpoint_freq,
                             state, deterministic, diagnostic)  # fmt: skip
    # the diagnostic's hooks first: at an iteration's start it logs the last one before the checkpoint is saved
    callbacks = [callback] if diagnostic is None else [diagnostic, callback]
    with STOP.deferred(checkpoint is not None):  # a stop: a checkpoint at the next iteration boundary, then stopped
        model.learn(campaign.timesteps - model.num_timesteps, callback=callbacks, reset_num_timesteps=resumed is None)
    cpu, wall = callback.training_time()
    curve = callback.curve
    if checkpoint is not None:
        remove_checkpoint(checkpoint)
        if trial is not None:  # none left to go on from
            trial.set_user_attr("checkpoint", None)
    env.close()
    eval_env.close()
    return {
        "curve": curve,
        "max_average_return": max(curve["mean"]),
        "final_return": curve["mean"][-1],
        "timesteps": int(model.num_timesteps),
        "cpu_seconds": cpu,
        "wall_seconds": wall,
        "eval_cpu_seconds": callback.eval_cpu,
        "eval_wall_seconds": callback.eval_wall,
        "steps_per_cpu_second": model.num_timesteps / cpu,
        "steps_per_wall_second": model.num_timesteps / wall,
        "arguments": resolved_arguments(model),
        "resumed_from": state.get("timesteps", 0),
        **({"local_generalization": series(diagnostic.results)} if diagnostic is not None else {}),
        **provenance(),
    }


def train_through_the_zoo(
    campaign: Campaign, task: str, variant: str, seed: int, trial: optuna.Trial | None = None
) -> dict[str, Any]:
    """One training through rl-zoo3's entry point (``zoo.run``: its EvalCallback, deterministic episodes), as a
    process of its own whose CPU time includes its evaluations; each evaluation's CPU time is the run's, prorated by
    steps, and its wall-clock time comes from the Monitor file."""
    with tempfile.TemporaryDirectory() as folder:
        args = argparse.Namespace(conf=campaign.conf_of(variant), eval_freq=campaign.eval_freq,
                                  eval_episodes=campaign.eval_episodes, out=pathlib.Path(folder))  # fmt: skip
        line = zoo.run(task, variant, seed, campaign.timesteps, args)
        name = zoo.run_name(task, variant, seed)
        if not (args.out / f"{name}.json").exists():
            raise RuntimeError(f"{line}\n{(args.out / f'{name}.err').read_text()[-3000:]}")
        run = json.loads((args.out / f"{name}.json").read_text())
        log = parse_log((args.out / "runs" / name / "output.log").read_text(errors="replace"))
    points = run["curve"]
    curve = {"steps": [p["timesteps"] for p in points], "mean": [p["mean_return"] for p in points],
             "std": [p["std_return"] for p in points], "cpu_s": [zoo.cpu_seconds(run, p) for p in points],
             "wall_s": [p["wall_s"] for p in points]}  # fmt: skip
    if trial is not None:
        for step, mean in zip(curve["steps"], curve["mean"]):
            trial.report(mean, step)
    return {
        "curve": curve,
        "max_average_return": max(curve["mean"]),
        "final_return": curve["mean"][-1],
        "timesteps": run["timesteps"],
        "cpu_seconds": run["cpu_time_s"],
        "wall_seconds": run["wall_time_s"],
        "eval_cpu_seconds": 0.0,  # inside the run's own
        "eval_wall_seconds": 0.0,
        "steps_per_cpu_second": run["timesteps"] / run["cpu_time_s"],
        "steps_per_wall_second": run["timesteps"] / run["wall_time_s"],
        "arguments": {"command": run["command"], "options": repr(run["options"])},
        "training_log": log,  # SB3's training tables, compactly (training_logs.parse_log)
        "zoo_run": run,  # zoo.run's record of the run
        **provenance(),
    }


def series(results: list[dict[str, float]]) -> dict[str, list[float]]:
    """A diagnostic's results (one entry per iteration or window) as a series per key."""
    return {key: [float(entry[key]) for entry in results] for key in sorted(results[0])} if results else {}


def resolved_arguments(model: PPO) -> dict[str, str]:
    """Every constructor argument as the model holds it (class defaults included), as text: those of the model's
    constructor, and where it passes ``**kwargs`` on (the off-policy PeVFA mixin), those of the next one's."""
    names: set[str] = set()
    for cls in type(model).__mro__:
        if "__init__" in vars(cls):
            parameters = inspect.signature(cls.__init__).parameters
            names |= set(parameters)
            if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
                break
    values = {name: getattr(model, name) for name in names if name not in ("self", "policy", "env") and hasattr(model, name)}
    return {name: repr(value) for name, value in values.items()}


@functools.cache
def provenance() -> dict[str, Any]:
    """The package's commit when this process started (``+dirty`` with uncommitted changes), the library versions and
    the machine."""

    def git(*args: str) -> str:
        result = subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT)
        return result.stdout.strip() if result.returncode == 0 else "unknown"

    commit = git("rev-parse", "--short", "HEAD")
    if git("status", "--porcelain", "--untracked-files=no", "--", "sb3_pevfa", "benchmarks/campaign.py", "benchmarks/engine"):
        commit += "+dirty"
    versions = {"torch": th.__version__, "stable_baselines3": sb3.__version__, "gymnasium": gym.__version__,
                "mujoco": mujoco.__version__, "optuna": optuna.__version__, "python": sys.version.split()[0]}  # fmt: skip
    return {"commit": commit, "versions": versions, "machine": f"{socket.gethostname()} ({os.cpu_count()} CPUs)"}
