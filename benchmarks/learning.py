"""Learning benchmark: SB3 PPO (A2C) vs PPOPeVFA (A2CPeVFA) variants through rl-zoo3, at identical hyperparameters.

Every (env, variant, seed) is one rl-zoo3 training (``python -m sb3_pevfa.train --algo ppo|ppo_pevfa|a2c|a2c_pevfa``)
reading the same config file per base algorithm (``benchmarks/hyperparams/learning.yml``: SB3's PPO defaults;
``learning_a2c.yml``: SB3's A2C defaults); PeVFA variants add only their PeVFA options (``--hyperparams``).
rl-zoo3's EvalCallback evaluates every ``--eval-freq`` steps (``--eval-episodes`` deterministic episodes); its
``evaluations.npz`` becomes one JSON file per run. The runs are scheduled by the campaign engine (``campaign.py``,
protocol ``zoo``): one Optuna study per invocation in ``<out>/campaign.journal``, ``--workers`` processes with one torch
thread each, an interrupted sweep resumed by the same command (the runs of dead workers enqueued again); the
finished runs are written to ``<out>`` as JSON, and tasks, variants and seeds whose runs all have one are skipped.

    # SB3's defaults (docs/results-sb3-defaults.md): Hopper-v5 and Walker2d-v5, 300k steps, 5 seeds
    python benchmarks/learning.py --env Hopper-v5 Walker2d-v5 --variants ppo pevfa-opr --seeds 0 1 2 3 4
    # the report only: Table-1 style markdown with rliable bootstrap CIs, and the learning curves
    python benchmarks/learning.py --report --out runs/learning --plot runs/learning.png
    # runs of several invocations on machines of different speeds: per-second views against each seed's PPO run
    python benchmarks/learning.py --report --paired --out docs/results/zoo-tuned/shipped-entries
    # A2C vs A2CPeVFA (SB3's A2C defaults), Hopper-v5, 100k steps, 5 seeds
    python benchmarks/learning.py --env Hopper-v5 --variants a2c a2c-pevfa-opr --timesteps 100000 --eval-freq 10000 \
        --out docs/results/notes/a2c-pevfa/learning_a2c --baseline a2c --plot docs/results/notes/a2c-pevfa/learning_a2c.png
"""

import argparse
import hashlib
import inspect
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

import aggregate
import numpy as np
import yaml
from stable_baselines3 import A2C, PPO

from sb3_pevfa.pevfa.arguments import PAPER_SCHEDULE

#: The shared hyperparameters of each base algorithm (``--conf`` replaces them).
CONFS = {
    "ppo": pathlib.Path(__file__).parent / "hyperparams" / "learning.yml",
    "a2c": pathlib.Path(__file__).parent / "hyperparams" / "learning_a2c.yml",
}

