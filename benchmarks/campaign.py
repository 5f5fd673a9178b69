"""Learning campaigns as resumable Optuna studies: one study per campaign, a grid of task x variant x seed
(``GridSampler``; each worker enqueues a grid point that no trial holds, drawn at random), one training per trial.

Every trial stores, as user attributes, its evaluation curve (env steps, mean and std of the evaluation returns, the
training's CPU and wall-clock seconds at each evaluation), its CPU and wall-clock seconds (evaluation apart), env steps
per CPU-second, the package's commit and the versions of torch, SB3, gymnasium and mujoco. The report
(``campaign_report.py``) reads the storage alone.

Storage: a JournalStorage file per campaign, ``benchmarks/campaigns/<campaign>.journal``, committed with the
repository, so a campaign resumes from git on any machine; ``--storage postgresql://...`` (any SQLAlchemy URL) lets
any number of machines pull trials from one database, with Optuna's heartbeat failing the trials of dead workers and
``RetryHeartbeatStaleTrialCallback`` enqueueing them again. On a journal file, ``run`` first fails the RUNNING trials whose
worker is gone (its process on this machine, or no heartbeat for ``--stale-after`` seconds) and enqueues each again;
a trial stopped by SIGINT/SIGTERM is enqueued again too, and goes on from its last checkpoint where the machine kept
it. A grid point whose worker died more than ``MAX_RETRY`` times (stops do not count) and a trial whose training
raised stay failed (the report lists both). A worker out of grid points waits while others run the last ones and
takes over any whose worker dies. A task, variant and seed counts once in the report, however often it ran.

    # the paper's Table 1, part (a): 6 tasks x {paper PPO, PPO-PeVFA OPR-E2E} x seeds 0-4, 1M steps (days of CPU)
    nohup python benchmarks/campaign.py run --campaign table1 --workers 2 > campaign.log 2>&1 &
    python benchmarks/campaign.py status --campaign table1
    # many machines: one database, the same command on each
    python benchmarks/campaign.py run --campaign table1 --workers 16 --storage postgresql://user:pw@host/db
    # a campaign of your own (its definition is stored in the study on creation)
    python benchmarks/campaign.py run --campaign mine --protocol sb3 --tasks Hopper-v5 --variants ppo opr \
        --seeds 0 1 --timesteps 300000
"""

import argparse
import contextlib
import dataclasses
import functools
import hashlib
import inspect
import json
import os
import pathlib
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import learning
import mujoco
import numpy as np
import optuna
import sqlalchemy
import stable_baselines3 as sb3
import torch as th
import training_logs
from optuna.storages import JournalStorage, RDBStorage
from optuna.storages.journal import JournalFileBackend
from optuna.trial import FrozenTrial, TrialState
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import KVWriter, Logger
from stable_baselines3.common.vec_env import VecEnv

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.diagnostics.local_generalization import LocalGeneralizationCallback
from sb3_pevfa.protocols import authors_protocol, make_authors_env, paper_protocol

try:  # Optuna >= 4.9's names of the callback that enqueues a stale trial again, and of RDBStorage's argument
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    RETRY_ARGUMENT = "heartbeat_stale_trial_callback"
except ImportError:  # pragma: no cover
    from optuna.storages import RetryFailedTrialCallback as RetryHeartbeatStaleTrialCallback

    RETRY_ARGUMENT = "failed_trial_callback"

warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)

ROOT = pathlib.Path(__file__).resolve().parents[1]
CAMPAIGN_DIR = ROOT / "benchmarks" / "campaigns"
#: The six tasks of the paper's Table 1 in today's versions (the paper: -v1 tasks of gym 0.9.1, LunarLander-v2)
TABLE1_TASKS = (
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "InvertedDoublePendulum-v5",
    "LunarLanderContinuous-v3",
)
#: A retried trial is enqueued again at most this many times
MAX_RETRY = 3
#: Where a running trial keeps its checkpoint: outside the work tree, which a new session may lay anew
CHECKPOINT_DIR = pathlib.Path(os.environ.get("SB3_PEVFA_CHECKPOINTS", pathlib.Path.home() / ".cache" / "sb3-pevfa"))
#: Env steps between two checkpoints of a running trial
CHECKPOINT_FREQ = 100_000
#: The evaluation env of seed s is seeded with s + this (the training env with s)
EVAL_SEED_OFFSET = 10_000
#: Today's cheaper schedule of historical updates (PPOPeVFA's defaults): 256 samples of 8 policies per 40 steps
DEFAULT_SCHEDULE = dict(history_batch_size=256, history_batch_policies=8, history_train_freq=40, rollout_encoder_gradient=None)

