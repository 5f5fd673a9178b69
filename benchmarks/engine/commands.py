"""The command lines of the scripts in ``benchmarks/``, each script's docstring its help: ``campaign.py`` (run, work,
status), ``campaign_report.py``, ``learning.py`` (zoo runs scheduled as a campaign, each written as a JSON record, and
their report) and ``training_logs.py``."""

import argparse
import hashlib
import json
import os
import pathlib
import sys

import optuna

from . import training_logs, zoo_report
from .deadline import UNTIL_FORMS, parse_until
from .definitions import CAMPAIGNS, OFF_POLICY, VARIANTS, ZOO_VARIANTS, Campaign
from .report import report, summary
from .results import overview, status
from .storage import is_stored, open_study, storage_of
from .workers import run, unmakeable, work
from .zoo import run_name

#: ``--storage`` of the campaign commands
STORAGE_HELP = "database URL or journal file (default: benchmarks/campaigns/)"


def parser_of(description: str | None) -> argparse.ArgumentParser:
    """A command line's parser, its help the script's docstring as written."""
    return argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)


def campaign_main(argv: list[str] | None = None, description: str | None = None) -> None:
    """``campaign.py run|work|status``: a new campaign's definition stored first, where one is given."""
    parser = parser_of(description)
    parser.add_argument("command", choices=["run", "work", "status"])
    parser.add_argument("--campaign", nargs="+", default=None,
                        help=f"campaigns, run in this order: of {sorted(CAMPAIGNS)}, or a new name (status without it: "
                             "one line per campaign)")  # fmt: skip
    parser.add_argument("--storage", default=None, help=STORAGE_HELP)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="worker processes (default: the cores)")
    parser.add_argument("--stale-after", type=float, default=1800.0,
                        help="journal storage: a RUNNING trial of another machine without a heartbeat for this "
                             "many seconds is failed and enqueued again (here: once its process is gone)")  # fmt: skip
    parser.add_argument("--until", default=None,
                        help="run, work: a deadline: only grid points expected to end before it are taken, and trials "
                             "still running at it stop (as by SIGTERM: a checkpoint at the next iteration boundary; "
                             f"the next run goes on from it): {UNTIL_FORMS}")  # fmt: skip
    parser.add_argument("--fill", action="store_true",
                        help="run, work with --until: take every grid point in the campaigns' order, as without a "
                             "deadline (one running then stops with a checkpoint, and the next run goes on from it on "
                             "a machine that keeps them), protocol zoo's only where they end before it")  # fmt: skip
    parser.add_argument("--retry-raised", action="store_true",
                        help="run: enqueue again the grid points whose training raised (once the cause is mended; "
                             "the status shows each one's exception)")  # fmt: skip
    new = parser.add_argument_group("a new campaign's definition (stored in its study when it is created)")
    new.add_argument("--protocol", choices=sorted(VARIANTS))
    new.add_argument("--tasks", nargs="+")
    new.add_argument("--variants", nargs="+")
    new.add_argument("--seeds", nargs="+", type=int)
    new.add_argument("--timesteps", type=int)
    new.add_argument("--eval-freq", type=int, default=None, help="default: 20000")
    new.add_argument("--eval-episodes", type=int, default=None, help="default: 10")
    new.add_argument("--conf", help="protocol zoo: the rl-zoo3 hyperparameter file of every variant (in the repository)")
    args = parser.parse_args(argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    defining = args.protocol or args.tasks or args.variants or args.seeds or args.timesteps
    if args.campaign is None and (args.command != "status" or defining):
        parser.error(f"{args.command} needs --campaign (campaign.py status without it lists the campaigns)")
    if not defining and (args.eval_freq, args.eval_episodes, args.conf) != (None, None, None):
        parser.error("--eval-freq, --eval-episodes and --conf belong to a new campaign's definition (with --protocol, ...)")
    if args.retry_raised and args.command != "run":
        parser.error("--retry-raised is an option of run")
    if args.until is not None and args.command == "status":
        parser.error("--until is an option of run and work")
    if args.fill and args.until is None:
        parser.error("--fill goes with --until (a deadline)")
    try:
        until = None if args.until is None else parse_until(args.until, passed=args.command == "work")
    except ValueError as error:
        parser.error(str(error))
    given = definition(parser, args) if defining else None
    if args.campaign is None:
        overview(args.storage)
        return
    try:  # an unknown campaign, or one given again with another definition
        opened(args.campaign, args.storage, given)
    except ValueError as error:
        parser.error(str(error))
    if args.command == "run":
        run(args.campaign, args.storage, args.workers, args.stale_after, args.retry_raised, until, args.fill)
    elif args.command == "work":
        work(args.campaign, args.storage, args.stale_after, until, args.fill)
    else:
        try:
            status(args.campaign, args.storage, args.workers)
            sys.stdout.flush()  # here, not at exit: the last block may find the pipe closed too
        except BrokenPipeError:  # read through head or less, which stopped reading: nothing is wrong
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's flush at exit would raise again


def definition(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Campaign:
    """The campaign the command line defines (checked as a new one where the storage does not hold it yet)."""
    missing = [n for n in ("protocol", "tasks", "variants", "seeds", "timesteps") if getattr(args, n) is None]
    if missing:
        parser.error(f"a campaign's definition needs --{' --'.join(missing)} as well")
    if len(args.campaign) > 1:
        parser.error("define one campaign at a time")
    evaluation = (20_000 if args.eval_freq is None else args.eval_freq,
                  10 if args.eval_episodes is None else args.eval_episodes)  # fmt: skip
    try:
        given = Campaign(args.protocol, tuple(args.tasks), tuple(args.variants), tuple(args.seeds), args.timesteps,
                         *evaluation, args.conf)  # fmt: skip
        if not is_stored(args.campaign[0], args.storage):  # a stored definition is read as it was
            given.check_new()
            problems = unmakeable(given.protocol, given.tasks)  # before the definition is stored for good
            if problems:
                raise ValueError(f"these tasks cannot be trained here: {'; '.join(problems)}")
    except ValueError as error:
        parser.error(str(error))
    return given


def opened(names: list[str], storage: str | None, given: Campaign | None = None) -> list[Campaign]:
    """The campaigns, their studies opened (the first one created with ``given``); a ValueError for a campaign that
    is neither the repository's nor in the storage (a mistyped name leaves no empty journal file behind), or one
    given again with another definition."""
    for name in names:
        stored = name in CAMPAIGNS or (given is not None and name == names[0]) or is_stored(name, storage)
        if not stored:
            where = f"in {storage}" if storage else f"in the repository ({sorted(CAMPAIGNS)})"
            raise ValueError(f"No campaign {name!r} {where}: give --protocol, --tasks, --variants, --seeds and "
                             "--timesteps to define a new one (campaign.py), or --storage where it is")  # fmt: skip
    return [open_study(name, storage_of(name, storage), given if i == 0 else None)[1] for i, name in enumerate(names)]


def campaign_report_main(argv: list[str] | None = None, description: str | None = None) -> None:
    """``campaign_report.py``: the report printed, and written with its figures to ``--out``."""
    parser = parser_of(description)
    parser.add_argument("--campaign", nargs="+", required=True)
    parser.add_argument("--storage", default=None, help=STORAGE_HELP)
    parser.add_argument("--baseline", default=None, help="the variant every ratio is to (default: ppo, sac in protocol sac)")
    parser.add_argument("--workers", type=int, default=2, help="cores the expected duration is for")
    where = "write report.md, summary.md (a results page's share of it) and the figures in this folder"
    parser.add_argument("--out", type=pathlib.Path, default=None, help=where)
    parser.add_argument("--beside", nargs="+", default=None, help="campaigns of another protocol, their ratios beside")
    args = parser.parse_args(argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        campaigns = opened(args.campaign, args.storage)
        opened(args.beside or [], args.storage)
    except ValueError as error:
        parser.error(str(error))
    protocols = {c.protocol for c in campaigns}
    labels = {f"{c.protocol}:{v}" if len(protocols) > 1 else v for c in campaigns for v in c.variants}
    args.baseline = args.baseline or ("sac" if protocols <= set(OFF_POLICY) else "ppo")
    if args.baseline not in labels:
        parser.error(f"--baseline {args.baseline!r} is none of these campaigns' variants: {sorted(labels)}")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    png = args.out / "curves.png" if args.out else None
    cache: dict = {}  # the report and its summary read the storage once
    text = report(args.campaign, args.storage, args.baseline, args.workers, png, args.beside, cache)
    if args.out:
        (args.out / "report.md").write_text(text)
        (args.out / "summary.md").write_text(summary(args.campaign, args.storage, args.baseline, args.beside, cache))
    print(text)


def learning_main(argv: list[str] | None = None, description: str | None = None) -> None:
    """``learning.py``: the runs without a record in ``--out`` trained (``schedule``), unless ``--report``; the report."""
    parser = parser_of(description)
    parser.add_argument("--env", nargs="+", default=["Hopper-v5", "Walker2d-v5"])
    parser.add_argument("--variants", nargs="+", default=["ppo", "pevfa-opr"], choices=list(ZOO_VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--eval-freq", type=int, default=20_000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="runs at a time (default: the cores)")
    parser.add_argument("--conf", type=pathlib.Path, default=None, help="rl-zoo3 hyperparameters shared by all variants")
    parser.add_argument("--baseline", default="ppo", choices=list(ZOO_VARIANTS), help="the variant the report compares to")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/learning"))
    parser.add_argument("--report", action="store_true", help="only print the table of the results in --out")
    parser.add_argument("--retry-raised", action="store_true", help="train again the runs whose training raised")
    parser.add_argument("--plot", type=pathlib.Path, default=None, help="also write learning curves to this PNG")
    parser.add_argument(
        "--paired", action="store_true", help="per-second views against the baseline run of each seed (several machines)"
    )
    args = parser.parse_args(argv)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if args.report and not any(args.out.glob("*.json")):
        parser.error(f"--report: no runs in {args.out}")
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report:
        schedule(args)
    print(zoo_report.report(args.out, args.baseline, args.paired))
    if args.plot is not None:
        zoo_report.plot(args.out, args.plot)
        zoo_report.plot_profiles(args.out, args.plot.with_name(f"{args.plot.stem}_profile.png"), args.baseline, args.paired)


def schedule(args: argparse.Namespace) -> None:
    """The requested runs without a JSON in ``--out``, as a campaign of protocol zoo (the study named by its
    definition, in ``<out>/campaign.journal``), then every finished run of it written to ``--out``."""
    asked = [(t, v, s) for t in args.env for v in args.variants for s in args.seeds]
    records = {point: args.out / f"{run_name(*point)}.json" for point in asked}
    other = [f"{path.name} ({', '.join(differ)})" for path in records.values()
             if path.exists() and (differ := settings_differ(json.loads(path.read_text()), args))]  # fmt: skip
    if other:
        raise SystemExit(f"{args.out} holds runs of other settings, which would be reported as these: {', '.join(other)}; "
                         "give another --out")  # fmt: skip
    missing = [point for point, path in records.items() if not path.exists()]
    if not missing:
        return
    conf = None if args.conf is None else str(args.conf.resolve())
    grid = Campaign("zoo", *(tuple(dict.fromkeys(p[i] for p in missing)) for i in range(3)), args.timesteps,
                    args.eval_freq, args.eval_episodes, conf)  # fmt: skip
    digest = hashlib.sha1(json.dumps(grid.definition(), sort_keys=True).encode()).hexdigest()[:10]
    name, journal = f"learning-{digest}", str(args.out / "campaign.journal")
    study, _ = open_study(name, storage_of(name, journal), grid)
    try:
        run([name], journal, args.workers, stale_after=1800.0, retry_raised=args.retry_raised)
    finally:
        export(study, args.out)


def settings_differ(record: dict, args: argparse.Namespace) -> list[str]:
    """The settings of a run's record (its steps, and its evaluation's in its rl-zoo3 command) that differ from
    ``args``', as ``name: record's, asked``."""
    words = record.get("command", "").split()
    held = {"timesteps": record.get("timesteps")}
    for flag, name in (("--eval-freq", "eval_freq"), ("--eval-episodes", "eval_episodes")):
        if flag in words[:-1]:
            held[name] = int(words[words.index(flag) + 1])
    return [f"{name} {value} not {getattr(args, name)}" for name, value in held.items() if value != getattr(args, name)]


def export(study: optuna.Study, out: pathlib.Path) -> None:
    """Every complete trial's run as ``<out>/<run>.json`` and its training tables as ``<out>/logs/<run>.json``."""
    for trial in study.get_trials(deepcopy=False):
        record = trial.user_attrs.get("zoo_run")
        if trial.state.name != "COMPLETE" or record is None:
            continue
        name = run_name(record["env"], record["variant"], record["seed"])
        if not (out / f"{name}.json").exists():
            (out / f"{name}.json").write_text(json.dumps(record, indent=1))
            (out / "logs").mkdir(exist_ok=True)
            (out / "logs" / f"{name}.json").write_text(json.dumps(trial.user_attrs["training_log"]))


def training_logs_main(argv: list[str] | None = None, description: str | None = None) -> None:
    """``training_logs.py``: the logs of ``--out``'s runs kept compactly, then each env's report."""
    parser = parser_of(description)
    parser.add_argument("--out", type=pathlib.Path, required=True, help="a benchmarks/learning.py result folder")
    parser.add_argument("--env", nargs="+", default=["Hopper-v5"])
    parser.add_argument("--plot", type=pathlib.Path, default=None)
    parser.add_argument(
        "--windows",
        type=int,
        nargs="+",
        default=None,
        help="also the signals per window of env steps, given by the windows' upper ends (e.g. 100000 200000 300000)",
    )
    args = parser.parse_args(argv)
    training_logs.collect(args.out)
    for env_id in args.env:
        print(training_logs.report(args.out, env_id), end="\n\n")
        if args.windows:
            print(training_logs.window_report(args.out, env_id, args.windows), end="\n\n")
    if args.plot is not None:
        training_logs.plot(args.out, args.env, args.plot)