#: PeVFA options of each variant (rl-zoo3 ``--hyperparams``); "ppo" is SB3's PPO. "pevfa-opr" is PPOPeVFA's defaults
#: (results recorded before the cheaper schedule hold what "pevfa-opr-paper-schedule" gives today).
#: Variants named "a2c..." train A2C / A2CPeVFA instead.
VARIANTS: dict[str, dict | None] = {
    "ppo": None,
    "pevfa-none": dict(representation="none"),
    "pevfa-random": dict(representation="random"),
    "pevfa-opr": {},
    "pevfa-spr": dict(representation="spr"),
    "pevfa-fingerprint": dict(representation="fingerprint"),
    "pevfa-opr-critic-first": dict(update_order="critic_first"),
    # CL on the historical updates' cadence (the default since CL's train_freq=None; every 10 env steps before)
    "pevfa-opr-cl": dict(representation_objectives=("cl",)),
    "pevfa-opr-cl-paper-cadence": dict(representation_objectives=("cl",), objective_kwargs={"cl": {"train_freq": 10}}),
    "pevfa-spr-aux": dict(representation="spr", representation_objectives=("aux",)),
    "pevfa-opr-paper": dict(
        update_order="critic_first", value_target_lambda=1.0, learning_rate=1e-4, critic_learning_rate=1e-3, **PAPER_SCHEDULE
    ),
    # the paper's historical updates (64 uniform samples per 10 steps, the encoder also trained on the rollout)
    "pevfa-opr-paper-schedule": dict(PAPER_SCHEDULE),
    # the critic's embedding stream (issue: chi saturated a Tanh stream), each spelled out: the paper's ReLU, a
    # layer-normalised chi, both (the default since the 300k ablation), and the earlier default (the actor's Tanh)
    "pevfa-opr-relu": dict(policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='none')"),
    "pevfa-opr-relu-layernorm": dict(policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='layernorm')"),
    "pevfa-opr-layernorm": dict(policy_kwargs="dict(critic_activation_fn=None, chi_normalization='layernorm')"),
    "pevfa-opr-tanh": dict(policy_kwargs="dict(critic_activation_fn=None, chi_normalization='none')"),
    "pevfa-opr-relu-layernorm-recomputed": dict(
        policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='layernorm')", history_targets="recomputed"
    ),
    # targets of the historical samples: recomputed with the current critic, or the paper's Monte-Carlo returns
    "pevfa-opr-recomputed": dict(history_targets="recomputed"),
    "pevfa-opr-mc": dict(value_target_lambda=1.0),
    # chi without the historical updates (the encoder then learns from the rollout's value loss)
    "pevfa-opr-no-history": dict(history_train_freq=0),
    # under VecNormalize: the history as its rollouts saw it (before the history was re-expressed in today's statistics)
    "pevfa-opr-stale-normalization": dict(history_normalization="rollout"),
    # the critic and encoder at 10x the config's learning rate (the paper's ratio: actor 1e-4, critic 1e-3), and
    # its control: the same critic and rate without chi and without historical updates
    "pevfa-opr-critic-lr-x10": dict(critic_learning_rate_scale=10),
    "pevfa-none-no-history-critic-lr-x10": dict(representation="none", history_train_freq=0, critic_learning_rate_scale=10),
    # an embedding stream whose units cannot die (ELU: a gradient at every input), where ReLU units went flat
    "pevfa-opr-elu": dict(policy_kwargs="dict(critic_activation_fn=nn.ELU)"),
    # a quarter of the historical updates (one per 160 env steps): less of the mixture of old policies in the critic
    "pevfa-opr-history-freq-160": dict(history_train_freq=160),
    # a fifth of the history (40k samples: the last ~20 policies of 2048 steps, where 200k holds ~98): younger data
    "pevfa-opr-history-40k": dict(history_buffer_size=40_000),
    "a2c": None,
    "a2c-pevfa-opr": {},
}


def run_name(env_id: str, variant: str, seed: int) -> str:
    return f"{env_id}_{variant}_seed{seed}"


def base_algorithm(variant: str) -> str:
    return "a2c" if variant.startswith("a2c") else "ppo"


def conf_file(variant: str, args: argparse.Namespace) -> pathlib.Path:
    return args.conf or CONFS[base_algorithm(variant)]


def variant_options(variant: str, env_id: str, conf: pathlib.Path) -> dict | None:
    """The variant's rl-zoo3 ``--hyperparams`` for ``env_id``'s entry of ``conf``: ``critic_learning_rate_scale``
    resolved into a ``critic_learning_rate`` of that multiple of the entry's constant ``learning_rate`` (the base
    algorithm's default if it has none), and ``policy_kwargs`` added to the entry's own (which rl-zoo3 would replace)."""
    options = VARIANTS[variant]
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


# ---------------------------------------------------------------------------------------------------- report
def load_results(out: pathlib.Path) -> dict[str, dict[str, list[dict]]]:
    """env -> variant -> runs (sorted by seed)."""
    results: dict[str, dict[str, list[dict]]] = {}
    for path in sorted(out.glob("*.json")):
        result = json.loads(path.read_text())
        folder = out / "runs" / path.stem
        if "wall_s" not in result["curve"][0] and folder.is_dir():  # runs of before the per-second view
            add_wall_clock(result, folder)
        results.setdefault(result["env"], {}).setdefault(result["variant"], []).append(result)
    for variants in results.values():
        for runs in variants.values():
            runs.sort(key=lambda r: r["seed"])
    return results