#: protocol -> variant -> PPOPeVFA constructor arguments (None: SB3's PPO with its defaults)
VARIANTS: dict[str, dict[str, dict[str, Any] | None]] = {
    "paper": {
        "ppo": paper_protocol("ppo"),
        "opr-e2e": paper_protocol("ppo_pevfa"),
        "opr-e2e-default-schedule": paper_protocol("ppo_pevfa", **DEFAULT_SCHEDULE),
        "random": paper_protocol("ppo_pevfa", representation="random"),
        "opr-cl": paper_protocol("ppo_pevfa", representation_objectives=("cl",)),
        "spr-e2e": paper_protocol("ppo_pevfa", representation="spr"),
        "fingerprint-e2e": paper_protocol("ppo_pevfa", representation="fingerprint"),
        # OPR-E2E with the local-generalization diagnostic (paper Fig. 3b / 8): a conventional critic of the paper's
        # PPO (2x128 ReLU, its learning rate) trained beside it; the diagnostic's critic counts in its CPU time
        "opr-e2e+local-generalization": paper_protocol("ppo_pevfa"),
    },
    # the authors' code's training loop (sb3_pevfa.protocols.authors_protocol), on make_authors_env's envs
    "authors": {
        "ppo": authors_protocol("ppo"),
        "opr-e2e": authors_protocol("ppo_pevfa"),
        # the paper's control: a fixed random code per policy in place of a learned representation (Ran PR)
        "random": authors_protocol("ppo_pevfa", representation="random"),
    },
    # learning.py's variants, trained through rl-zoo3's entry point on one hyperparameter file (the campaign's conf)
    "zoo": dict(learning.VARIANTS),
    "sb3": {
        "ppo": None,
        "opr": {},
        "spr": dict(representation="spr"),
        "fingerprint": dict(representation="fingerprint"),
    },
}


#: Protocols whose evaluation samples actions (the authors' code); the others evaluate the deterministic policy
STOCHASTIC_EVALUATION = {"authors"}
#: Protocols whose envs are not Gymnasium's as made (task, seed) -> VecEnv
ENV_MAKERS = {"authors": make_authors_env}

#: Variants that run a diagnostic beside their training: variant -> the callback's constructor arguments
LOCAL_GENERALIZATION = {"opr-e2e+local-generalization": dict(net_arch=(128, 128))}


@dataclasses.dataclass(frozen=True)
class Campaign:
    """A grid of trainings: every task x variant x seed, ``timesteps`` each, evaluated every ``eval_freq`` steps
    over ``eval_episodes`` episodes (deterministic, except in the protocols of ``STOCHASTIC_EVALUATION``)."""

    protocol: str
    tasks: tuple[str, ...]
    variants: tuple[str, ...]
    seeds: tuple[int, ...]
    timesteps: int
    eval_freq: int = 20_000
    eval_episodes: int = 10
    #: protocol "zoo": the rl-zoo3 hyperparameter file of every variant (relative to the repository); None: learning.py's
    #: default file of each variant's base algorithm (``learning.CONFS``)
    conf: str | None = None

    def __post_init__(self) -> None:
        if self.protocol not in VARIANTS:
            raise ValueError(f"Unknown protocol {self.protocol!r}, valid choices: {sorted(VARIANTS)}")
        unknown = sorted(set(self.variants) - set(VARIANTS[self.protocol]))
        if unknown:
            raise ValueError(
                f"Unknown variants {unknown} of protocol {self.protocol!r}, valid: {sorted(VARIANTS[self.protocol])}"
            )
        if not (self.tasks and self.variants and self.seeds):
            raise ValueError("A campaign needs at least one task, one variant and one seed")
        if self.protocol != "zoo" and self.conf is not None:
            raise ValueError("only protocol 'zoo' takes a conf (an rl-zoo3 hyperparameter file)")
        if self.conf is not None and not (ROOT / self.conf).is_file():
            raise ValueError(f"No hyperparameter file {self.conf!r} in the repository")
        if min(self.timesteps, self.eval_freq, self.eval_episodes) <= 0 or self.eval_freq > self.timesteps:
            raise ValueError("timesteps, eval_freq and eval_episodes must be positive, eval_freq at most timesteps")

    @property
    def search_space(self) -> dict[str, list]:
        return {"task": list(self.tasks), "variant": list(self.variants), "seed": list(self.seeds)}

    @property
    def grid(self) -> list[tuple[str, str, int]]:
        return [(t, v, s) for t in self.tasks for v in self.variants for s in self.seeds]

    def definition(self) -> dict[str, Any]:
        """What the study stores: the grid and, per variant, its constructor arguments as text."""
        settings = {variant: repr(VARIANTS[self.protocol][variant]) for variant in self.variants}
        definition = {**dataclasses.asdict(self), "tasks": list(self.tasks), "variants": list(self.variants),
                      "seeds": list(self.seeds), "settings": settings}  # fmt: skip
        if self.conf is None:
            del definition["conf"]  # as campaigns stored it before the zoo protocol
        for variant in self.variants if self.protocol == "zoo" else ():  # the files' contents too
            settings[f"{variant} conf"] = hashlib.sha1(self.conf_of(variant).read_bytes()).hexdigest()
        return definition

    def conf_of(self, variant: str) -> pathlib.Path:
        """Protocol zoo: the hyperparameter file ``variant`` trains with."""
        return ROOT / self.conf if self.conf else learning.CONFS[learning.base_algorithm(variant)]

    def checkpoint_folder(self, name: str) -> pathlib.Path:
        """Where the running trials of this campaign (under this study name) keep their checkpoints."""
        digest = hashlib.sha1(json.dumps(self.definition(), sort_keys=True).encode()).hexdigest()[:10]
        return CHECKPOINT_DIR / f"{name}-{digest}"

    @classmethod
    def from_definition(cls, definition: dict[str, Any]) -> "Campaign":
        fields = {f.name for f in dataclasses.fields(cls)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in definition.items() if k in fields}
        return cls(**values)


