"""Tune PPOPeVFA with rl-zoo3's own Optuna machinery, then draw the study with Optuna's own visualizations.

One process:

    python examples/optuna_search.py --env Hopper-v5 --n-trials 50 --timesteps 300000 --out runs/optuna

Several workers sharing one study (create it once, then run the same command in several shells or machines):

    optuna create-study --storage sqlite:///study.db --study-name pevfa --direction maximize
    python examples/optuna_search.py --storage sqlite:///study.db --study-name pevfa --n-trials 10   # each worker
    # a journal file (study.log) serves the processes of one machine; postgresql://user:password@host/db many

The search is rl-zoo3's (``python -m sb3_pevfa.train -optimize``, i.e. its ``ExperimentManager``): each trial starts
from the env's entry of the shipped ``hyperparams/ppo_pevfa.yml`` (``n_envs``, ``normalize``, ``policy_kwargs``...)
and the sampled parameters replace the entry's (rl-zoo3's PPO space plus PeVFA's,
``sb3_pevfa.rl_zoo.hyperparams_opt``; as in rl-zoo3, a sampled ``net_arch`` / ``activation_fn`` replaces the
entry's whole ``policy_kwargs``);
rl-zoo3's ``TrialEvalCallback`` evaluates and prunes, its samplers and pruners are chosen by name and its storages
by URL. The study is then drawn under ``<out>/plots/``: interactive plotly pages (``optuna.visualization``, HTML)
and the same plots as PNGs (``optuna.visualization.matplotlib``). rl-zoo3's own flags can follow ``--``.

Needs the zoo extra: pip install -e ".[zoo]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("zoo", "examples/optuna_search.py")

import argparse
import pathlib
import sys
import warnings

import matplotlib
import optuna

from sb3_pevfa import train

#: Optuna's plots of a study, by file name: the search, the pruning curves and the parameters
PLOTS = ("optimization_history", "intermediate_values", "param_importances", "parallel_coordinate", "slice")


def storage_of(url: str | None) -> optuna.storages.BaseStorage | str | None:
    """The storage as rl-zoo3 opens it: a path ending in ``.log`` is a journal file, anything else an RDB URL."""
    if url is not None and url.endswith(".log"):
        return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(url))
    return url


def search(args: argparse.Namespace, zoo_args: list[str]) -> optuna.Study:
    """Run ``args.n_trials`` trials of rl-zoo3's search in this process and return the (shared) study."""
    storage = args.storage or str(args.out / "study.log")  # a study to draw even when none is shared
    argv = [
        "--algo", "ppo_pevfa", "--env", args.env, "-f", str(args.out), "-optimize", "--n-trials", str(args.n_trials),
        "-n", str(args.timesteps), "--n-evaluations", str(args.n_evaluations), "--eval-episodes", str(args.eval_episodes),
        "--sampler", args.sampler, "--pruner", args.pruner, "--storage", storage, "--study-name", args.study_name,
        "--search-space", args.search_space, "--num-threads", "1", "--no-optim-plots",
    ]  # fmt: skip
    if args.seed is not None:
        argv += ["--seed", str(args.seed)]
    try:
        train.main(argv + zoo_args)
    except ValueError as error:  # rl-zoo3 reports study.best_trial, which raises when no trial completed
        if "No trials are completed" not in str(error):
            raise
        print(f"no trial completed ({error})")
    return optuna.load_study(study_name=args.study_name, storage=storage_of(storage))


def save_plots(study: optuna.Study, folder: pathlib.Path) -> list[pathlib.Path]:
    """Each of :data:`PLOTS` as ``<name>.html`` (plotly, sharing one ``plotly.min.js``) and ``<name>.png``.

    A plot that the study cannot give yet (e.g. parameter importances before two trials completed) is skipped with
    Optuna's reason printed."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)  # Optuna's matplotlib module
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name in PLOTS:
        try:
            figure = getattr(optuna.visualization, f"plot_{name}")(study)
            with_matplotlib = getattr(optuna.visualization.matplotlib, f"plot_{name}")(study)
        except (ValueError, RuntimeError, ImportError) as error:  # ImportError: older Optuna's fANOVA needs scikit-learn
            print(f"{name}: not drawn ({error})")
            continue
        figure.write_html(folder / f"{name}.html", include_plotlyjs="directory")
        axes = with_matplotlib.flat[0] if hasattr(with_matplotlib, "flat") else with_matplotlib
        axes.figure.savefig(folder / f"{name}.png", dpi=100, bbox_inches="tight")
        plt.close(axes.figure)
        written += [folder / f"{name}.html", folder / f"{name}.png"]
    return written


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    zoo_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--n-trials", type=int, default=20, help="trials run by this worker")
    parser.add_argument("--timesteps", type=int, default=50_000, help="env steps per trial")
    parser.add_argument("--n-evaluations", type=int, default=5, help="evaluations (and pruning points) per trial")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--sampler", default="tpe", choices=["random", "tpe", "auto"])
    parser.add_argument("--pruner", default="median", choices=["halving", "median", "none"])
    parser.add_argument("--storage", default=None, help="journal file (*.log), sqlite:///file.db or postgresql://...")
    parser.add_argument("--study-name", default=None, help="default: ppo_pevfa-<env> (one study per task)")
    parser.add_argument("--search-space", choices=["full", "small"], default="full")
    parser.add_argument("--seed", type=int, default=None, help="seeds the sampler and the trials (default: random)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/optuna"), help="zoo logs and plots")
    parser.add_argument("--tiny", action="store_true", help="2 trials of 1024 steps in the small space (a smoke test)")
    args = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    args.study_name = args.study_name or f"ppo_pevfa-{args.env}"
    if args.tiny:
        args.n_trials, args.timesteps, args.n_evaluations, args.eval_episodes, args.search_space = 2, 1024, 2, 2, "small"
    study = search(args, zoo_args)
    completed = study.get_trials(states=(optuna.trial.TrialState.COMPLETE,))
    if completed:
        print(f"best of {len(study.trials)} trials: {study.best_value:.1f} with {study.best_params}")
    written = save_plots(study, args.out / "plots")
    print(f"{len(written)} plots under {args.out / 'plots'}")


if __name__ == "__main__":
    main()