def scores(runs: list[dict]) -> dict[str, np.ndarray]:
    """Per-seed scores: max average return (the paper's), final average return, area under the curve (mean)."""
    curves = [np.array([c["mean_return"] for c in r["curve"]]) for r in runs]
    return {
        "max": np.array([c.max() for c in curves]),
        "final": np.array([c[-1] for c in curves]),
        "auc": np.array([c.mean() for c in curves]),
    }


def bootstrap_ci(values: np.ndarray, reps: int = 5000) -> tuple[float, float]:
    """Percentile bootstrap 95 % CI of the mean over seeds: rliable's stratified bootstrap for a single task.

    (scipy's, since rliable 1.2 does not run with today's arch/pandas: arch 7 fails to import under pandas 3 and
    arch 8 rejects rliable's ``random_state`` argument.)"""
    from scipy.stats import bootstrap

    if len(values) < 2:
        return float("nan"), float("nan")
    result = bootstrap((values,), np.mean, n_resamples=reps, method="percentile", rng=np.random.default_rng(0))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def report(out: pathlib.Path, baseline: str = "ppo", paired: bool = False) -> str:
    """Table-1 style markdown per task: max average return +- half a std over seeds (as the paper), its rliable
    95 % CI, final return, area under the curve, the change of the mean vs PPO, seeds and wall time."""
    lines = []
    results = load_results(out)
    for env_id, variants in sorted(results.items()):
        base = scores(variants[baseline])["max"].mean() if baseline in variants else None
        lines += [
            f"**{env_id}** ({variants[next(iter(variants))][0]['timesteps']:,} steps)",
            "",
            f"| variant | seeds | max avg return (± ½ std) | 95 % CI (bootstrap) | vs {baseline} | final avg return | "
            "area under curve | max per seed | wall time / run |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for variant, runs in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
            s = scores(runs)
            low, high = bootstrap_ci(s["max"])
            change = "" if base is None or variant == baseline else f"{s['max'].mean() / base - 1:+.0%}"
            lines.append(
                f"| {variant} | {len(runs)} | {s['max'].mean():.0f} ± {s['max'].std() / 2:.0f} | [{low:.0f}, {high:.0f}] | "
                f"{change} | {s['final'].mean():.0f} ± {s['final'].std() / 2:.0f} | {s['auc'].mean():.0f} | "
                f"{', '.join(f'{v:.0f}' for v in s['max'])} | {np.mean([r['wall_time_s'] for r in runs]):.0f} s |"
            )
        lines += ["", *per_second(variants, baseline, paired), ""]
    return "\n".join(lines + aggregate_table(results, baseline, paired))


def task_scores(results: dict[str, dict[str, list[dict]]], baseline: str, paired: bool = False) -> dict[str, dict[str, dict]]:
    """view -> variant -> task -> per-seed scores, for the variants run on every task that has the baseline: the
    max average return (per step) and the best-so-far return at the baseline's mean wall-clock time (per second;
    ``paired``: at the time of the baseline run of the same seed, :func:`paired_runs`)."""
    tasks = {env_id: variants for env_id, variants in results.items() if baseline in variants}
    common = set.intersection(*(set(variants) for variants in tasks.values())) if tasks else set()
    views: dict[str, dict[str, dict]] = {
        "max average return (per step)": {},
        "best-so-far at the baseline's time": {},
        "best-so-far at the baseline's CPU time": {},
    }
    for env_id, variants in tasks.items():
        for variant in common:
            runs = variants[variant]
            views["max average return (per step)"].setdefault(variant, {})[env_id] = scores(runs)["max"]
            pairs = paired_runs(runs, variants[baseline], paired)
            if pairs and "wall_s" in runs[0]["curve"][0]:
                best = np.array([best_so_far_at(r, budgets(base)["wall"]) for r, base in pairs])
                views["best-so-far at the baseline's time"].setdefault(variant, {})[env_id] = best
            if pairs and all("cpu_time_s" in r for r in runs + variants[baseline]):
                best = np.array([best_so_far_at(r, budgets(base)["cpu"], "cpu") for r, base in pairs])
                views["best-so-far at the baseline's CPU time"].setdefault(variant, {})[env_id] = best
    return {view: variants for view, variants in views.items() if variants or view.endswith("(per step)")}


def aggregate_table(results: dict[str, dict[str, list[dict]]], baseline: str, paired: bool = False) -> list[str]:
    """The aggregate over tasks (benchmarks/aggregate.py): IQM and mean of the scores normalised by the baseline's
    mean per task, with 95 % stratified bootstrap CIs over tasks and seeds."""
    views = task_scores(results, baseline, paired)
    if not views["max average return (per step)"]:
        return []
    tasks = sorted(views["max average return (per step)"][baseline])
    lines = [
        f"**Aggregate over {len(tasks)} task(s)** ({', '.join(tasks)}; each run's score / {baseline}'s mean on its task; "
        "IQM and mean with 95 % stratified bootstrap CIs):",
        "",
        "| view | variant | runs | IQM [95 % CI] | mean [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for view, variants in views.items():
        for variant, raw in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
            normalized = aggregate.normalized(raw, variants[baseline])
            iqm_low, iqm_high = aggregate.stratified_bootstrap_ci(normalized, aggregate.iqm)
            mean_low, mean_high = aggregate.stratified_bootstrap_ci(normalized, aggregate.mean)
            lines.append(
                f"| {view} | {variant} | {sum(len(v) for v in raw.values())} | {aggregate.iqm(normalized):.2f} "
                f"[{iqm_low:.2f}, {iqm_high:.2f}] | {aggregate.mean(normalized):.2f} [{mean_low:.2f}, {mean_high:.2f}] |"
            )
    return [*lines, ""]


def plot_profiles(out: pathlib.Path, png: pathlib.Path, baseline: str, paired: bool = False) -> None:
    """Performance profiles of both views (fraction of runs above tau, baseline-normalised, with 95 % bands)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    views = task_scores(load_results(out), baseline, paired)
    fig, axes = plt.subplots(1, len(views), figsize=(6 * len(views), 4), squeeze=False)
    taus = np.linspace(0.0, 2.0, 81)
    for ax, (view, variants) in zip(axes[0], views.items()):
        for variant, raw in sorted(variants.items()):
            normalized = aggregate.normalized(raw, variants[baseline])
            low, high = aggregate.profile_band(normalized, taus)
            ax.plot(taus, aggregate.performance_profile(normalized, taus), label=variant)
            ax.fill_between(taus, low, high, alpha=0.2)
        ax.set(title=f"{view}, {', '.join(sorted(next(iter(variants.values()), {})))}", xlabel=f"score / {baseline}'s mean",
               ylabel="fraction of runs > tau")  # fmt: skip
        ax.legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)


def cpu_seconds(run: dict, point: dict) -> float:
    """The training process's CPU seconds at evaluation ``point``: the run's CPU time prorated by its steps (only the
    whole run's is recorded; a run's CPU per step is about constant, the history's cost being bounded from its first
    5k steps)."""
    return run["cpu_time_s"] * (point["timesteps"] / run["timesteps"])  # exactly the run's at its last step


def best_so_far_at(run: dict, seconds: float, clock: str = "wall") -> float:
    """The best evaluation of ``run`` made within ``seconds`` of its start (``clock``: ``"wall"``-clock or ``"cpu"``
    seconds of the training process; -inf if none)."""
    times = [c["wall_s"] if clock == "wall" else cpu_seconds(run, c) for c in run["curve"]]
    return aggregate.best_within([c["mean_return"] for c in run["curve"]], times, seconds, float("-inf"))


def budgets(baseline_runs: list[dict]) -> dict[str, float]:
    """The baseline's mean wall-clock and CPU seconds of a whole run."""
    return {
        "wall": float(np.mean([r["curve"][-1].get("wall_s", np.inf) for r in baseline_runs])),
        "cpu": float(np.mean([r.get("cpu_time_s", np.inf) for r in baseline_runs])),
    }


def paired_runs(runs: list[dict], baseline_runs: list[dict], paired: bool) -> list[tuple[dict, list[dict]]]:
    """Each run with the baseline runs that set its budget: all of them, or (``paired``) the one of its seed, which
    ran beside it on the same machine (runs of a seed the baseline lacks are left out). Pairs keep the per-second
    view true when invocations ran on machines of different speeds."""
    if not paired:
        return [(run, baseline_runs) for run in runs]
    by_seed = {r["seed"]: r for r in baseline_runs}
    return [(run, [by_seed[run["seed"]]]) for run in runs if run["seed"] in by_seed]


def per_second(variants: dict[str, list[dict]], baseline: str, paired: bool = False) -> list[str]:
    """The same runs per second: speed (steps per wall-clock and per CPU second of the training process) and the
    best-so-far return at the baseline's own mean wall-clock time of a whole run; ``paired``: speed as the mean
    ratio to the baseline run of the same seed, and that run's time as the budget (:func:`paired_runs`)."""
    if baseline not in variants or "wall_s" not in variants[baseline][0]["curve"][0]:
        return []
    budget = budgets(variants[baseline])
    has_cpu = all("cpu_time_s" in r for runs in variants.values() for r in runs)
    clocks = ("wall", "cpu") if has_cpu else ("wall",)
    if paired:
        title = f"Per second, each seed against the {baseline} run of its seed (its whole run's time the budget"
        at = "at the paired run's time"
        columns = [f"best-so-far {at} (± ½ std) | per seed |", f"best-so-far {at}, CPU (± ½ std) | per seed |"]
    else:
        title = f"Per second (budgets: {baseline}'s mean run, {budget['wall']:.0f} s wall-clock" + (
            f", {budget['cpu']:.0f} CPU-s" if has_cpu else ""
        )
        columns = [f"best-so-far at {budget['wall']:.0f} s (± ½ std) | per seed |",
                   f"best-so-far at {budget['cpu']:.0f} CPU-s (± ½ std) | per seed |"]  # fmt: skip
    lines = [
        title + ("; an evaluation's CPU time is its run's, prorated by steps):" if has_cpu else "):"),
        "",
        f"| variant | steps/s (wall) | steps/CPU-s | speed vs {baseline} (wall / CPU) | " + " ".join(columns[: len(clocks)]),
        "|---|---|---|---|---|---|" + ("---|---|" if has_cpu else ""),
    ]
    for variant, runs in sorted(variants.items(), key=lambda item: (item[0] != baseline, item[0])):
        pairs = paired_runs(runs, variants[baseline], paired)
        if not pairs:
            continue
        runs = [run for run, _ in pairs]
        speed = np.array([speed_of(r, "wall") for r in runs])
        cpu = np.mean([speed_of(r, "cpu") for r in runs]) if has_cpu else np.nan
        ratio = {
            clock: np.mean([speed_of(run, clock) / np.mean([speed_of(b, clock) for b in base]) for run, base in pairs])
            for clock in clocks
        }
        row = f"| {variant} | {speed.mean():.0f} ± {speed.std():.0f} | "
        row += f"{cpu:.0f} | " if has_cpu else "not recorded | "
        row += f"{ratio['wall']:.2f}x / " + (f"{ratio['cpu']:.2f}x | " if has_cpu else "- | ")
        for clock in clocks:
            best = np.array([best_so_far_at(r, budgets(base)[clock], clock) for r, base in pairs])
            row += f"{best.mean():.0f} ± {best.std() / 2:.0f} | {', '.join(f'{v:.0f}' for v in best)} | "
        lines.append(row.rstrip())
    return lines


def speed_of(run: dict, clock: str) -> float:
    """Environment steps per second of a whole run, by ``"wall"``-clock or by the training process's ``"cpu"`` time."""
    return run["timesteps"] / run["wall_time_s" if clock == "wall" else "cpu_time_s"]


def plot(out: pathlib.Path, png: pathlib.Path) -> None:
    """Learning curves per task, against environment steps (top), wall-clock seconds and CPU seconds of the training
    process (bottom; prorated by steps, :func:`cpu_seconds`): mean over seeds with a band of one std, every variant
    in its fixed colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = load_results(out)
    fig, axes = plt.subplots(3, len(results), figsize=(6 * len(results), 12), squeeze=False)
    palette = plt.get_cmap("tab20").colors  # more variants than the ten default colours: none shares one
    colors = {variant: palette[(2 * i) % 20 + (2 * i) // 20 % 2] for i, variant in enumerate(VARIANTS)}
    for column, (env_id, variants) in enumerate(sorted(results.items())):
        for variant, runs in sorted(variants.items()):
            n = min(len(r["curve"]) for r in runs)
            returns = np.array([[c["mean_return"] for c in r["curve"][:n]] for r in runs])
            mean, std = returns.mean(axis=0), returns.std(axis=0)
            clocks = {
                "timesteps": lambda r, c: c["timesteps"],
                "wall_s": lambda r, c: c["wall_s"],
                "cpu_time_s": lambda r, c: cpu_seconds(r, c),
            }
            for row, (key, at) in enumerate(clocks.items()):
                if key not in runs[0]["curve"][0] and key not in runs[0]:
                    continue
                x = np.mean([[at(r, c) for c in r["curve"][:n]] for r in runs], axis=0)  # seeds' mean time per point
                ax = axes[row, column]
                ax.plot(x, mean, color=colors.get(variant), label=f"{variant} ({len(runs)} seeds)")
                ax.fill_between(x, mean - std, mean + std, color=colors.get(variant), alpha=0.2)
        axes[0, column].set(title=env_id, xlabel="environment steps", ylabel="average return (deterministic)")
        axes[1, column].set(title=env_id, xlabel="wall-clock seconds (mean over seeds)", ylabel="average return")
        axes[2, column].set(title=env_id, xlabel="CPU seconds of the training process (mean over seeds)",
                            ylabel="average return")  # fmt: skip
        axes[0, column].legend()
    fig.tight_layout()
    fig.savefig(png, dpi=100)


def schedule(args: argparse.Namespace) -> None:
    """The requested runs without a JSON in ``--out``, as a campaign of protocol zoo (the study named by its
    definition, in ``<out>/campaign.journal``), then every finished run of it written to ``--out``."""
    import campaign

    missing = [(t, v, s) for t in args.env for v in args.variants for s in args.seeds
               if not (args.out / f"{run_name(t, v, s)}.json").exists()]  # fmt: skip
    if not missing:
        return
    conf = None if args.conf is None else str(args.conf.resolve())
    grid = campaign.Campaign("zoo", *(tuple(dict.fromkeys(p[i] for p in missing)) for i in range(3)), args.timesteps,
                             args.eval_freq, args.eval_episodes, conf)  # fmt: skip
    digest = hashlib.sha1(json.dumps(grid.definition(), sort_keys=True).encode()).hexdigest()[:10]
    name, journal = f"learning-{digest}", str(args.out / "campaign.journal")
    study, _ = campaign.open_study(name, campaign.storage_of(name, journal), grid)
    try:
        campaign.run([name], journal, args.workers, stale_after=1800.0)
    finally:
        export(study, args.out)


def export(study, out: pathlib.Path) -> None:
    """Every complete trial's run as ``<out>/<run>.json`` and its training tables as ``<out>/logs/<run>.json``."""
    for trial in study.get_trials(deepcopy=False):
        run = trial.user_attrs.get("zoo_run")
        if trial.state.name != "COMPLETE" or run is None:
            continue
        name = run_name(run["env"], run["variant"], run["seed"])
        if not (out / f"{name}.json").exists():
            (out / f"{name}.json").write_text(json.dumps(run, indent=1))
            (out / "logs").mkdir(exist_ok=True)
            (out / "logs" / f"{name}.json").write_text(json.dumps(trial.user_attrs["training_log"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Hopper-v5", "Walker2d-v5"])
    parser.add_argument("--variants", nargs="+", default=["ppo", "pevfa-opr"], choices=list(VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--eval-freq", type=int, default=20_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="runs at a time (default: the cores)")
    parser.add_argument("--conf", type=pathlib.Path, default=None, help="rl-zoo3 hyperparameters shared by all variants")
    parser.add_argument("--baseline", default="ppo", choices=list(VARIANTS), help="the variant the report compares to")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/learning"))
    parser.add_argument("--report", action="store_true", help="only print the table of the results in --out")
    parser.add_argument("--plot", type=pathlib.Path, default=None, help="also write learning curves to this PNG")
    parser.add_argument(
        "--paired", action="store_true", help="per-second views against the baseline run of each seed (several machines)"
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report:
        schedule(args)
    print(report(args.out, args.baseline, args.paired))
    if args.plot is not None:
        plot(args.out, args.plot)
        plot_profiles(args.out, args.plot.with_name(f"{args.plot.stem}_profile.png"), args.baseline, args.paired)


if __name__ == "__main__":
    main()