#: The campaigns of this repository, in the order the Table-1 reproduction runs them
CAMPAIGNS: dict[str, Campaign] = {
    # (a) the paper's PPO vs PPO-PeVFA OPR-E2E with the paper's schedule of historical updates
    "table1": Campaign("paper", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5)), 1_000_000),
    # (b) PPO-PeVFA with today's default schedule of historical updates, in the same protocol
    "table1-default-schedule": Campaign("paper", TABLE1_TASKS, ("opr-e2e-default-schedule",), tuple(range(5)), 1_000_000),
    # (c) the other representations and objectives, then five more seeds
    "table1-variants": Campaign("paper", TABLE1_TASKS, ("random", "opr-cl", "spr-e2e"), tuple(range(5)), 1_000_000),
    "table1-seeds5-9": Campaign("paper", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5, 10)), 1_000_000),
    # the learned probe-state fingerprint in the same protocol, once the Table-1 grid is done
    "table1-fingerprint": Campaign("paper", TABLE1_TASKS, ("fingerprint-e2e",), tuple(range(5)), 1_000_000),
    # Table 1 as the authors' code trains (2M steps on every task, Ant too), ahead of the grids above that still run
    "table1-authors": Campaign("authors", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5)), 2_000_000),
    # then the paper's Ran PR control in the same protocol: a fixed random code per policy in place of OPR
    "table1-authors-random": Campaign("authors", TABLE1_TASKS, ("random",), tuple(range(5)), 2_000_000),
    # the pilot of table1-authors: one task and seed, to check that its PPO lands near the paper's before the grid runs
    "table1-authors-pilot": Campaign("authors", ("Hopper-v5",), ("ppo", "opr-e2e"), (0,), 2_000_000),
    # the local-generalization diagnostic (paper Fig. 3b / 8) where grid (a)'s direction differs from the paper's
    "table1-local-generalization": Campaign(
        "paper", ("Walker2d-v5", "Hopper-v5"), ("opr-e2e+local-generalization",), tuple(range(3)), 1_000_000
    ),
    # the representations at SB3's PPO defaults through rl-zoo3 (as docs/results-sb3-defaults.md), 300k steps
    "representations-300k": Campaign(
        "zoo",
        ("Hopper-v5", "Walker2d-v5"),
        ("ppo", "pevfa-opr", "pevfa-spr", "pevfa-fingerprint"),
        tuple(range(5)),
        300_000,
        conf="benchmarks/hyperparams/learning.yml",
    ),
}


# ---------------------------------------------------------------------------------------------- one training
class CurveCallback(BaseCallback):
    """Evaluates every ``eval_freq`` env steps over ``n_eval_episodes`` episodes (SB3's ``evaluate_policy``;
    deterministic actions unless ``deterministic=False``), records the training's CPU and wall-clock seconds so far
    (evaluations and checkpoints apart), and reports the mean return to the Optuna trial, with a heartbeat. With a
    ``checkpoint`` folder, it saves the model, its history and its own state there at the first iteration boundary
    after every ``checkpoint_freq`` env steps; ``state`` is such a saved state, to go on from."""

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
    ):
        super().__init__()
        self.deterministic = deterministic
        self.eval_env, self.trial, self.eval_freq, self.n_eval_episodes = eval_env, trial, eval_freq, n_eval_episodes
        self.checkpoint, self.checkpoint_freq = checkpoint, checkpoint_freq
        state = state or {}
        self.curve: dict[str, list[float]] = state.get("curve", {k: [] for k in ("steps", "mean", "std", "cpu_s", "wall_s")})
        self.before = {key: state.get(key, 0.0) for key in ("cpu", "wall", "eval_cpu", "eval_wall")}
        self.segment_eval_cpu = self.segment_eval_wall = 0.0
        self.start_cpu, self.start_wall = time.process_time(), time.perf_counter()
        self.next_checkpoint = (state.get("timesteps", 0) // checkpoint_freq + 1) * checkpoint_freq if checkpoint_freq else 0

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
        if self.checkpoint is None or not self.checkpoint_freq or self.num_timesteps < self.next_checkpoint:
            return
        with self.apart():
            save_checkpoint(self.checkpoint, self.model, self.state())
        self.next_checkpoint = (self.num_timesteps // self.checkpoint_freq + 1) * self.checkpoint_freq

    def state(self) -> dict[str, Any]:
        cpu, wall = self.training_time()
        return {"timesteps": self.num_timesteps, "curve": self.curve, "cpu": cpu, "wall": wall,
                "eval_cpu": self.eval_cpu, "eval_wall": self.eval_wall}  # fmt: skip


def save_checkpoint(folder: pathlib.Path, model: PPO, state: dict[str, Any]) -> None:
    """The model, its history and ``state``, each file replaced whole (a kill leaves the previous one or the new one;
    the state, written last, names the steps the model must have)."""
    folder.mkdir(parents=True, exist_ok=True)
    model.save(folder / "model.tmp.zip")
    os.replace(folder / "model.tmp.zip", folder / "model.zip")
    if isinstance(model, PPOPeVFA):
        model.save_history(folder / "history.tmp.npz")
        os.replace(folder / "history.tmp.npz", folder / "history.npz")
        state = {**state, "n_policies": model.history.n_policies}
    (folder / "state.tmp.json").write_text(json.dumps(state))
    os.replace(folder / "state.tmp.json", folder / "state.json")


def load_checkpoint(folder: pathlib.Path | None, protocol: str, variant: str, env) -> tuple[PPO, dict[str, Any]] | None:
    """The model and state saved in ``folder``, or None where there is none or its files do not belong together."""
    if folder is None or not (folder / "state.json").exists():
        return None
    state = json.loads((folder / "state.json").read_text())
    algorithm = PPO if VARIANTS[protocol][variant] is None else PPOPeVFA
    model = algorithm.load(folder / "model.zip", env=env)
    if isinstance(model, PPOPeVFA):
        model.load_history(folder / "history.npz")
        if model.history.n_policies != state["n_policies"]:
            return None
    return (model, state) if model.num_timesteps == state["timesteps"] else None


def make_model(protocol: str, variant: str, env, seed: int) -> PPO:
    """The model of one grid point (``VARIANTS``)."""
    arguments = VARIANTS[protocol][variant]
    if arguments is None:
        return PPO("MlpPolicy", env, seed=seed)
    return PPOPeVFA("MlpPolicy", env, seed=seed, **arguments)


def train(campaign: Campaign, task: str, variant: str, seed: int, trial: optuna.Trial | None = None,
          checkpoint: pathlib.Path | None = None, checkpoint_freq: int = CHECKPOINT_FREQ) -> dict[str, Any]:  # fmt: skip
    """Train one grid point with evaluations; returns what the trial stores. With a ``checkpoint`` folder, the run
    goes on from the checkpoint there (if any; its env starts a new episode) and saves one every ``checkpoint_freq``
    env steps; the folder is removed when the run is complete."""
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
    deterministic = campaign.protocol not in STOCHASTIC_EVALUATION
    callback = CurveCallback(
        eval_env, trial, campaign.eval_freq, campaign.eval_episodes, checkpoint, checkpoint_freq, state, deterministic
    )
    callbacks: list[BaseCallback] = [callback]
    logged = MemoryOutput()
    if variant in LOCAL_GENERALIZATION:
        model.set_logger(Logger(folder=None, output_formats=[logged]))
        callbacks.append(LocalGeneralizationCallback(**LOCAL_GENERALIZATION[variant]))
    model.learn(campaign.timesteps - model.num_timesteps, callback=callbacks, reset_num_timesteps=resumed is None)
    cpu, wall = callback.training_time()
    curve = callback.curve
    if checkpoint is not None:
        shutil.rmtree(checkpoint, ignore_errors=True)
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
        **({"local_generalization": logged.series("pevfa/local_gen/")} if variant in LOCAL_GENERALIZATION else {}),
        **provenance(),
    }


def train_through_the_zoo(
    campaign: Campaign, task: str, variant: str, seed: int, trial: optuna.Trial | None = None
) -> dict[str, Any]:
    """One training through rl-zoo3's entry point (``learning.run``: its EvalCallback, deterministic episodes), as a
    process of its own whose CPU time includes its evaluations; each evaluation's CPU time is the run's, prorated by
    steps, and its wall-clock time comes from the Monitor file."""
    with tempfile.TemporaryDirectory() as folder:
        args = argparse.Namespace(conf=campaign.conf_of(variant), eval_freq=campaign.eval_freq,
                                  eval_episodes=campaign.eval_episodes, out=pathlib.Path(folder))  # fmt: skip
        line = learning.run(task, variant, seed, campaign.timesteps, args)
        name = learning.run_name(task, variant, seed)
        if not (args.out / f"{name}.json").exists():
            raise RuntimeError(f"{line}\n{(args.out / f'{name}.err').read_text()[-3000:]}")
        run = json.loads((args.out / f"{name}.json").read_text())
        log = training_logs.parse_log((args.out / "runs" / name / "output.log").read_text(errors="replace"))
    points = run["curve"]
    curve = {"steps": [p["timesteps"] for p in points], "mean": [p["mean_return"] for p in points],
             "std": [p["std_return"] for p in points], "cpu_s": [learning.cpu_seconds(run, p) for p in points],
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
        "training_log": log,  # SB3's training tables, compactly (benchmarks/training_logs.py)
        "zoo_run": run,  # learning.py's record of the run
        **provenance(),
    }


class MemoryOutput(KVWriter):
    """An SB3 logger output that keeps every dumped row in memory."""

    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        self.rows.append(dict(key_values))

    def series(self, prefix: str) -> dict[str, list[float]]:
        """The keys under ``prefix`` (prefix removed), over the rows that log them."""
        rows = [row for row in self.rows if any(key.startswith(prefix) for key in row)]
        keys = sorted({key for row in rows for key in row if key.startswith(prefix)})
        return {key[len(prefix) :]: [float(row.get(key, np.nan)) for row in rows] for key in keys}


def resolved_arguments(model: PPO) -> dict[str, str]:
    """Every constructor argument as the model holds it (class defaults included), as text."""
    names = inspect.signature(type(model).__init__).parameters
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
    if git("status", "--porcelain", "--untracked-files=no", "--", "sb3_pevfa", "benchmarks/campaign.py"):
        commit += "+dirty"
    versions = {"torch": th.__version__, "stable_baselines3": sb3.__version__, "gymnasium": gym.__version__,
                "mujoco": mujoco.__version__, "optuna": optuna.__version__, "python": sys.version.split()[0]}  # fmt: skip
    return {"commit": commit, "versions": versions, "machine": f"{socket.gethostname()} ({os.cpu_count()} CPUs)"}


# ---------------------------------------------------------------------------------------------- storage and study
def storage_of(campaign: str, storage: str | None = None) -> optuna.storages.BaseStorage:
    """``storage``: a database URL (``postgresql://...``, ``sqlite:///...``), a journal file's path, or None for
    ``benchmarks/campaigns/<campaign>.journal``."""
    if storage and "://" in storage:
        for attempt in range(3):  # machines starting together race to create the schema: the losers read it
            try:
                return RDBStorage(
                    storage,
                    heartbeat_interval=60,
                    grace_period=600,
                    **{RETRY_ARGUMENT: RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)},
                )
            except sqlalchemy.exc.IntegrityError:
                if attempt == 2:
                    raise
                time.sleep(1.0 + attempt)
    path = pathlib.Path(storage) if storage else CAMPAIGN_DIR / f"{campaign}.journal"
    path.parent.mkdir(parents=True, exist_ok=True)
    return JournalStorage(JournalFileBackend(str(path)))


def open_study(
    name: str, storage: optuna.storages.BaseStorage, given: Campaign | None = None
) -> tuple[optuna.Study, Campaign]:
    """The campaign's study, created with ``given`` (or this file's ``CAMPAIGNS[name]``) and its definition stored;
    a stored campaign is never redefined: a different definition is a ValueError."""
    expected = given or CAMPAIGNS.get(name)
    existing = {summary.study_name for summary in optuna.get_all_study_summaries(storage)}
    if name not in existing and expected is None:
        raise ValueError(f"Unknown campaign {name!r}: one of {sorted(CAMPAIGNS)}, or give --protocol, --tasks, "
                         "--variants, --seeds and --timesteps to define a new one")  # fmt: skip
    if name in existing:
        study = optuna.load_study(study_name=name, storage=storage)
    else:  # load_if_exists: another machine may create it at the same moment
        study = optuna.create_study(study_name=name, storage=storage, direction="maximize", load_if_exists=True)
    stored = study.user_attrs.get("campaign")
    if stored is None:  # new (or created by a machine that has not stored its definition yet: the same command's)
        if expected is None:
            raise ValueError(f"Campaign {name!r} has no definition yet: give it (--protocol, --tasks, ...)")
        study.set_user_attr("campaign", expected.definition())
        stored = expected.definition()
    campaign = Campaign.from_definition(stored)
    expected = expected or campaign  # a campaign of one's own: its variants' settings as this code defines them
    if expected.definition() != stored:
        raise ValueError(
            f"Campaign {name!r} was started as {stored}, and is now given as {expected.definition()}: a campaign's "
            "protocol never changes; start one under another name"
        )
    study.sampler = optuna.samplers.GridSampler(campaign.search_space)  # the grid; workers enqueue its points (draw)
    return study, campaign


def grid_point(trial: FrozenTrial) -> tuple[str, str, int] | None:
    params = trial.params or trial.system_attrs.get("fixed_params", {})
    return (params["task"], params["variant"], params["seed"]) if {"task", "variant", "seed"} <= set(params) else None


def grid_states(study: optuna.Study, campaign: Campaign) -> dict[tuple[str, str, int], list[FrozenTrial]]:
    """Every grid point's trials, in order."""
    states: dict[tuple[str, str, int], list[FrozenTrial]] = {point: [] for point in campaign.grid}
    for trial in study.get_trials(deepcopy=False):
        point = grid_point(trial)
        if point in states:
            states[point].append(trial)
    return states


def _interrupted(trial: FrozenTrial) -> bool:
    return trial.state == TrialState.FAIL and bool(trial.user_attrs.get("interrupted"))


def _alive(worker: dict[str, Any], stale_after: float, heartbeat: float | None) -> bool:
    """Whether the worker of a RUNNING trial still runs: its process on this machine, else a recent heartbeat."""
    if worker.get("host") == socket.gethostname() and worker.get("boot_id") == _boot_id():
        try:
            cmdline = pathlib.Path(f"/proc/{worker['pid']}/cmdline").read_bytes()
        except OSError:
            return False
        return b"campaign.py\x00work" in cmdline  # that process, not another one under a reused pid
    return heartbeat is not None and time.time() - heartbeat < stale_after


def _boot_id() -> str:
    try:
        return pathlib.Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def deaths(latest: FrozenTrial, trials: dict[int, FrozenTrial]) -> int:
    """How many times the worker of a grid point died (a trial failed as "worker gone"), over ``latest`` and the
    trials it retries (``trials``: by number); deliberate stops (SIGINT, SIGTERM) do not count."""
    attempts = [*latest.system_attrs.get("retry_history", []), latest.number]
    return sum(trials[n].user_attrs.get("interrupted") == "worker gone" for n in attempts if n in trials)


def retried_enough(latest: FrozenTrial, trials: dict[int, FrozenTrial]) -> bool:
    """Whether an interrupted grid point is left failed: its worker died more than ``MAX_RETRY`` times."""
    return _interrupted(latest) and deaths(latest, trials) > MAX_RETRY


def recover(study: optuna.Study, campaign: Campaign, stale_after: float = 1800.0) -> list[int]:
    """Fail the RUNNING trials of dead workers (journal storage: the process on this machine is gone, else no
    heartbeat for ``stale_after`` seconds; a database: Optuna's heartbeat, whose callback enqueues the retry) and
    enqueue each grid point whose latest trial was interrupted again, unless its worker died more than ``MAX_RETRY``
    times. Returns the numbers of the trials retried."""
    storage = study._storage
    if isinstance(storage, RDBStorage):
        optuna.storages.fail_stale_trials(study)
    by_number = {t.number: t for t in study.get_trials(deepcopy=False)}
    retried = []
    for trials in grid_states(study, campaign).values():
        if any(t.state in (TrialState.COMPLETE, TrialState.WAITING) for t in trials):
            continue
        for trial in trials:
            if trial.state != TrialState.RUNNING or isinstance(storage, RDBStorage):
                continue
            started = trial.datetime_start.timestamp() if trial.datetime_start else None
            if not _alive(trial.user_attrs.get("worker", {}), stale_after, trial.user_attrs.get("heartbeat", started)):
                storage.set_trial_user_attr(trial._trial_id, "interrupted", "worker gone")
                storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
        trials = [storage.get_trial(t._trial_id) for t in trials if t.state != TrialState.PRUNED]  # not duplicates
        if not trials or any(t.state == TrialState.RUNNING for t in trials):
            continue
        latest = trials[-1]
        history = latest.system_attrs.get("retry_history", [])
        if _interrupted(latest) and not retried_enough(latest, {**by_number, **{t.number: t for t in trials}}):
            # Optuna's retry (as RetryHeartbeatStaleTrialCallback enqueues it), without the failed run's attributes
            enqueue(study, grid_point(latest), failed_trial=latest.system_attrs.get("failed_trial", latest.number),
                    retry_history=[*history, latest.number])  # fmt: skip
            retried.append(latest.number)
    return retried


def enqueue(study: optuna.Study, point: tuple[str, str, int], **system_attrs: Any) -> None:
    """A waiting trial of ``point`` with fixed parameters, as ``Study.enqueue_trial`` makes it: the GridSampler gives
    such a trial no grid id, so it never marks another grid point as visited (a trial that draws its parameters from
    the sampler, as retries did before, takes the id of its number and left that id's point to random draws)."""
    params = dict(zip(("task", "variant", "seed"), point))
    study.add_trial(optuna.create_trial(state=TrialState.WAITING, system_attrs={"fixed_params": params, **system_attrs}))


def draw(study: optuna.Study, campaign: Campaign, rng: random.Random) -> None:
    """Enqueue a grid point that no trial holds, drawn at random (each worker its own draw, so that workers starting
    together rarely take the same one), unless a trial waits already (a retry first)."""
    states = grid_states(study, campaign)
    if any(t.state == TrialState.WAITING for trials in states.values() for t in trials):
        return
    free = [point for point, trials in states.items() if not trials]
    if free:
        enqueue(study, rng.choice(free))


def pending(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points that no worker has started and that wait for one (never run, or enqueued again)."""
    count = 0
    for trials in grid_states(study, campaign).values():
        if not trials or any(t.state == TrialState.WAITING for t in trials):
            count += 1
    return count


def done(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points with a complete trial."""
    return sum(any(t.state == TrialState.COMPLETE for t in trials) for trials in grid_states(study, campaign).values())


# ---------------------------------------------------------------------------------------------- workers
def objective(campaign: Campaign):
    def run_trial(trial: optuna.Trial) -> float:
        try:
            trial.set_user_attr("interrupted", "")
            task = trial.suggest_categorical("task", list(campaign.tasks))
            variant = trial.suggest_categorical("variant", list(campaign.variants))
            seed = trial.suggest_categorical("seed", list(campaign.seeds))
            point = (task, variant, seed)
            this = trial.study._storage.get_trial(trial._trial_id)
            taken = [t for t in trial.study.get_trials(deepcopy=False)
                     if t.number != trial.number and grid_point(t) == point and _yields(this, t)]  # fmt: skip
            if taken:  # the grid point is done, or another worker took it at the same moment
                trial.set_user_attr("duplicate_of", taken[0].number)
                raise optuna.TrialPruned()
            trial.set_user_attr("worker", {"host": socket.gethostname(), "boot_id": _boot_id(), "pid": os.getpid()})
            trial.set_user_attr("heartbeat", time.time())
            folder = campaign.checkpoint_folder(trial.study.study_name) / f"{task}_{variant}_seed{seed}"
            result = train(campaign, task, variant, seed, trial, checkpoint=folder)
            for key, value in result.items():
                trial.set_user_attr(key, value)
        except (KeyboardInterrupt, SystemExit):
            trial.set_user_attr("interrupted", "stopped")
            raise
        return result["max_average_return"]

    return run_trial


def _yields(trial: FrozenTrial, other: FrozenTrial) -> bool:
    """Whether ``trial`` leaves its grid point to ``other``, a trial of the same point: to a complete one; a new trial
    to a retried one, waiting or running (so that the retry of a dead worker's trial runs, once); between two of the
    same kind, the later to the earlier."""
    if other.state == TrialState.COMPLETE:
        return True
    retried, other_retried = "retry_history" in trial.system_attrs, "retry_history" in other.system_attrs
    if other.state == TrialState.WAITING:
        return other_retried and not retried
    if other.state == TrialState.RUNNING:
        return other_retried > retried or (other_retried == retried and other.number < trial.number)
    return False


def _stop(*_: Any) -> None:
    """SIGTERM: stop as SIGINT does (the trial is marked interrupted and enqueued again by the next ``run``)."""
    raise KeyboardInterrupt


def work(names: list[str], storage: str | None, stale_after: float = 1800.0) -> None:
    """One worker: trials of the campaigns one after another, each campaign's grid before the next one's; then, while
    other workers run the last grid points, it waits, and runs any whose worker dies."""
    signal.signal(signal.SIGTERM, _stop)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    provenance()  # the code this process runs
    studies = [(name, *open_study(name, storage_of(name, storage))) for name in names]
    for name, study, campaign in studies:
        work_on(name, study, campaign)
    delay = 1.0
    while any(running(study, campaign) for _, study, campaign in studies):
        time.sleep(delay)
        delay = min(2 * delay, 60.0)
        for name, study, campaign in studies:
            recover(study, campaign, stale_after)
            work_on(name, study, campaign)


def running(study: optuna.Study, campaign: Campaign) -> int:
    """Grid points without a complete trial whose latest trial runs."""
    count = 0
    for trials in grid_states(study, campaign).values():
        trials = [t for t in trials if t.state != TrialState.PRUNED]  # not duplicates
        complete = any(t.state == TrialState.COMPLETE for t in trials)
        count += bool(trials) and trials[-1].state == TrialState.RUNNING and not complete
    return count


def work_on(name: str, study: optuna.Study, campaign: Campaign) -> None:
    total = len(campaign.grid)

    def announce(study: optuna.Study, trial: FrozenTrial) -> None:
        task, variant, seed = grid_point(trial) or ("(no parameters)", "", "")
        if trial.state == TrialState.COMPLETE:
            a = trial.user_attrs
            line = (f"max average return {a['max_average_return']:.1f}, final {a['final_return']:.1f}, "
                    f"{a['steps_per_cpu_second']:.0f} steps/CPU-s, {a['cpu_seconds'] / 60:.1f} CPU-min "
                    f"(+{a['eval_cpu_seconds'] / 60:.1f} evaluating), {a['wall_seconds'] / 60:.1f} wall-min")  # fmt: skip
        else:
            line = trial.state.name
        print(f"[{done(study, campaign)}/{total}] {name} #{trial.number} {task} {variant} seed {seed}: {line}", flush=True)

    rng = random.Random()  # seeded from the OS: workers draw apart
    while pending(study, campaign):
        draw(study, campaign, rng)
        study.optimize(objective(campaign), n_trials=1, catch=(Exception,), callbacks=[announce], gc_after_trial=True)


def run(names: list[str], storage: str | None, workers: int, stale_after: float) -> None:
    """Recover the trials of dead workers, start ``workers`` worker processes over the campaigns in order and show
    the grids' progress."""
    studies = []
    for name in names:
        study, campaign = open_study(name, storage_of(name, storage))
        retried = recover(study, campaign, stale_after)
        if retried:
            print(f"{name}: trials {retried} were interrupted or their worker is gone: enqueued again", flush=True)
        print(f"{name}: {done(study, campaign)}/{len(campaign.grid)} grid points complete, "
              f"{pending(study, campaign)} waiting", flush=True)  # fmt: skip
        studies.append((study, campaign))
    command = [sys.executable, str(pathlib.Path(__file__).resolve()), "work", "--campaign", *names]
    command += ["--stale-after", str(stale_after)]
    command += ["--storage", storage] if storage else []
    processes = [subprocess.Popen(command) for _ in range(workers)]

    def stop(*_: Any) -> None:
        for process in processes:
            process.send_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, stop)
    from tqdm import tqdm

    def complete() -> int:
        return sum(done(study, campaign) for study, campaign in studies)

    total = sum(len(campaign.grid) for _, campaign in studies)
    with tqdm(total=total, initial=complete(), desc=" ".join(names), unit="trial", disable=None) as bar:
        while any(process.poll() is None for process in processes):
            time.sleep(10)
            bar.update(complete() - bar.n)
    codes = [process.wait() for process in processes]
    if any(codes):
        raise SystemExit(f"{' '.join(names)}: workers exited with {codes}")


def status(names: list[str], storage: str | None, workers: int) -> None:
    """Each grid point's trials, then the campaigns' expected duration (the report's estimate)."""
    from campaign_report import collect, expected_duration

    for name in names:
        status_of(name, storage)
    runs, progress, _, campaigns = collect(names, storage)
    print(expected_duration(runs, progress, campaigns, workers))


def status_of(name: str, storage: str | None) -> None:
    study, campaign = open_study(name, storage_of(name, storage))
    counts: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        counts[trial.state.name] = counts.get(trial.state.name, 0) + 1
    print(f"{name}: {done(study, campaign)}/{len(campaign.grid)} grid points complete; trials by state {counts}")
    for (task, variant, seed), trials in grid_states(study, campaign).items():
        states = " ".join(
            f"#{t.number}:{t.state.name}" + (f" (max average return {t.value:.0f})" if t.value is not None else "")
            for t in trials
        )
        print(f"  {task:28s} {variant:26s} seed {seed}: {states or '-'}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=["run", "work", "status"])
    parser.add_argument("--campaign", nargs="+", required=True,
                        help=f"campaigns, run in this order: of {sorted(CAMPAIGNS)}, or a new name")  # fmt: skip
    parser.add_argument("--storage", default=None, help="database URL or journal file (default: benchmarks/campaigns/)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="worker processes (default: the cores)")
    parser.add_argument("--stale-after", type=float, default=1800.0,
                        help="journal storage: a RUNNING trial of another machine without a heartbeat for this "
                             "many seconds is failed and enqueued again (here: once its process is gone)")  # fmt: skip
    new = parser.add_argument_group("a new campaign's definition (stored in its study when it is created)")
    new.add_argument("--protocol", choices=sorted(VARIANTS))
    new.add_argument("--tasks", nargs="+")
    new.add_argument("--variants", nargs="+")
    new.add_argument("--seeds", nargs="+", type=int)
    new.add_argument("--timesteps", type=int)
    new.add_argument("--eval-freq", type=int, default=20_000)
    new.add_argument("--eval-episodes", type=int, default=10)
    new.add_argument("--conf", help="protocol zoo: the rl-zoo3 hyperparameter file of every variant (in the repository)")
    args = parser.parse_args(argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if args.protocol or args.tasks or args.variants or args.seeds or args.timesteps:
        missing = [n for n in ("protocol", "tasks", "variants", "seeds", "timesteps") if getattr(args, n) is None]
        if missing:
            parser.error(f"a campaign's definition needs --{' --'.join(missing)} as well")
        given = Campaign(args.protocol, tuple(args.tasks), tuple(args.variants), tuple(args.seeds), args.timesteps,
                         args.eval_freq, args.eval_episodes, args.conf)  # fmt: skip
        if len(args.campaign) > 1:
            parser.error("define one campaign at a time")
        open_study(args.campaign[0], storage_of(args.campaign[0], args.storage), given)
    if args.command == "run":
        run(args.campaign, args.storage, args.workers, args.stale_after)
    elif args.command == "work":
        work(args.campaign, args.storage, args.stale_after)
    else:
        status(args.campaign, args.storage, args.workers)


if __name__ == "__main__":
    main()
