"""Learning campaigns (benchmarks/campaign.py over the package benchmarks/engine/): a tiny grid through Optuna's
journal storage, a killed worker's trial retried exactly once, a resume from the journal and the report from the
storage alone."""

import contextlib
import datetime
import functools
import json
import logging
import os
import pathlib
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import types

import mujoco
import numpy as np
import optuna
import pytest
import torch
from optuna.distributions import CategoricalDistribution
from optuna.trial import TrialState
from stable_baselines3.common.env_util import make_vec_env

ROOT = pathlib.Path(__file__).parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import engine.report  # noqa: E402
from engine import aggregate, commands, definitions, figures, results, storage, tables, training, workers  # noqa: E402

TASK = "InvertedPendulum-v5"


@pytest.fixture(autouse=True)
def checkpoints(tmp_path, monkeypatch):
    """Trials keep their checkpoints in the test's folder (workers started as subprocesses too)."""
    monkeypatch.setenv("SB3_PEVFA_CHECKPOINTS", str(tmp_path / "checkpoints"))
    monkeypatch.setattr(definitions, "CHECKPOINT_DIR", tmp_path / "checkpoints")


@pytest.fixture(autouse=True)
def fresh_stop(monkeypatch):
    """A stop of each test's own (a stop asked in one test, as the worker's signal handlers ask it, stays there), and
    the signal handlers and the alarm put back."""
    stop = training.Stop()
    monkeypatch.setattr(training, "STOP", stop)
    monkeypatch.setattr(workers, "STOP", stop)
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)
    saved = [signal.getsignal(s) for s in stops]
    yield stop
    signal.setitimer(signal.ITIMER_REAL, 0)
    for s, handler in zip(stops, saved):
        signal.signal(s, handler)


def _definition(*variants: str, seeds=("0",), timesteps: int = 4000) -> list[str]:
    return ["--protocol", "paper", "--tasks", TASK, "--variants", *variants, "--seeds", *seeds,
            "--timesteps", str(timesteps), "--eval-freq", "2000", "--eval-episodes", "2"]  # fmt: skip


def _campaign(*args: str) -> str:
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), *args]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    return result.stdout


def _study(name: str, journal: pathlib.Path) -> optuna.Study:
    return storage.open_study(name, storage.storage_of(name, str(journal)))[0]


def test_campaign_runs_its_grid_resumes_from_the_journal_and_reports(tmp_path, capsys):
    journal = tmp_path / "tiny.journal"
    definition = _definition("ppo", "opr-e2e")
    stdout = _campaign("run", "--campaign", "tiny", "--storage", str(journal), "--workers", "2", *definition)
    everything = _study("tiny", journal).get_trials()
    assert stdout.count("tiny #") == len(everything)  # one line per finished trial
    # two workers may draw one grid point at once: the second is pruned as a duplicate, never trained twice
    trials = [t for t in everything if t.state != TrialState.PRUNED]
    assert all("duplicate_of" in t.user_attrs for t in everything if t.state == TrialState.PRUNED)
    assert sorted((t.params["variant"], t.state.name) for t in trials) == [("opr-e2e", "COMPLETE"), ("ppo", "COMPLETE")]
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    for trial in trials:
        attrs = trial.user_attrs
        curve = attrs["curve"]
        assert curve["steps"] == [2000, 4000] and sorted(trial.intermediate_values) == [2000, 4000]
        assert trial.value == attrs["max_average_return"] == max(curve["mean"]) and attrs["final_return"] == curve["mean"][-1]
        assert [trial.intermediate_values[s] for s in curve["steps"]] == curve["mean"]
        assert 0 < curve["cpu_s"][0] < curve["cpu_s"][1] <= attrs["cpu_seconds"] and attrs["eval_cpu_seconds"] > 0
        assert attrs["steps_per_cpu_second"] == pytest.approx(4000 / attrs["cpu_seconds"])
        assert attrs["versions"]["torch"] == torch.__version__ and attrs["versions"]["mujoco"] == mujoco.__version__
        assert attrs["commit"].removesuffix("+dirty") == head  # the code the worker ran
    # the same command again: the grid is complete, nothing runs twice
    again = _campaign("run", "--campaign", "tiny", "--storage", str(journal), "--workers", "2")
    assert "tiny: 2/2 grid points complete, 0 waiting" in again
    assert len(_study("tiny", journal).get_trials()) == len(everything)
    # the status shows each grid point's trials and, once complete, its max average return
    shown = _campaign("status", "--campaign", "tiny", "--storage", str(journal))
    for trial in trials:
        assert f"#{trial.number}:COMPLETE (max average return {trial.value:.0f})" in shown
    assert "nothing left to run" in shown.splitlines()[-1]
    # a stored campaign is never redefined
    with pytest.raises(SystemExit):  # a usage error
        _campaign_main("run", "--campaign", "tiny", "--storage", str(journal), *_definition("ppo"))
    assert "a campaign's definition never changes" in capsys.readouterr().err
    # the report, from the storage alone
    text = engine.report.report(["tiny"], str(journal), "ppo", 2, tmp_path / "curves.png")
    value = {t.params["variant"]: t.value for t in trials}
    row = next(line for line in text.splitlines() if line.startswith(f"| {TASK} | "))
    ratio = value["opr-e2e"] / value["ppo"]
    assert row.startswith(f"| {TASK} | {value['ppo']:.0f} ± 0 (1) | {value['opr-e2e']:.0f} ± 0 (1) **{ratio:.2f}x** |")
    assert "Campaigns tiny: 2 of 2 runs complete." in text and "Deviations from the paper" in text
    assert (tmp_path / "curves.png").stat().st_size > 10_000


def test_a_journal_of_the_old_layout_finishes_its_grid_and_reports_both_runs(tmp_path):
    """A journal that the engine wrote before it became a package (seed 0 complete, seed 1 never run): the same
    command finishes the grid, the old trial stays as it was, and the status and the report read both runs."""
    journal = tmp_path / "old.journal"
    shutil.copy(ROOT / "tests" / "data" / "old_layout.journal", journal)
    old = _study("old-layout", journal).trials[0]
    assert old.state == TrialState.COMPLETE and old.params["seed"] == 0 and old.value == 15.0
    stdout = _campaign("run", "--campaign", "old-layout", "--storage", str(journal), "--workers", "1")
    assert "old-layout: 1/2 grid points complete, 1 waiting" in stdout
    trials = _study("old-layout", journal).get_trials()
    assert [(t.params["seed"], t.state) for t in trials] == [(0, TrialState.COMPLETE), (1, TrialState.COMPLETE)]
    assert trials[0].user_attrs == old.user_attrs and trials[0].value == old.value  # kept as the old code stored it
    new = trials[1]
    assert new.user_attrs["curve"]["steps"] == [2000, 4000] and new.value == new.user_attrs["max_average_return"]
    assert set(new.user_attrs) - set(old.user_attrs) == {"checkpoint"}  # the same keys, and where its checkpoint is
    assert set(old.user_attrs) <= set(new.user_attrs)
    assert set(new.user_attrs["worker"]) == set(old.user_attrs["worker"])
    assert set(new.user_attrs["versions"]) == set(old.user_attrs["versions"])
    shown = _campaign("status", "--campaign", "old-layout", "--storage", str(journal))
    assert "#0:COMPLETE (max average return 15)" in shown and f"#1:COMPLETE (max average return {new.value:.0f})" in shown
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign_report.py"), "--campaign", "old-layout",
               "--storage", str(journal), "--out", str(tmp_path / "report")]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    text = (tmp_path / "report" / "report.md").read_text()
    scores = np.array([old.value, new.value])
    assert "Campaigns old-layout: 2 of 2 runs complete." in text and text == result.stdout.removesuffix("\n")
    assert f"| {TASK} | {scores.mean():.0f} ± {scores.std() / 2:.0f} (2) |" in text
    assert (tmp_path / "report" / "curves.png").stat().st_size > 10_000
    assert (tmp_path / "report" / "summary.md").read_text().startswith("2 of 2 runs complete, 4,000 env steps per run.")


def test_two_machines_share_one_campaign_on_postgresql(postgres_url):
    """The command of every machine with one database URL: each grid point trains once, whichever worker takes it."""
    definition = _definition("ppo", seeds=("0", "1", "2"), timesteps=2000)
    command = ["run", "--campaign", "pg", "--storage", postgres_url, "--workers", "1", *definition]
    first = subprocess.Popen(
        [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), *command], stdout=subprocess.PIPE, text=True
    )
    second = _campaign(*command)
    first_out, _ = first.communicate(timeout=600)
    assert first.returncode == 0
    study = optuna.load_study(study_name="pg", storage=postgres_url)
    assert sorted(t.params["seed"] for t in study.trials if t.state == TrialState.COMPLETE) == [0, 1, 2]
    # nothing trained twice: a grid point both machines drew at once is pruned in the second one
    others = [t for t in study.trials if t.state != TrialState.COMPLETE]
    assert all(t.state == TrialState.PRUNED and "duplicate_of" in t.user_attrs for t in others)
    assert (first_out + second).count("pg #") == len(study.trials)


@pytest.mark.parametrize("error", ["IntegrityError", "ProgrammingError"])
def test_a_machine_that_loses_the_race_to_create_the_schema_reads_it(monkeypatch, error):
    """Machines starting together on a fresh database race to create Optuna's tables: the loser's CREATE fails on a
    duplicate row (IntegrityError) or table (PostgreSQL's DuplicateTable, a ProgrammingError); it tries again."""
    import sqlalchemy

    calls = []

    def created_by_another(*args, **kwargs):
        calls.append(args)
        if len(calls) == 1:
            raise getattr(sqlalchemy.exc, error)("CREATE TABLE studies", {}, Exception("already exists"))
        return "storage"

    monkeypatch.setattr(storage, "RDBStorage", created_by_another)
    monkeypatch.setattr(storage.time, "sleep", lambda seconds: None)
    assert storage.storage_of("pg", "postgresql://machine/db") == "storage" and len(calls) == 2


def _campaign_main(*args: str) -> None:
    commands.campaign_main(list(args))


def test_a_killed_workers_trial_is_retried_exactly_once(tmp_path):
    journal = tmp_path / "kill.journal"
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), "run", "--campaign", "kill", "--storage",
               str(journal), "--workers", "1", *_definition("ppo", seeds=("0", "1"), timesteps=8000)]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    killed = None
    while killed is None and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.5)
        if journal.exists():
            running = [t for t in _study("kill", journal).get_trials() if t.state == TrialState.RUNNING]
            killed = next((t for t in running if "progress" in t.user_attrs), None)  # mid-training
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert killed is not None, "no trial reached its first evaluation"
    assert _study("kill", journal).trials[killed.number].state == TrialState.RUNNING  # a dead worker's trial
    stdout = _campaign("run", "--campaign", "kill", "--storage", str(journal), "--workers", "2")
    assert f"trials [{killed.number}] were interrupted or their worker is gone" in stdout
    trials = _study("kill", journal).get_trials()
    assert trials[killed.number].state == TrialState.FAIL
    retries = [t for t in trials if t.system_attrs.get("failed_trial") == killed.number]
    assert len(retries) == 1 and retries[0].state == TrialState.COMPLETE and retries[0].params == killed.params
    complete = sorted(t.params["seed"] for t in trials if t.state == TrialState.COMPLETE)
    assert complete == [0, 1]  # every grid point once


def test_recover_enqueues_interrupted_trials_once_and_leaves_failed_trainings(tmp_path, capsys):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1, 2, 3, 4), 4000, 2000, 2)
    study, _ = storage.open_study("recover", storage.storage_of("recover", str(tmp_path / "r.journal")), tiny)
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}

    def add(seed: int, system_attrs=None, **user_attrs) -> None:
        params = {"task": TASK, "variant": "ppo", "seed": seed}
        study.add_trial(optuna.create_trial(state=TrialState.FAIL, params=params, distributions=distributions,
                                            user_attrs=user_attrs, system_attrs=system_attrs))  # fmt: skip

    add(0, interrupted="stopped")  # SIGINT / SIGTERM
    add(1, error="RuntimeError: a NaN")  # its training raised: it stays failed
    for attempt in range(storage.MAX_RETRY + 1):  # trials 2-5: its worker died once and on each retry
        add(2, {"retry_history": list(range(2, 2 + attempt))} if attempt else None, interrupted="worker gone")
    for attempt in range(storage.MAX_RETRY + 2):  # trials 6-10: stopped again and again, never dead
        add(3, {"retry_history": list(range(6, 6 + attempt))} if attempt else None, interrupted="stopped")
    assert storage.recover(study, tiny) == [0, 10] and storage.recover(study, tiny) == []  # enqueued once
    waiting = [t for t in study.get_trials() if t.state == TrialState.WAITING]
    assert [storage.grid_point(t) for t in waiting] == [(TASK, "ppo", 0), (TASK, "ppo", 3)]
    assert waiting[0].system_attrs["retry_history"] == [0] and waiting[1].system_attrs["retry_history"] == [6, 7, 8, 9, 10]
    assert storage.pending(study, tiny) == 3  # seeds 0 and 3 again and seed 4, never started; not seeds 1 and 2
    results.status_of("recover", str(tmp_path / "r.journal"))
    shown = capsys.readouterr().out  # why each failed trial stopped
    assert "seed 0: #0:FAIL (interrupted: stopped) #11:WAITING\n" in shown
    assert "seed 1: #1:FAIL (raised RuntimeError: a NaN)\n" in shown
    assert "seed 2: #2:FAIL (interrupted: worker gone) #3:FAIL (interrupted: worker gone)" in shown
    # a failed trial without a reason kept: on a database, Optuna's heartbeat failed it (and retries it itself); on a
    # journal, a stop reached it as it marked itself: tried again
    failed = optuna.create_trial(state=TrialState.FAIL)
    assert results.trial_outcome(failed, database=True) == " (interrupted: worker gone)"
    assert results.trial_outcome(failed) == " (failed: no reason kept, tried again)"
    progress = {"progress": {"steps": 1_020_000, "cpu_s": 450.0, "wall_s": 500.0}}  # at its last evaluation
    running = optuna.create_trial(state=TrialState.RUNNING, user_attrs=progress)
    assert results.trial_outcome(running) == " (last evaluation at 1,020,000 env steps, 7.5 CPU-min)"
    stopped = optuna.create_trial(state=TrialState.FAIL, user_attrs={**progress, "interrupted": "stopped"})
    assert results.trial_outcome(stopped) == " (interrupted: stopped; last evaluation at 1,020,000 env steps, 7.5 CPU-min)"
    done = optuna.create_trial(state=TrialState.COMPLETE, value=251.4, user_attrs=progress)  # complete runs keep theirs
    assert results.trial_outcome(done) == " (max average return 251)"
    assert results.trial_outcome(optuna.create_trial(state=TrialState.RUNNING)) == ""  # before its first evaluation
    raised = optuna.create_trial(state=TrialState.FAIL, user_attrs={**progress, "error": "RuntimeError: a NaN"})
    assert results.trial_outcome(raised) == " (raised RuntimeError: a NaN)"
    duplicate = optuna.create_trial(state=TrialState.PRUNED, user_attrs={"duplicate_of": 7})  # a worker drew a held point
    assert results.trial_outcome(duplicate) == " (a duplicate of #7)"
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, params={"task": TASK, "variant": "ppo", "seed": 4},
                                        distributions=distributions))  # fmt: skip
    assert storage.recover(study, tiny) == [13] and not storage.raised(study.trials[13])
    notes = results.collect(["recover"], str(tmp_path / "r.journal"))[2]
    assert notes == [
        f"{TASK} ppo seed 1: trial 1 failed (its training raised RuntimeError: a NaN)",
        f"{TASK} ppo seed 2: trial 5's worker died {storage.MAX_RETRY + 1} times: not retried again",
    ]
    with pytest.raises(ValueError, match="Unknown variants \\['opr'\\] of protocol 'paper'"):
        definitions.Campaign("paper", (TASK,), ("opr",), (0,), 4000)
    with pytest.raises(ValueError, match="Unknown campaign 'nothing'"):
        storage.open_study("nothing", storage.storage_of("nothing", str(tmp_path / "n.journal")))


@pytest.mark.parametrize("kind", ["journal", "database"])
def test_recover_leaves_a_retry_whose_training_raised_and_prunes_a_taken_grid_point(tmp_path, monkeypatch, capsys, kind):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1, 2, 3), 4000, 2000, 2)
    where = str(tmp_path / "r.journal") if kind == "journal" else f"sqlite:///{tmp_path / 'r.db'}"  # Optuna's heartbeat
    study, _ = storage.open_study("raise", storage.storage_of("raise", where), tiny)
    assert storage.on_database(study) == (kind == "database")  # through the cache Optuna wraps a database in
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    params = {"task": TASK, "variant": "ppo", "seed": 0}
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, params=params, distributions=distributions,
                                        user_attrs={"interrupted": "stopped"}))  # fmt: skip
    assert storage.recover(study, tiny) == [0]

    def raises(*args, **kwargs):
        raise RuntimeError("a NaN in the update")

    monkeypatch.setattr(workers, "train", raises)
    study.optimize(workers.objective(tiny), n_trials=1, catch=(RuntimeError,))  # the retry runs and raises
    retry = study.trials[1]
    assert retry.state == TrialState.FAIL and retry.system_attrs["failed_trial"] == 0 and not retry.user_attrs["interrupted"]
    assert results.trial_outcome(retry) == " (raised RuntimeError: a NaN in the update)"  # the status says why
    assert storage.recover(study, tiny) == []  # a training that raised stays failed
    assert workers.failed(study, tiny) == 1 and "1 grid points failed: their training raised" in workers.failed_text(
        study, tiny
    )
    assert storage.recover(study, tiny, retry_raised=True) == [1]  # unless asked, once the cause is mended
    again = study.trials[2]
    assert again.state == TrialState.WAITING and storage.grid_point(again) == (TASK, "ppo", 0)
    assert again.system_attrs["retry_history"] == [0, 1] and storage.recover(study, tiny, retry_raised=True) == []
    study.optimize(workers.objective(tiny), n_trials=1, catch=(RuntimeError,))
    results.status_of("raise", where)  # a retried training that raised is not a dead worker's
    assert "#0:FAIL (interrupted: stopped) #1:FAIL (raised RuntimeError: a NaN in the update) #2:FAIL (raised" in (
        capsys.readouterr().out
    )
    text = engine.report.report(["raise"], where, "ppo", 2, None)  # no run complete yet
    assert text.endswith(f"- {TASK} ppo seed 0: trial 2 failed (its training raised RuntimeError: a NaN in the update)")
    # a grid point that another trial has taken is pruned, never trained twice
    study.add_trial(optuna.create_trial(state=TrialState.COMPLETE, value=1.0, params={**params, "seed": 1},
                                        distributions=distributions))  # fmt: skip
    study.enqueue_trial({**params, "seed": 1})
    study.optimize(workers.objective(tiny), n_trials=1)
    assert study.trials[-1].state == TrialState.PRUNED and study.trials[-1].user_attrs["duplicate_of"] == 3
    study.enqueue_trial({**params, "seed": 2})  # a first trial that raises, enqueued again by --retry-raised
    study.optimize(workers.objective(tiny), n_trials=1, catch=(RuntimeError,))
    assert storage.recover(study, tiny, retry_raised=True) == [2, 5]  # seed 0 again too
    results.status_of("raise", where)
    assert "seed 2: #5:FAIL (raised RuntimeError: a NaN in the update) #7:WAITING\n" in capsys.readouterr().out
    # a trial without a reason kept: on a database, one Optuna's heartbeat failed (its retries are Optuna's); on a
    # journal, a stop that cut its marking short: tried again, never counted as raised
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, params={**params, "seed": 3}, distributions=distributions))
    assert workers.failed(study, tiny) == 0  # seeds 0 and 2 wait again; seed 3 kept no exception
    assert storage.recover(study, tiny, retry_raised=True) == ([] if kind == "database" else [8])
    results.status_of("raise", where)
    outcome = "(interrupted: worker gone)\n" if kind == "database" else "(failed: no reason kept, tried again) #9:WAITING\n"
    assert f"seed 3: #8:FAIL {outcome}" in capsys.readouterr().out


def test_run_stops_before_any_worker_where_a_task_left_to_train_cannot_be_made(tmp_path, monkeypatch):
    tiny = definitions.Campaign("paper", (TASK, "NoSuchTask-v0", "Pendulum-v1", "CartPole-v1"), ("ppo",), (0,), 4000, 2000, 2)
    study, _ = storage.open_study("made", storage.storage_of("made", str(tmp_path / "m.journal")), tiny)
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    study.add_trial(optuna.create_trial(state=TrialState.COMPLETE, value=1.0, distributions=distributions,
                                        params={"task": "Pendulum-v1", "variant": "ppo", "seed": 0}))  # fmt: skip
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, distributions=distributions, user_attrs={"error": "x"},
                                        params={"task": "CartPole-v1", "variant": "ppo", "seed": 0}))  # fmt: skip
    made, make = [], workers.gymnasium.make
    monkeypatch.setattr(workers.gymnasium, "make", lambda task: made.append(task) or make(task))
    monkeypatch.setattr(workers.subprocess, "Popen", lambda *args, **kwargs: pytest.fail("a worker started"))
    with pytest.raises(SystemExit, match=r"(?s)cannot be trained on this machine.*made: NoSuchTask-v0: NameNotFound"):
        workers.run(["made"], str(tmp_path / "m.journal"), workers=1, stale_after=1800.0)
    assert made == [TASK, "NoSuchTask-v0"]  # not the tasks whose grid points are complete or failed for good


def test_retries_and_draws_train_every_grid_point_once_without_duplicates(tmp_path, monkeypatch):
    """A retry enqueued while trials of other points exist, then a worker to the end: each point trains once and no
    trial is pruned as a duplicate (a retry that took the sampler's grid id of its number left that id's point to
    random draws of the whole grid, most of them duplicates)."""
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), tuple(range(8)), 4000, 2000, 2)
    journal = str(tmp_path / "d.journal")
    study, _ = storage.open_study("draws", storage.storage_of("draws", journal), tiny)
    trained = []

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        trained.append(seed)
        if len(trained) == 3:  # the third training is stopped: the next run enqueues it again
            raise KeyboardInterrupt
        keys = ("final_return", "cpu_seconds", "eval_cpu_seconds", "wall_seconds", "steps_per_cpu_second")
        return {"max_average_return": float(seed), **dict.fromkeys(keys, 1.0)}

    monkeypatch.setattr(workers, "train", train)
    with pytest.raises(KeyboardInterrupt):
        workers.work_on("draws", study, tiny)
    assert storage.recover(study, tiny) == [2]
    workers.work_on("draws", study, tiny)
    trials = study.get_trials()
    assert sorted(trained) == sorted([*range(8), trained[2]])  # the stopped one twice, every other point once
    assert [t.state for t in trials].count(TrialState.PRUNED) == 0 and len(trials) == 9
    assert sorted(t.params["seed"] for t in trials if t.state == TrialState.COMPLETE) == list(range(8))
    retry = next(t for t in trials if "retry_history" in t.system_attrs)
    assert retry.params == trials[2].params and retry.state == TrialState.COMPLETE


def test_a_worker_with_nothing_left_waits_for_running_trials_and_runs_one_whose_worker_died(tmp_path, monkeypatch):
    """The last grid point runs in another worker, which dies: a worker out of work does not exit but retries it."""
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 4000, 2000, 2)
    journal = str(tmp_path / "w.journal")
    study, _ = storage.open_study("wait", storage.storage_of("wait", journal), tiny)
    gone = subprocess.Popen(["true"])
    gone.wait()  # a worker of this machine that is gone, its heartbeat recent
    worker = {"host": socket.gethostname(), "boot_id": storage.boot_id(), "pid": gone.pid}
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    params = {"task": TASK, "variant": "ppo", "seed": 0}
    attrs = {"worker": worker, "heartbeat": time.time()}
    running = optuna.create_trial(state=TrialState.RUNNING, params=params, distributions=distributions, user_attrs=attrs)
    study.add_trial(running)
    assert storage.pending(study, tiny) == 0 and storage.running(study, tiny) == 1
    trained = []

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        trained.append(seed)
        keys = ("final_return", "cpu_seconds", "eval_cpu_seconds", "wall_seconds", "steps_per_cpu_second")
        return {"max_average_return": 1.0, **dict.fromkeys(keys, 1.0)}

    monkeypatch.setattr(workers, "train", train)
    workers.work(["wait"], journal)
    trials = study.get_trials()
    assert trained == [0] and [t.state for t in trials] == [TrialState.FAIL, TrialState.COMPLETE]
    assert trials[0].user_attrs["interrupted"] == "worker gone" and trials[1].system_attrs["retry_history"] == [0]


def test_the_report_names_the_runs_that_went_on_from_a_checkpoint_in_one_line(tmp_path):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1, 2, 3), 4000, 2000, 2)
    journal = str(tmp_path / "c.journal")
    study, _ = storage.open_study("resumed", storage.storage_of("resumed", journal), tiny)
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    for seed, resumed in ((0, 2000), (1, 0), (2, 4000)):
        study.add_trial(optuna.create_trial(state=TrialState.COMPLETE, value=1.0, distributions=distributions,
                                            params={"task": TASK, "variant": "ppo", "seed": seed},
                                            user_attrs={"resumed_from": resumed}))  # fmt: skip
    notes = results.collect(["resumed"], journal)[2]
    assert notes == [
        f"Went on from a checkpoint (task, variant, seed, at env step): {TASK} ppo 0 (2,000), {TASK} ppo 2 (4,000)"
    ]


def test_a_new_trial_leaves_its_grid_point_to_a_retried_one():
    def trial(number: int, state: TrialState, retried: bool = False) -> optuna.trial.FrozenTrial:
        attrs = {"retry_history": [0]} if retried else {}
        made = optuna.create_trial(state=state, value=1.0 if state == TrialState.COMPLETE else None, system_attrs=attrs)
        made.number = number
        return made

    new, retry = trial(5, TrialState.RUNNING), trial(4, TrialState.RUNNING, retried=True)
    assert workers._yields(new, retry) and not workers._yields(retry, new)  # whichever checks first
    assert workers._yields(new, trial(6, TrialState.WAITING, retried=True))  # the retry not started yet
    assert not workers._yields(retry, trial(6, TrialState.RUNNING))  # a later new one: the retry keeps the point
    assert workers._yields(trial(7, TrialState.RUNNING), new) and not workers._yields(new, trial(7, TrialState.RUNNING))
    assert workers._yields(retry, trial(9, TrialState.COMPLETE))  # the point is done
    assert not workers._yields(new, trial(1, TrialState.FAIL)) and not workers._yields(new, trial(2, TrialState.PRUNED))


def test_training_cpu_time_excludes_the_evaluations(monkeypatch):
    """Each evaluation burns 3 s of CPU: the training CPU time of the run and of its curve leaves it out, the
    evaluation time holds it (an update and a 2000-step rollout take about a second here)."""
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 4000, 2000, 2)
    evaluate = training.evaluate_policy

    def slow_evaluation(*args, **kwargs):
        start = time.process_time()
        while time.process_time() - start < 3.0:
            pass
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(training, "evaluate_policy", slow_evaluation)
    result = training.train(tiny, TASK, "ppo", 0)
    cpu = result["curve"]["cpu_s"]
    assert result["eval_cpu_seconds"] >= 6.0
    assert cpu[1] - cpu[0] < 3.0  # a rollout and an update between the evaluations, not the first evaluation
    assert 0 < result["cpu_seconds"] - cpu[1] < 3.0  # the last update after the last evaluation, not the evaluation
    assert result["arguments"]["max_grad_norm"] == "inf" and result["arguments"]["learning_rate"] == "0.0001"


def test_report_statistics_by_hand(monkeypatch):
    runs = {"A": {"ppo": [{"max_average_return": 100.0}, {"max_average_return": 200.0}],
                  "opr-e2e": [{"max_average_return": 300.0}, {"max_average_return": 400.0}]}}  # fmt: skip
    row = tables.table(runs, "ppo", paper=False)[2]
    assert row == "| A | 150 ± 25 (2) | 350 ± 25 (2) **2.33x** |"  # mean ± half the std over seeds, ratio of means
    run = {"curve": {"mean": [1.0, 5.0, 3.0, 9.0], "cpu_s": [1.0, 2.0, 3.0, 4.0]}}
    assert tables.best_so_far_at(run, 3.5) == 5.0 and np.isnan(tables.best_so_far_at(run, 0.5))

    # speed against the baseline's runs on the same machine: 50 against 100 there, not against 400 on another
    def timed(speed: float, boot: str) -> dict:
        return {"steps_per_cpu_second": speed, "steps_per_wall_second": speed, "cpu_seconds": 4.0, "curve": run["curve"],
                "worker": {"boot_id": boot}, "max_average_return": 9.0}  # fmt: skip

    rows = tables.speed({"A": {"ppo": [timed(100, "a"), timed(400, "b")], "opr-e2e": [timed(50, "a")]}}, "ppo")
    assert rows[0] == "| task | ppo | opr-e2e |" and rows[2] == "| A | 250 (250), 0 | 0.50x (0.50x), 1.00x, 0 |"

    # per env step the max average returns, 40 / 20; per CPU-second the best within PPO's 2 CPU-seconds, 30 / 10
    def scored(values: list[float], cpu: list[float]) -> dict:
        return {"max_average_return": max(values), "cpu_seconds": 2.0, "curve": {"mean": values, "cpu_s": cpu}}

    ppo, opr = [scored([10.0, 20.0], [1.0, 3.0])] * 2, [scored([30.0, 40.0], [1.5, 5.0])] * 2
    rows, normalized = tables.aggregates({"A": {"ppo": ppo, "opr-e2e": opr}}, "ppo")
    assert rows[2:] == ["| ppo | 1 | 2 | 1.00 [1.00, 1.00] | — | 1.00 [1.00, 1.00], — |",
                        "| opr-e2e | 1 | 2 | 2.00 [2.00, 2.00] | 1.00 | 3.00 [3.00, 3.00], 1.00 |"]  # fmt: skip
    assert normalized["opr-e2e"]["A"].tolist() == [2.0, 2.0]  # the profile's scores are per env step

    # the target: tasks above the baseline's mean, the IQM of [1.5, 1.5, 0.9, 0.9] (its middle half) and its CI
    def two_tasks(a: float, b: float) -> dict:
        return {"A": {"ppo": [scored([100.0], [1.0])] * 2, "opr-e2e": [scored([a], [1.0])] * 2},
                "B": {"ppo": [scored([100.0], [1.0])] * 2, "opr-e2e": [scored([b], [1.0])] * 2}}  # fmt: skip

    assert tables.target(two_tasks(150.0, 90.0), "ppo", {"ppo": 6, "opr-e2e": 4}) == [
        "- opr-e2e: above ppo on 1 of 2 tasks (below on B 0.90x), IQM 1.20 [1.20, 1.20]: missed by 4 task(s); "
        "provisional, runs to come: 2 of ppo"
    ]
    assert tables.target(two_tasks(110.0, 80.0), "ppo", {"opr-e2e": 6}) == [  # [1.1, 1.1, 0.8, 0.8]
        "- opr-e2e: above ppo on 1 of 2 tasks (below on B 0.80x), IQM 0.95 [0.95, 0.95]: missed by 4 task(s), "
        "0.200 of IQM, 0.050 of the lower bound; provisional, runs to come: 2 of opr-e2e"
    ]
    # within half a percent of the baseline's mean: a tie, not above
    assert tables.target(two_tasks(150.0, 100.4), "ppo", {})[0].startswith(
        "- opr-e2e: above ppo on 1 of 2 tasks (tied on B 1.00x), IQM 1.25"
    )
    three = {**two_tasks(150.0, 100.4), "C": two_tasks(90.0, 0.0)["A"]}
    assert "on 1 of 3 tasks (tied on B 1.00x; below on C 0.90x)" in tables.target(three, "ppo", {})[0]
    two = two_tasks(150.0, 102.0)  # [1.5, 1.5, 1.02, 1.02]: IQM 1.26, both tasks above
    assert tables.target(two, "ppo", {}) == ["- opr-e2e: above ppo on 2 of 2 tasks, IQM 1.26 [1.26, 1.26]: "
                                             "missed by 3 task(s)"]  # fmt: skip
    monkeypatch.setitem(tables.TARGET, "tasks", 2)
    assert tables.target(two, "ppo", {})[0].endswith("IQM 1.26 [1.26, 1.26]: met")
    # SAC's target: both tasks, IQM 1.1, no bound on the CI, and the median speed ratio (same machine) at least 0.7x
    sac = {task: {"sac": [{**r, "steps_per_cpu_second": 100.0} for r in bv["ppo"]],
                  "opr": [{**r, "steps_per_cpu_second": speed} for r, speed in zip(bv["opr-e2e"], (60.0, 90.0))]}
           for task, bv in two.items()}  # fmt: skip
    spec = tables.TARGETS["sac"]
    assert tables.target(sac, "sac", {}, spec) == [
        "- opr: above sac on 2 of 2 tasks, IQM 1.26 [1.26, 1.26], 0.75x sac's steps per CPU-second (median of 4 runs): met"
    ]
    sac["B"]["opr"][1]["steps_per_cpu_second"] = 60.0  # ratios 0.6, 0.9, 0.6, 0.6
    assert tables.target(sac, "sac", {}, spec)[0].endswith("0.60x sac's steps per CPU-second (median of 4 runs): "
                                                           "missed by 0.10x of speed")  # fmt: skip
    assert tables.target_wording(spec, "sac") == (
        "above sac's mean on at least 2 of its 2 tasks, IQM at least 1.1, at 0.7x sac's env steps per CPU-second or more"
    )
    two["A"]["opr-e2e+local-generalization"] = two["A"]["opr-e2e"]  # the diagnostic's runs: in the table only
    assert "opr-e2e+local-generalization" in tables.table(two, "ppo", paper=False)[0]
    assert [row.split(" |")[0] for row in tables.aggregates(two, "ppo")[0][2:]] == ["| ppo", "| opr-e2e"]
    two["B"]["opr-e2e-default-schedule"] = two["B"]["opr-e2e"]  # the target is the paper's OPR-E2E's alone
    assert tables.target(two, "ppo", {}) == ["- opr-e2e: above ppo on 2 of 2 tasks, IQM 1.26 [1.26, 1.26]: met"]
    assert tables.target(two, "opr-e2e", {}) == []  # nor against itself as the baseline
    # training signals: the mean over the last third of a run's iterations, then over runs; — where none is logged
    nan = float("nan")
    logged = {"train/explained_variance": [0.0, 0.0, 0.0, 0.0, 0.5, 0.7], "pevfa/value_chi_gradient": [nan] * 3 + [1, 2, 6]}
    other = {"train/explained_variance": [0.0] * 4 + [0.9, 0.9], "pevfa/value_chi_gradient": [nan] * 6}
    rows = tables.training_signals({"A": {"opr": [{"training_log": logged}, {"training_log": other}]}})
    assert rows[2] == "| A | opr | 2 | 0.75 | — | 4 | — | — |"  # (0.6 + 0.9) / 2; (2 + 6) / 2, the all-nan run apart
    # expected duration: the whole grid, a missing seed at its variant's mean time on the task; a complete grid says so
    grid = definitions.Campaign("sb3", ("A",), ("ppo",), (0, 1), 1000, eval_freq=1000)
    done = {"seed": 0, "cpu_seconds": 3000.0, "eval_cpu_seconds": 600.0, "wall_seconds": 3600.0, "eval_wall_seconds": 0.0}
    assert "about 2.0 CPU-hours in all, 0.5 wall-clock hours left on 2" in results.expected_duration(
        {"A": {"ppo": [done]}}, {}, [grid], workers=2
    )
    complete = {"A": {"ppo": [done, {**done, "seed": 1}]}}
    assert results.expected_duration(complete, {}, [grid], workers=2).startswith("Duration: 2.0 CPU-hours")
    # a variant not yet run on a task: another variant's time there, times the two variants' ratio where both ran
    two_variants = definitions.Campaign("sb3", ("A", "B"), ("ppo", "opr"), (0,), 1000, eval_freq=1000)
    slow = {**done, "cpu_seconds": 6600.0, "wall_seconds": 7200.0}  # twice ppo's time on A
    runs = {"A": {"ppo": [done], "opr": [slow]}, "B": {"ppo": [{**done, "cpu_seconds": 1200.0, "wall_seconds": 1800.0}]}}
    assert "about 4.5 CPU-hours in all, 1.0 wall-clock hours left on 1" in results.expected_duration(
        runs, {}, [two_variants], workers=1
    )  # 1 + 2 + 0.5 + 0.5 * 2 CPU-hours of training and evaluation; 0.5 * 2 wall-clock hours left on B
    running = {("B", "opr"): [{"steps": 500, "cpu_s": 1800.0, "wall_s": 1800.0, "seed": 0}]}  # B's run half done
    assert "about 4.5 CPU-hours in all, 0.5 wall-clock hours left on 1" in results.expected_duration(
        runs, running, [two_variants], workers=1
    )  # extrapolated from its progress: 3600 CPU-s and wall-s in all, 1800 of them left
    # a variant with no run yet: its protocol's other variants' mean on the task (never another protocol's)
    three = definitions.Campaign("sb3", ("A",), ("ppo", "opr", "spr"), (0,), 1000, eval_freq=1000)
    assert "about 4.5 CPU-hours in all, 1.5 wall-clock hours left on 1" in results.expected_duration(
        {"A": {"ppo": [done], "opr": [slow]}}, {}, [three], workers=1
    )  # spr at (1 + 2) / 2 CPU-hours, (1 + 2) / 2 wall-clock hours left
    assert results.scaled_time({("A", "paper:ppo"): np.ones(2)}, ("A", "authors:random")) is None
    nothing = results.expected_duration({}, {}, [three], workers=1)  # never "0.0 hours" for runs it cannot estimate
    assert nothing.startswith("Expected duration: not known yet") and "the 3 runs left" in nothing
    assert results.scaled_time({("A", "authors:ppo"): np.ones(2)}, ("A", "authors:random")).tolist() == [1.0, 1.0]
    x, y = {"A": np.array([1.0, 3.0])}, {"A": np.array([2.0, 3.0])}
    assert tables.probability_of_improvement(x, y) == 0.375  # pairs: 1>2 no, 1>3 no, 3>2 yes, 3=3 half
    # the baseline's spread widens the interval of the normalized IQM
    scores, base = {"A": np.array([2.0, 2.1, 1.9, 2.0])}, {"A": np.array([0.5, 1.5, 0.8, 1.2])}
    fixed = aggregate.stratified_bootstrap_ci(aggregate.normalized(scores, base))
    low, high = aggregate.normalized_bootstrap_ci(scores, base)
    assert high - low > 2 * (fixed[1] - fixed[0]) and low < 2.0 < high


def test_a_results_pages_table_and_summary_by_hand(monkeypatch):
    """Per task: the returns, the variant's ratios per step, at the baseline's CPU time and in speed, another
    protocol's per step and the paper's; the summary picks the target's variant, reads the storage once with its
    report and says what is provisional or left out."""

    made = {"final_return": 0.0, "eval_cpu_seconds": 0.0, "wall_seconds": 2.0, "eval_wall_seconds": 0.0, "seed": 0,
            "commit": "abc", "machine": "m", "versions": dict.fromkeys(("torch", "stable_baselines3", "gymnasium",
                                                                          "mujoco"), "1")}  # fmt: skip

    def run(best: list[float], cpu_s: list[float], cpu: float, speed: float) -> dict:
        curve = {"mean": best, "cpu_s": cpu_s, "steps": [1000] * len(best)}
        return {"max_average_return": max(best), "cpu_seconds": cpu, "steps_per_cpu_second": speed, **made,
                "steps_per_wall_second": speed**0.5, "curve": curve}  # fmt: skip

    # ppo's best within its own 2 CPU-seconds: 100 and 200 (mean 150); over its runs: 140 and 200 (mean 170)
    ppo = [run([100.0, 140.0], [1.0, 3.0], 2.0, 100.0), run([200.0], [1.0], 2.0, 100.0)]
    opr = [run([150.0, 340.0], [1.5, 4.0], 4.0, 50.0)] * 2  # 150 within ppo's 2 CPU-seconds, 340 by its end
    runs = {"X": {"ppo": ppo[:1]}, "Hopper-v5": {"ppo": ppo, "opr-e2e": opr}}
    other = {"Hopper-v5": {"ppo": ppo[:1], "opr-e2e": [run([50.0], [1.0], 2.0, 100.0)]}}  # 50 / 140 per step
    assert tables.compact(runs, "ppo", "opr-e2e", other, "that protocol") == [
        "| task | ppo | opr-e2e | per step | at ppo's CPU time | speed | that protocol, per step | the paper, per step |",
        "|---|---|---|---|---|---|---|---|",
        "| Hopper-v5 | 170 ± 15 (2) | 340 ± 0 (2) | 2.00x | 1.00x | 0.50x | 0.36x | 1.27x |",  # Table 1's order first
        "| X | 140 ± 0 (1) | — | — | — | — | — | — |",
    ]
    alone = tables.compact({"A": runs["Hopper-v5"]}, "ppo", "opr-e2e")  # no other protocol, no published value
    assert alone[2] == "| A | 170 ± 15 (2) | 340 ± 0 (2) | 2.00x | 1.00x | 0.50x |"
    runs["Hopper-v5"]["random"] = opr  # the target's variant, not the first in Table 1's order
    grid = definitions.Campaign("paper", ("Hopper-v5", "X"), ("ppo", "random", "opr-e2e"), (0, 1), 1000, eval_freq=1000)
    theirs = definitions.Campaign("paper", ("Hopper-v5",), ("ppo", "opr-e2e"), (0, 1), 1000, eval_freq=1000)
    reads = []

    def collect(names: list[str], storage: str | None) -> tuple:
        reads.append(names[0])
        return (runs, {}, [], [grid]) if names[0] == "c" else (other, {}, [], [theirs])

    monkeypatch.setattr(engine.report, "collect", collect)
    text = engine.report.summary(["c"], None, "ppo")
    assert text.startswith("7 of 12 runs complete, 1,000 env steps per run (provisional). Best evaluation")
    assert "| task | ppo | opr-e2e | per step |" in text and "| ppo | 2 | 3 |" in text and "| random | 1 | 2 |" in text
    assert text.rstrip().endswith("provisional, runs to come: 2 of opr-e2e, 1 of ppo")
    cache: dict = {}
    beside = engine.report.summary(["c"], None, "ppo", ["d"], cache)
    assert "| 0.36x | 1.27x |" in beside and "The paper protocol's column: 2 of 4 runs complete (provisional)." in beside
    engine.report.report(["c"], None, "ppo", 2, None, ["d"], cache)
    assert reads[-2:] == ["c", "d"]  # the report read nothing again
    sb3 = types.SimpleNamespace(**{**vars(grid), "protocol": "sb3", "grid": grid.grid})  # a protocol without a target
    runs["Y"] = {"ppo": [run([-5.0], [1.0], 2.0, 100.0)], "random": opr}
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [sb3]))
    text = engine.report.summary(["c"], None, "ppo")  # the first variant compared
    assert "| task | ppo | random | per step |" in text and "Target" not in text
    assert "| Y | -5 ± 0 (1) | 340 ± 0 (2) | — | — | 0.50x | — |" in text  # no ratio to a negative mean
    assert "Left out of the aggregates and the target: Y, where ppo's mean is not positive" in text
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: ({}, {}, [], [grid]))
    assert engine.report.summary(["c"], None, "ppo") == "0 of 12 runs complete, 1,000 env steps per run (provisional).\n"


def _one_evaluation_runs(**tasks: tuple[list[float], list[float]]) -> dict:
    """task -> (ppo's max average returns, opr-e2e's), one evaluation per run: the report's numbers at their
    boundaries (spread seeds, values on each threshold)."""

    def scored(value: float) -> dict:
        return {"max_average_return": value, "cpu_seconds": 2.0, "curve": {"mean": [value], "cpu_s": [1.0], "steps": [1]}}

    return {t: {"ppo": [scored(v) for v in base], "opr-e2e": [scored(v) for v in mine]} for t, (base, mine) in tasks.items()}


# --- aggregate.py: the bootstrap's confidence level, independent (not paired) draws, the profile's strict ">" ---------
def test_bootstrap_intervals_are_95_percent_percentiles_of_independent_draws():
    # three seeds 0, 1, 2: a replicate of all three draws 0 has P = 1/27 = 3.7 % (> 2.5 %, < 5 %), so the 95 % CI's
    # ends are the extremes 0 and 2 (mean of three; 3 runs trim none); a 90 % CI would be [1/3, 5/3]
    assert aggregate.stratified_bootstrap_ci({"A": np.array([0.0, 1.0, 2.0])}) == (0.0, 2.0)
    assert aggregate.normalized_bootstrap_ci({"A": np.array([0.0, 1.0, 2.0])}, {"A": np.ones(3)}) == (0.0, 2.0)
    # the baseline's seeds are drawn apart from the variant's: means 1 and 3 against 3 and 1 (P 1/16 each) give the
    # ratios 1/3 and 3; drawn with the same indices every ratio would be 1
    low, high = aggregate.normalized_bootstrap_ci({"A": np.array([1.0, 3.0])}, {"A": np.array([1.0, 3.0])})
    assert (low, high) == pytest.approx((1 / 3, 3.0))
    # the profile counts scores strictly above tau; its band's low end at tau 0.5 is 0 (P 1/27 that no draw is above)
    assert aggregate.performance_profile({"A": np.array([1.0, 2.0])}, np.array([1.0])).tolist() == [0.5]
    low, high = aggregate.profile_band({"A": np.array([0.0, 1.0, 2.0])}, np.array([0.5]))
    assert (low.tolist(), high.tolist()) == ([0.0], [1.0])


def test_probability_of_improvement_weighs_tasks_equally():
    # task A: 200 > 100 (1.0); task B: 50, 50, 50 < 100 (0.0): 0.5 over tasks, not 1 / 4 over the pooled pairs
    x, y = {"A": np.array([200.0]), "B": np.full(3, 50.0)}, {"A": np.array([100.0]), "B": np.array([100.0])}
    assert tables.probability_of_improvement(x, y) == 0.5


# --- tables.target: the verdict line's boundaries -------------------------------------------------------------------
def test_the_targets_tie_band_is_half_a_percent_both_sides_inclusive():
    # +0.5 % and -0.5 %: ties (inclusive); +0.8 %: above (a 1 % band would tie it); -1 %: below
    runs = _one_evaluation_runs(B=([100.0], [100.5]), C=([100.0], [99.5]), D=([100.0], [100.8]), E=([100.0], [99.0]))
    assert tables.target(runs, "ppo", {})[0].startswith(
        "- opr-e2e: above ppo on 1 of 4 tasks (tied on B 1.00x, C 0.99x; below on E 0.99x), IQM"
    )


def test_the_target_reads_the_iqm_and_the_mean_margin():
    # normalized [1, 1, 1, 5]: IQM 1.00 (the mean would be 2.00); the task's mean 200 is 2x ppo's (its median a tie)
    line = tables.target(_one_evaluation_runs(A=([100.0] * 4, [100.0, 100.0, 100.0, 500.0])), "ppo", {})[0]
    assert line.startswith("- opr-e2e: above ppo on 1 of 1 tasks, IQM 1.00 [")
    row = tables.aggregates(_one_evaluation_runs(A=([100.0] * 4, [100.0, 100.0, 100.0, 500.0])), "ppo")[0][3]
    assert row.startswith("| opr-e2e | 1 | 4 | 1.00 [")


def test_the_targets_ci_resamples_the_baseline_and_reads_low_then_high():
    # opr-e2e 100, 100 against ppo 50, 150: a replicate's ppo mean is 50, 100 or 150 (P 1/4, 1/2, 1/4), the ratio
    # 2, 1 or 0.67: the 95 % CI is [0.67, 2.00] (fixed at ppo's mean it would be [1.00, 1.00])
    runs = _one_evaluation_runs(A=([50.0, 150.0], [100.0, 100.0]))
    assert ", IQM 1.00 [0.67, 2.00]: missed by" in tables.target(runs, "ppo", {})[0]
    assert tables.aggregates(runs, "ppo")[0][3].startswith("| opr-e2e | 1 | 2 | 1.00 [0.67, 2.00] |")


def test_the_targets_bounds_are_met_at_equality_except_the_ci_s_lower_bound():
    # every ratio 1.5: IQM 1.5 [1.5, 1.5]; IQM "at least" 1.5 is met, a lower bound "above" 1.5 is not
    spec = {"variant": "opr-e2e", "tasks": 1, "of": "its 1 task", "iqm": 1.5, "low": 1.5, "speed": None}
    runs = _one_evaluation_runs(A=([100.0] * 2, [150.0] * 2))
    assert tables.target(runs, "ppo", {}, spec) == [
        "- opr-e2e: above ppo on 1 of 1 tasks, IQM 1.50 [1.50, 1.50]: missed by 0.000 of the lower bound"
    ]
    assert tables.target(runs, "ppo", {}, {**spec, "low": None})[0].endswith(": met")
    # Table 1's target at ratios of exactly 1.0 on 5 tasks: tied everywhere, 0.150 of IQM and 0.000 of the bound short
    same = _one_evaluation_runs(**{t: ([100.0] * 2, [100.0] * 2) for t in "ABCDE"})
    assert tables.target(same, "ppo", {})[0].endswith("missed by 5 task(s), 0.150 of IQM, 0.000 of the lower bound")
    # SAC's speed bound at exactly 0.7x (70 against 100 steps per CPU-second): met
    sac = {
        t: {
            "sac": [{**r, "steps_per_cpu_second": 100.0} for r in bv["ppo"]],
            "opr": [{**r, "steps_per_cpu_second": 70.0} for r in bv["opr-e2e"]],
        }
        for t, bv in runs.items()
    }
    sac["B"] = sac["A"]
    assert tables.target(sac, "sac", {}, tables.TARGETS["sac"])[0].endswith(
        "0.70x sac's steps per CPU-second (median of 4 runs): met"
    )


# --- the results page's per-task ratios (tables.compact's columns) ---------------------------------------------------
def test_ratios_at_the_baselines_cpu_time_per_step_and_speed_by_hand():
    def base(cpu: float, boot: str, speed: float = 100.0, eval_cpu: float = 0.0) -> dict:
        return {"cpu_seconds": cpu, "eval_cpu_seconds": eval_cpu, "steps_per_cpu_second": speed,
                "max_average_return": 100.0, "worker": {"boot_id": boot}}  # fmt: skip

    # ppo on machine a: 2 and 4 CPU-seconds of training (mean 3; its evaluations' 10 apart), on machine b: 12
    ppo = [base(2.0, "a", eval_cpu=10.0), base(4.0, "a", speed=400.0), base(12.0, "b")]
    run = {"curve": {"mean": [150.0, 300.0, 500.0], "cpu_s": [2.5, 3.5, 5.0]}, "steps_per_cpu_second": 100.0,
           "worker": {"boot_id": "a"}, "max_average_return": 500.0}  # fmt: skip
    # best within the mean of machine a's ppo training CPU (3 s): 150 (not 300 at the max, 500 at all machines' 6 s)
    assert tables.at_baseline_cpu(run, ppo) == 150.0
    # speed against machine a's ppo, 100, 100 and 400 steps per CPU-second: 100 / their mean 200 (not / median 100)
    ppo.insert(0, base(2.0, "a"))
    assert tables.speed_ratio(run, ppo, "steps_per_cpu_second") == 0.5
    # per env step: the variant's mean max average return over ppo's: (100 + 100 + 400) / 3 / 100
    mine = [{"max_average_return": v} for v in (100.0, 100.0, 400.0)]
    assert tables.per_step(mine, [{"max_average_return": 100.0}]) == 2.0
    # a baseline mean of exactly 0 is no base for a ratio
    zero = {"Z": {"ppo": [{"max_average_return": 0.0}], "opr": [{"max_average_return": 5.0}]}}
    assert tables.comparable(zero, "ppo", "opr") == []


def test_the_speed_tables_cpu_minutes_are_training_minutes():
    def timed(cpu: float) -> dict:
        return {"cpu_seconds": cpu, "eval_cpu_seconds": 600.0, "steps_per_cpu_second": 100.0,
                "steps_per_wall_second": 100.0, "max_average_return": 1.0,
                "curve": {"mean": [1.0], "cpu_s": [1.0]}}  # fmt: skip

    rows = tables.speed({"A": {"ppo": [timed(7200.0)], "opr": [timed(3600.0)]}}, "ppo")
    assert rows[2] == "| A | 100 (100), 120 | 1.00x (1.00x), 1.00x, 60 |"


def test_a_summarys_run_count_is_over_every_campaigns_grid(monkeypatch):
    # a diagnostic variant by name, and by its report label where campaigns mix protocols
    assert definitions.is_diagnostic("opr-e2e+local-generalization")
    assert definitions.is_diagnostic("authors:opr-e2e+local-generalization") and not definitions.is_diagnostic("authors:opr")

    def run(value: float) -> dict:
        return {"max_average_return": value, "cpu_seconds": 2.0, "steps_per_cpu_second": 1.0,
                "steps_per_wall_second": 1.0, "curve": {"mean": [value], "cpu_s": [1.0], "steps": [1000]}}  # fmt: skip

    first = definitions.Campaign("sb3", ("A",), ("ppo",), (0,), 1000, eval_freq=1000)
    second = definitions.Campaign("sb3", ("A",), ("opr",), (0, 1, 2), 1000, eval_freq=1000)
    runs = {"A": {"ppo": [run(100.0)], "opr": [run(200.0)]}}
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [first, second]))
    text = engine.report.summary(["one", "two"], None, "ppo")
    assert text.startswith("2 of 4 runs complete, 1,000 env steps per run (provisional).")
    complete = definitions.Campaign("sb3", ("A",), ("opr",), (0,), 1000, eval_freq=1000)
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [first, complete]))
    text = engine.report.summary(["one", "two"], None, "ppo")
    assert text.startswith("2 of 2 runs complete, 1,000 env steps per run. ") and "provisional" not in text
    # a diagnostic's runs counted apart from the grid's that the table shows
    diagnostic = definitions.Campaign("paper", ("A",), ("opr-e2e+local-generalization",), (0, 1), 1000, eval_freq=1000)
    runs["A"]["opr-e2e+local-generalization"] = [run(150.0)]
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [first, complete, diagnostic]))
    text = engine.report.summary(["one", "two", "three"], None, "ppo")
    head = "2 of 2 runs complete (and 1 of 2 runs of the local-generalization diagnostic), 1,000 env steps per run"
    assert text.startswith(head + " (provisional).")
    runs["A"]["opr-e2e+local-generalization"].append(run(150.0))
    assert engine.report.summary(["one", "two", "three"], None, "ppo").startswith(head.replace("1 of 2", "2 of 2") + ". ")


def test_aggregates_resample_within_tasks_and_leave_out_what_a_ratio_cannot_compare(monkeypatch):
    # stratified: each task keeps its two runs, so the IQM of [1, 1, 3, 3] never moves; pooled draws would move it
    low, high = aggregate.stratified_bootstrap_ci({"A": np.array([1.0, 1.0]), "B": np.array([3.0, 3.0])})
    assert (low, high) == (2.0, 2.0)

    def scored(value: float, cpu: float = 1.0) -> dict:
        return {"max_average_return": value, "cpu_seconds": 2.0, "curve": {"mean": [value], "cpu_s": [cpu], "steps": [1000]}}

    # a task where the baseline's mean is negative: -50 against -100 is better, a ratio 0.5 would read worse
    runs = {"A": {"ppo": [scored(100.0)] * 2, "opr-e2e": [scored(150.0)] * 2},
            "B": {"ppo": [scored(-100.0)] * 2, "opr-e2e": [scored(-50.0)] * 2}}  # fmt: skip
    assert tables.comparable(runs, "ppo", "opr-e2e") == ["A"]
    rows, _ = tables.aggregates(runs, "ppo")
    assert rows[3] == "| opr-e2e | 1 | 2 | 1.50 [1.50, 1.50] | 1.00 | 1.50 [1.50, 1.50], 1.00 |"
    assert tables.target(runs, "ppo", {})[0].startswith("- opr-e2e: above ppo on 1 of 1 tasks, IQM 1.50")
    # a run with no evaluation within the baseline's CPU time: no IQM at that time rather than a nan counted as a loss
    late = {"A": {"ppo": [scored(100.0)] * 2, "opr-e2e": [scored(150.0, cpu=3.0)] * 2}}
    assert tables.aggregates(late, "ppo")[0][3].endswith("| — (a run has no evaluation in that time), — |")
    # the report says which tasks it left out
    made = {"final_return": 0.0, "eval_cpu_seconds": 0.0, "wall_seconds": 2.0, "eval_wall_seconds": 0.0, "seed": 0,
            "steps_per_cpu_second": 1.0, "steps_per_wall_second": 1.0, "commit": "abc", "machine": "m",
            "versions": dict.fromkeys(("torch", "stable_baselines3", "gymnasium", "mujoco"), "1")}  # fmt: skip
    runs = {
        task: {("opr" if v == "opr-e2e" else v): [{**r, **made} for r in rs] for v, rs in bv.items()}
        for task, bv in runs.items()
    }
    grid = definitions.Campaign("sb3", ("A", "B"), ("ppo", "opr"), (0,), 1000, eval_freq=1000)
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [grid]))
    text = engine.report.report(["sign"], None, "ppo", 2, None)
    assert "- Left out of the aggregates and the target: B, where ppo's mean is not positive" in text
    assert "Speed: ppo's env steps per CPU-second (wall-clock beside; evaluations apart)" in text
    assert "Against the target" not in text  # protocol sb3 has none
    zoo = types.SimpleNamespace(**{**vars(grid), "protocol": "zoo", "grid": grid.grid})  # rl-zoo3 times evaluations in
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [zoo]))
    assert "(wall-clock beside; evaluations included)" in engine.report.report(["zoo"], None, "ppo", 2, None)
    sac = types.SimpleNamespace(**{**vars(grid), "protocol": "sac", "grid": grid.grid})  # a protocol with a target
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], [sac]))
    assert "Against the target for opr (above ppo's mean on at least 2 of its 2 tasks, IQM at least 1.1, at 0.7x" in (
        engine.report.report(["sac"], None, "ppo", 2, None)
    )
    assert "Against the target" not in engine.report.report(["sac"], None, "sac", 2, None)  # no run of the baseline
    # another protocol's campaigns beside: the ratios per task in both, the paper's, and its aggregates
    other = {"Hopper-v5": {"ppo": [{**scored(200.0), **made}], "opr": [{**scored(100.0), **made}] * 3},
             "A": {"ppo": [{**scored(50.0), **made}]}}  # fmt: skip
    runs["Hopper-v5"] = {"ppo": runs["A"]["ppo"], "opr": runs["A"]["opr"][:1]}
    assert tables.beside(runs, other, "ppo", ("this", "that")) == [
        "| task | opr: this / that / the paper |",
        "|---|---|",
        "| Hopper-v5 | 1.50x (1/2) / 0.50x (3/1) / — |",  # Table 1 has no "opr"
        "| A | 1.50x (2/2) / — / — |",
        "| B | — / — / — |",  # ppo's mean is negative: no ratio
    ]
    other["Hopper-v5"]["opr-e2e"] = other["Hopper-v5"].pop("opr")
    runs["Hopper-v5"]["opr-e2e"] = runs["Hopper-v5"].pop("opr")
    assert tables.beside(runs, other, "ppo", ("this", "that"))[2] == "| Hopper-v5 | 1.50x (1/2) / 0.50x (3/1) / 1.27x |"
    assert tables.beside(runs, {"A": {"ppo": other["A"]["ppo"]}}, "ppo", ("this", "that")) == [
        "No variant but ppo in both protocols' runs."
    ]
    authors = types.SimpleNamespace(**{**vars(grid), "protocol": "authors", "grid": grid.grid})
    protocols = {"a": [authors], "b": [grid]}
    monkeypatch.setattr(engine.report, "collect", lambda names, storage: (runs, {}, [], protocols[names[0]]))
    text = engine.report.report(["a"], None, "ppo", 2, None, ["b"])
    assert "Beside campaigns b (sb3 protocol): each variant's ratio to ppo's mean max average return" in text
    assert "in the authors' protocol, the sb3 protocol and the paper's Table 1:" in text
    assert "Over tasks in the sb3 protocol:" in text
    assert "ppo in both protocols: its best evaluation within 1,000 env steps" in text
    # the baseline's best evaluation by the shorter budget and over the whole run, in both protocols
    curve = {"steps": [500, 1000, 2000], "mean": [10.0, 30.0, 50.0]}
    mine = {"T": {"ppo": [{"curve": curve, "max_average_return": 50.0, "cpu_seconds": 120.0}] * 2}}
    theirs = {"T": {"ppo": [{"curve": {**curve, "mean": [40.0, 20.0, 0.0]}, "max_average_return": 40.0,
                             "cpu_seconds": 60.0}]}, "U": {}}  # fmt: skip
    assert tables.baseline_beside(mine, theirs, "ppo", ("this", "that"), 1000)[2:] == [
        "| T | 30 ± 0 (2) | 50 ± 0 (2), 2 CPU-min | 40 ± 0 (1) | 40 ± 0 (1), 1 CPU-min |",
        "| U | — | — | — | — |",
    ]


def test_the_baselines_curves_in_two_protocols(tmp_path):
    """Curves are the runs' mean (± half a std) over their common length, per env step and per CPU minute; the figure
    of the baseline in two protocols has a column per task both ran."""

    def run(means: list[float], cpu: list[float]) -> dict:
        return {"curve": {"steps": [1000, 2000, 3000][: len(means)], "mean": means, "cpu_s": cpu}}

    curve = figures.mean_curve([run([1.0, 3.0, 5.0], [60.0, 120.0, 180.0]), run([3.0, 5.0], [120.0, 240.0])])
    np.testing.assert_allclose(curve["steps"], [1000, 2000])
    np.testing.assert_allclose(curve["cpu_minutes"], [1.5, 3.0])
    np.testing.assert_allclose(curve["mean"], [2.0, 4.0])
    np.testing.assert_allclose(curve["half_std"], [0.5, 0.5])
    mine = {"A": {"ppo": [run([1.0, 2.0], [1.0, 2.0])]}, "B": {"ppo": [run([1.0], [1.0])]}}
    theirs = {"A": {"ppo": [run([2.0, 3.0], [1.0, 2.0])]}}
    figures.plot_beside(mine, theirs, "ppo", ("this", "that"), tmp_path / "beside.png")
    assert (tmp_path / "beside.png").stat().st_size > 10_000
    figures.plot_beside(mine, {"C": theirs["A"]}, "ppo", ("this", "that"), tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()  # no task that both ran: no figure


def test_local_generalization_diagnostic_in_a_trial_and_the_report():
    tiny = definitions.Campaign("paper", (TASK,), ("opr-e2e+local-generalization",), (0,), 6000, 2000, 2)
    series = training.train(tiny, TASK, "opr-e2e+local-generalization", 0)["local_generalization"]
    assert series["timesteps"] == [2000.0, 4000.0, 6000.0]  # every iteration, the last one at the end of training
    assert all(len(series[key]) == 3 and min(series[key]) > 0 for key in ("pevfa_before", "vfa_before", "pevfa_after"))
    assert series["vfa_after"] != series["vfa_before"]  # the conventional critic trains beside the run
    by_hand = {"pevfa_before": [1.0, 4.0, 3.0, np.nan], "vfa_before": [2.0, 2.0, 1.0, 1.0],
               "pevfa_after": [1.0, 1.0, 1.0, 1.0], "vfa_after": [3.0, 1.0, 2.0, 1.0]}  # fmt: skip
    run = {"local_generalization": by_hand, "seed": 3, "max_average_return": 99.6}
    rows = tables.local_generalization({"A": {"x": [run], "ppo": [{}]}})
    # the iteration with a NaN left out; the run's ratios before: 0.5, 2 and 3
    assert rows[2:] == ["| A | x | 1 | 3 | 2.67 / 1.67 (2.00) | 33% | 1 / 2 | 3: 100 (2.00) |"]
    # over training: the geometric mean over runs of PeVFA's error / the conventional critic's, smoothed over 3
    other = {**by_hand, "pevfa_before": [4.0, 1.0, 3.0, 2.0], "timesteps": [1.0, 2.0, 3.0, 4.0]}
    curves = figures.local_generalization_curves([{**by_hand, "timesteps": [1.0, 2.0, 3.0, 4.0]}, other], 3)
    # per iteration: sqrt(0.5 * 2), sqrt(2 * 0.5), sqrt(3 * 3), 2 (the NaN left out)
    np.testing.assert_allclose(curves["before"], [1.0, np.exp(np.log(3) / 3), np.exp(np.log(6) / 3), 6**0.5])
    np.testing.assert_allclose(curves["after"][0], (1 / 3) ** 0.5)  # mean of log(1/3) and log(1), iterations 1-2
    assert curves["steps"].tolist() == [1.0, 2.0, 3.0, 4.0]
    np.testing.assert_allclose(figures.local_generalization_curves([other], 2)["before"][1], 1.0)  # 2 and 0.5
    # iterations of whole episodes, of varying size: on a grid of env steps every median iteration size (2000), each
    # run's log-ratio interpolated between its iterations, to the end of the shorter run (the longer run's 9000 left out)
    ones = [1.0] * 5
    short_first = {"timesteps": [500.0, 1000.0, 3000.0, 5000.0, 7000.0], "pevfa_before": [2.0, 0.5, 4.0, 1.0, 1.0],
                   "vfa_before": ones, "pevfa_after": ones, "vfa_after": ones}  # fmt: skip
    even = {"timesteps": [2000.0, 4000.0, 6000.0, 7500.0, 9000.0], "pevfa_before": [1.0, 1.0, 4.0, 0.25, 8.0],
            "vfa_before": ones, "pevfa_after": ones, "vfa_after": ones}  # fmt: skip
    curves = figures.local_generalization_curves([short_first, even], 1)
    np.testing.assert_allclose(curves["steps"], [2000.0, 4000.0, 6000.0])
    # the first run at 2000: halfway from 0.5 to 4 in logs (2 ** 0.5); at 4000: halfway from 4 to 1 (2); at 6000: 1
    np.testing.assert_allclose(curves["before"], [(2**0.5 * 1.0) ** 0.5, (2.0 * 1.0) ** 0.5, (1.0 * 4.0) ** 0.5])
    # off-policy runs by snapshot: a resumed one lacks windows 1 and 2, and its window 3 goes with window 3
    full = {
        **by_hand,
        "pevfa_before": [1.0, 2.0, 4.0, 8.0],
        "policy_id": [0.0, 1.0, 2.0, 3.0],
        "timesteps": [1.0, 2.0, 3.0, 4.0],
    }
    resumed = {key: [values[0], values[3]] for key, values in full.items()} | {"pevfa_before": [4.0, 2.0]}
    curves = figures.local_generalization_curves([resumed, full], 1)
    assert curves["steps"].tolist() == [1.0, 2.0, 3.0, 4.0]
    np.testing.assert_allclose(curves["before"], [1.0, 1.0, 4.0, 4.0])  # ratios: (0.5 * 2) ** 0.5, 1, 4, (8 * 2) ** 0.5
    # the longer off-policy run's snapshot 4 is past the shorter one's end: left out
    longer = {key: [*values, values[-1]] for key, values in full.items()} | {"policy_id": [0.0, 1.0, 2.0, 3.0, 4.0]}
    assert len(figures.local_generalization_curves([resumed, longer], 1)["steps"]) == 4
    # an unscored iteration between two scored ones: interpolated over (log 1 and log 4 give 2), not a gap
    gap = {"timesteps": [1.0, 2.0, 3.0], "pevfa_before": [1.0, np.nan, 4.0], "vfa_before": [1.0] * 3,
           "pevfa_after": [1.0] * 3, "vfa_after": [1.0] * 3}  # fmt: skip
    np.testing.assert_allclose(figures.local_generalization_curves([gap], 1)["before"], [1.0, 2.0, 4.0])
    # a run that went on from a checkpoint went on with its conventional critic: in the diagnostic; one without a
    # scored iteration is not
    resumed = {"local_generalization": {**other, "pevfa_before": [4.0, 1.0, 3.0, 0.5]}, "resumed_from": 2000,
               "seed": 1, "max_average_return": 250.0}  # fmt: skip
    empty = {"local_generalization": {}, "seed": 0}
    rows = tables.local_generalization({"A": {"x": [run, resumed, empty]}})
    # 16.5/7, 11/7; median of the 7 ratios 0.5, 2, 3, 2, 0.5, 3, 0.5; 3 of 7; 13/7; the resumed run's: 0.5, 0.5, 2, 3
    assert rows[2:] == ["| A | x | 2 | 7 | 2.36 / 1.57 (2.00) | 43% | 1 / 1.86 | 1: 250 (1.25), 3: 100 (2.00) |"]


def test_a_stopped_trial_goes_on_from_its_checkpoint(tmp_path, monkeypatch):
    tiny = definitions.Campaign("paper", (TASK,), ("opr-e2e",), (0,), 8000, 2000, 1)
    folder = tmp_path / "checkpoint"
    evaluate = training.evaluate_policy

    def stopped_at_6000(model, *args, **kwargs):
        if model.num_timesteps == 6000 and not (folder / "stopped").exists():
            (folder / "stopped").touch()
            start = time.process_time()
            while time.process_time() - start < 2.0:  # two seconds of CPU after the checkpoint, lost with the worker
                pass
            raise KeyboardInterrupt  # the worker ends mid-rollout
        return evaluate(model, *args, **kwargs)

    monkeypatch.setattr(training, "evaluate_policy", stopped_at_6000)
    start = time.process_time()
    with pytest.raises(KeyboardInterrupt):
        training.train(tiny, TASK, "opr-e2e", 0, checkpoint=folder, checkpoint_freq=4000)
    first_cpu = time.process_time() - start
    state = json.loads((folder / "state.json").read_text())
    assert (
        state["timesteps"] == 4000 and state["curve"]["steps"] == [2000, 4000] and state["n_policies"] == 3
    )  # the third recorded as its rollout starts
    start = time.process_time()
    result = training.train(tiny, TASK, "opr-e2e", 0, checkpoint=folder, checkpoint_freq=4000)
    resumed_cpu = time.process_time() - start
    counted = result["cpu_seconds"] + result["eval_cpu_seconds"]  # without the segment lost after the checkpoint
    assert state["cpu"] + state["eval_cpu"] < counted <= first_cpu - 2.0 + resumed_cpu
    assert result["resumed_from"] == 4000 and result["timesteps"] == 8000 and not folder.exists()
    assert result["curve"]["steps"] == [2000, 4000, 6000, 8000] and result["curve"]["mean"][:2] == state["curve"]["mean"]
    cpu = result["curve"]["cpu_s"]
    assert cpu == sorted(cpu) and cpu[1] == state["curve"]["cpu_s"][1] and cpu[-1] < result["cpu_seconds"]
    assert result["cpu_seconds"] > state["cpu"] and result["eval_cpu_seconds"] > state["eval_cpu"]


@pytest.mark.parametrize("protocol, variant, stop_at", [("paper", "opr-e2e", 6000), ("sac", "opr", 1500)])
def test_a_stop_saves_a_checkpoint_at_the_next_iteration_boundary_and_the_run_goes_on_from_it(
    tmp_path, monkeypatch, fresh_stop, protocol, variant, stop_at
):
    """SIGTERM while the worker evaluates at ``stop_at``: the training goes on to its next iteration boundary (the next
    rollout's start: after PPO's update of 2000 steps, after SAC's gradient step), saves a checkpoint there and stops;
    the next run goes on from that moment, not from the last periodic checkpoint (none here)."""
    if protocol == "sac":
        use_a_tiny_sac(monkeypatch, learning_starts=900)
        tiny = definitions.Campaign("sac", (TASK,), ("opr",), (0,), 2000, 500, 2)
    else:
        tiny = definitions.Campaign("paper", (TASK,), ("opr-e2e",), (0,), 8000, 2000, 1)
    signal.signal(signal.SIGTERM, workers._stop)
    evaluate, folder = training.evaluate_policy, tmp_path / "checkpoint"

    def signalled(model, *args, **kwargs):
        if model.num_timesteps == stop_at and not fresh_stop.asked:
            os.kill(os.getpid(), signal.SIGTERM)
        return evaluate(model, *args, **kwargs)

    monkeypatch.setattr(training, "evaluate_policy", signalled)
    with pytest.raises(KeyboardInterrupt):
        training.train(tiny, TASK, variant, 0, checkpoint=folder, checkpoint_freq=100_000)
    state = json.loads((folder / "state.json").read_text())
    assert state["timesteps"] == stop_at and state["curve"]["steps"][-1] == stop_at
    if protocol == "sac":  # with every transition so far
        model, _ = training.load_checkpoint(folder, protocol, variant, make_vec_env(TASK))
        assert model.replay_buffer.size() == stop_at
    fresh_stop.asked = False  # the next run's worker
    result = training.train(tiny, TASK, variant, 0, checkpoint=folder, checkpoint_freq=100_000)
    assert result["resumed_from"] == stop_at and result["timesteps"] == tiny.timesteps and not folder.exists()
    assert result["curve"]["steps"] == list(range(tiny.eval_freq, tiny.timesteps + 1, tiny.eval_freq))
    assert result["curve"]["mean"][: len(state["curve"]["mean"])] == state["curve"]["mean"]


def test_a_stop_asked_as_a_training_ends_completes_its_trial_and_stops_the_worker(tmp_path, monkeypatch, fresh_stop):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1), 4000, 2000, 2)
    journal = str(tmp_path / "end.journal")
    study, _ = storage.open_study("end", storage.storage_of("end", journal), tiny)

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        workers._stop()  # SIGTERM as the training ends (its last iteration, or after it): the run is stored first
        keys = ("final_return", "cpu_seconds", "eval_cpu_seconds", "wall_seconds", "steps_per_cpu_second")
        return {"max_average_return": 1.0, **dict.fromkeys(keys, 1.0)}

    monkeypatch.setattr(workers, "train", train)
    with pytest.raises(KeyboardInterrupt):
        workers.work_on("end", study, tiny)
    (trial,) = study.get_trials()
    assert trial.state == TrialState.COMPLETE and storage.pending(study, tiny) == 1


def test_a_trial_says_whether_it_goes_on_from_the_checkpoint_an_earlier_trial_saved(tmp_path, monkeypatch, capsys,
                                                                                     fresh_stop):  # fmt: skip
    """A stopped trial keeps where its checkpoint is (the status shows it); the next trial of the grid point says in the
    log that it goes on from a checkpoint, or, on a machine without the one saved last, that the run starts over."""
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 8000, 2000, 1)
    journal = str(tmp_path / "moved.journal")
    study, _ = storage.open_study("moved", storage.storage_of("moved", journal), tiny)
    folder, host = tiny.checkpoint_folder("moved", (TASK, "ppo", 0)), socket.gethostname()
    evaluate, stop_at = training.evaluate_policy, [4000, 2000, 2000]

    def stopped(model, *args, **kwargs):
        if stop_at and model.num_timesteps == stop_at[0]:
            stop_at.pop(0)
            workers._stop()  # SIGTERM during the evaluation: a checkpoint as the next rollout starts
        return evaluate(model, *args, **kwargs)

    def next_trial() -> str:
        fresh_stop.asked = False  # the next run's worker
        with contextlib.suppress(KeyboardInterrupt):
            workers.work_on("moved", study, tiny)
        storage.recover(study, tiny)  # as the next run does: a stopped point enqueued again
        return capsys.readouterr().out

    monkeypatch.setattr(training, "evaluate_policy", stopped)
    monkeypatch.setattr(workers, "train", functools.partial(training.train, checkpoint_freq=4000))
    assert "checkpoint" not in next_trial()  # none before
    assert study.trials[0].user_attrs["checkpoint"] == {"steps": 4000, "host": host}
    assert results.trial_outcome(study.trials[0]) == (
        f" (interrupted: stopped; checkpoint at 4,000 env steps on {host}; "
        f"last evaluation at 4,000 env steps, {study.trials[0].user_attrs['progress']['cpu_s'] / 60:.1f} CPU-min)"
    )
    shutil.move(folder, tmp_path / "elsewhere")  # another machine, or the cache cleared
    assert next_trial().splitlines()[0] == (
        f"moved #1 {TASK} ppo seed 0: trial #0 saved a checkpoint at 4,000 env steps on {host}; "
        f"none to go on from in {folder}: the run starts over"
    )
    assert study.trials[1].user_attrs["checkpoint"] == {"steps": 2000, "host": host}  # its own
    shutil.rmtree(folder)
    assert next_trial().splitlines()[0] == (
        f"moved #2 {TASK} ppo seed 0: trial #1 saved a checkpoint at 2,000 env steps on {host}; "
        f"none to go on from in {folder}: the run starts over"
    )  # the last one saved
    assert next_trial().splitlines()[0] == f"moved #3 {TASK} ppo seed 0: goes on from its checkpoint at 2,000 env steps"
    complete = study.trials[3]  # after a checkpoint at 4,000 env steps
    assert complete.state == TrialState.COMPLETE and complete.user_attrs["resumed_from"] == 2000
    assert complete.user_attrs["checkpoint"] is None and not folder.exists()


def test_a_retry_that_copied_its_trials_attributes_claims_no_checkpoint_of_its_own(tmp_path, monkeypatch):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 4000, 2000, 2)
    study, _ = storage.open_study("copied", storage.storage_of("copied", str(tmp_path / "copied.journal")), tiny)
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    study.add_trial(optuna.create_trial(  # as Optuna's heartbeat enqueues a dead worker's trial on a database
        state=TrialState.WAITING, params={"task": TASK, "variant": "ppo", "seed": 0}, distributions=distributions,
        user_attrs={"checkpoint": {"steps": 2000, "host": "gone"}}, system_attrs={"failed_trial": 0, "retry_history": [0]},
    ))  # fmt: skip

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(workers, "train", stopped)
    with pytest.raises(KeyboardInterrupt):
        study.optimize(workers.objective(tiny), n_trials=1)
    assert study.trials[0].user_attrs["checkpoint"] is None and results.trial_outcome(study.trials[0]) == (
        " (interrupted: stopped)"
    )


def _refused(main, capsys, *args: str) -> str:
    """The usage error a command line ends with (no traceback)."""
    with pytest.raises(SystemExit) as stopped:
        main(list(args))
    assert stopped.value.code == 2
    return capsys.readouterr().err.splitlines()[-1]


def test_a_users_mistakes_are_usage_errors_that_store_nothing(tmp_path, capsys):
    journal = str(tmp_path / "mine.journal")
    define = ["run", "--campaign", "mine", "--storage", journal, "--protocol", "sb3", "--variants", "ppo"]
    campaign = functools.partial(_refused, commands.campaign_main, capsys)
    twice = campaign(*define, "--tasks", TASK, "--seeds", "0", "0", "--timesteps", "4000", "--eval-freq", "2000")
    assert twice.endswith("seeds [0] given twice")
    stored = definitions.Campaign("sac", (TASK,), ("sac",), (0,), 3000, 1000, 2)  # read as stored, refused as new
    with pytest.raises(ValueError, match="trains from step 10,000 on"):
        stored.check_new()
    assert "eval_freq at most timesteps" in campaign(*define, "--tasks", TASK, "--seeds", "0", "--timesteps", "4000")
    typo = campaign(*define, "--tasks", "InvertedPendulm-v5", "--seeds", "0", "--timesteps", "4000", "--eval-freq", "2000")
    assert "cannot be trained here: InvertedPendulm-v5: NameNotFound" in typo
    sac = [*define[:-4], "--protocol", "sac", "--variants", "sac", "--seeds", "0", "--eval-freq", "5000"]
    assert "trains from step 10,000 on" in campaign(*sac, "--tasks", TASK, "--timesteps", "10000")
    box = campaign(*sac, "--tasks", "CartPole-v1", "--timesteps", "20000")
    assert "protocol 'sac' needs a Box action space, the task's is Discrete(2)" in box
    assert "No campaign 'mine' in " in campaign("status", "--campaign", "mine", "--storage", journal)
    assert "--retry-raised is an option of run" in campaign("status", "--campaign", "table1", "--retry-raised")
    assert "--fill goes with --until (a deadline)" in campaign("run", "--campaign", "table1", "--fill")
    alone = campaign("run", "--campaign", "mine", "--storage", journal, "--eval-freq", "5")
    assert "belong to a new campaign's definition" in alone
    assert not (tmp_path / "mine.journal").exists()  # none of these stored a definition
    tiny = definitions.Campaign("sb3", (TASK,), ("ppo",), (0,), 4000, 2000, 2)
    storage.open_study("mine", storage.storage_of("mine", journal), tiny)
    again = campaign(*define, "--tasks", TASK, "--seeds", "0", "1", "--timesteps", "4000", "--eval-freq", "2000",
                     "--eval-episodes", "2")  # fmt: skip
    assert "Campaign 'mine' was started with seeds [0] (given: [0, 1]): a campaign's definition never changes" in again
    report = functools.partial(_refused, commands.campaign_report_main, capsys)
    assert report("--campaign", "mine", "--storage", journal, "--baseline", "PPO").endswith(
        "--baseline 'PPO' is none of these campaigns' variants: ['ppo']"
    )
    commands.campaign_report_main(["--campaign", "mine", "--storage", journal, "--out", str(tmp_path / "new" / "out")])
    assert (tmp_path / "new" / "out" / "report.md").read_text().startswith("Campaigns mine: 0 of 1 runs complete.")


def test_status_without_a_campaign_lists_every_campaign_with_its_progress(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(storage, "CAMPAIGN_DIR", tmp_path)  # the repository's journal files: one of a new campaign
    tiny = definitions.Campaign("sb3", (TASK,), ("ppo", "opr"), (0, 1), 4000, 2000, 2)
    study = storage.open_study("mine", storage.storage_of("mine"), tiny)[0]
    distributions = {name: CategoricalDistribution(list(getattr(tiny, name + "s"))) for name in ("task", "variant", "seed")}
    for state, seed in ((TrialState.COMPLETE, 0), (TrialState.PRUNED, 0), (TrialState.RUNNING, 1), (TrialState.FAIL, 0)):
        study.add_trial(optuna.create_trial(state=state, value=1.0 if state == TrialState.COMPLETE else None,
                                            params={"task": TASK, "variant": "ppo" if seed else "opr", "seed": seed},
                                            distributions=distributions))  # fmt: skip
    commands.campaign_main(["status"])
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == [*definitions.CAMPAIGNS, "mine"]
    assert lines[-1] == f"{'mine':38s} sb3     1 tasks x 2 variants x 2 seeds, 4,000 steps: 1/4 complete, 1 running"
    assert lines[0] == f"{'table1':38s} paper   6 tasks x 2 variants x 5 seeds, 1,000,000 steps: 0/60 complete"
    assert [path.name for path in tmp_path.iterdir()] == ["mine.journal"]  # none made for the campaigns not started
    for command in ("run", "work"):
        assert f"{command} needs --campaign (campaign.py status without it lists" in _refused(
            commands.campaign_main, capsys, command
        )
    assert "status needs --campaign" in _refused(commands.campaign_main, capsys, "status", *_definition("ppo"))


def test_a_stored_definition_given_again_is_read_as_it_was(tmp_path, capsys):
    journal = str(tmp_path / "old.journal")
    old = definitions.Campaign("sac", (TASK,), ("sac",), (0,), 5000, 1000, 2)  # fewer steps than SAC's learning_starts
    storage.open_study("old", storage.storage_of("old", journal), old)
    commands.campaign_main(["status", "--campaign", "old", "--storage", journal, "--protocol", "sac", "--tasks", TASK,
                            "--variants", "sac", "--seeds", "0", "--timesteps", "5000", "--eval-freq", "1000",
                            "--eval-episodes", "2"])  # fmt: skip
    assert "old: 0/1 grid points complete" in capsys.readouterr().out


def test_a_kept_exception_is_one_line_with_its_start_and_end():
    text = workers.error_text(RuntimeError("run: FAILED (see err)\n" + "x" * 1000 + "\nValueError: the last line"))
    assert len(text) == workers.ERROR_LENGTH and "\n" not in text
    assert text.startswith("RuntimeError: run: FAILED (see err) xxx") and text.endswith("xxx ValueError: the last line")
    assert workers.error_text(ValueError("short")) == "ValueError: short"


def test_a_stopped_worker_ignores_a_second_signal_while_it_marks_its_trial():
    """A second SIGINT or SIGTERM, or the deadline's alarm, cannot cut the marking short."""
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)
    saved = [signal.getsignal(stop) for stop in stops]
    try:
        signal.signal(signal.SIGALRM, workers._stop)
        signal.setitimer(signal.ITIMER_REAL, 0.2)  # a deadline due while the trial is marked
        with pytest.raises(KeyboardInterrupt):
            workers._stop()
        assert [signal.getsignal(stop) for stop in stops] == [workers._ignore] * 3
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
        for stop in stops:  # handled by a no-op: nothing raised, the process lives on
            os.kill(os.getpid(), stop)
        time.sleep(0.3)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for stop, handler in zip(stops, saved):
            signal.signal(stop, handler)


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_run_stops_its_worker_which_marks_its_trial_stopped(tmp_path, stop):
    """Ctrl-C pressed twice (SIGINT to the terminal's process group), or ``kill -TERM`` of the processes twice: the
    worker marks its trial, exits with ``STOPPED``, and ``run`` says the same command goes on."""
    journal = tmp_path / "stop.journal"
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), "run", "--campaign", "stop", "--storage",
               str(journal), "--workers", "1", *_definition("ppo", timesteps=8000)]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline, running = time.monotonic() + 300, None
    while running is None and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.5)
        if journal.exists():
            trials = _study("stop", journal).get_trials()
            running = next((t for t in trials if t.state == TrialState.RUNNING and "progress" in t.user_attrs), None)
    if running is None:
        os.killpg(process.pid, signal.SIGKILL)
        pytest.fail(f"no trial reached its first evaluation: {process.communicate()[1][-3000:]}")
    for _ in range(2):
        os.killpg(process.pid, stop)
        time.sleep(0.2)
    try:
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 1 and "stop: stopped; the same run command goes on" in stderr, stderr[-2000:]
    assert "Traceback" not in stderr
    assert "stopping: the workers save a checkpoint and mark their trials (at most 120 s)" in stderr
    study, campaign = storage.open_study("stop", storage.storage_of("stop", str(journal)))
    trial = study.trials[running.number]
    assert trial.state == TrialState.FAIL and trial.user_attrs["interrupted"] == "stopped"
    saved = json.loads((campaign.checkpoint_folder("stop", storage.grid_point(trial)) / "state.json").read_text())
    assert saved["timesteps"] >= running.user_attrs["progress"]["steps"]  # where the stop found it, not a restart


def test_a_worker_that_does_not_stop_within_the_grace_is_killed(monkeypatch):
    code = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print(flush=True); time.sleep(60)"
    stuck = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    quits = subprocess.Popen([sys.executable, "-c", "import time; print(flush=True); time.sleep(60)"], stdout=subprocess.PIPE)
    for process in (stuck, quits):
        process.stdout.readline()  # its handler is set
    monkeypatch.setattr(workers, "STOP_GRACE", 2.0)
    saved = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        start = time.monotonic()
        workers.stop_workers([stuck, quits])
        assert signal.getsignal(signal.SIGINT) == signal.getsignal(signal.SIGTERM) == signal.SIG_IGN  # run exits next
    finally:
        signal.signal(signal.SIGINT, saved[0])
        signal.signal(signal.SIGTERM, saved[1])
    assert quits.wait(1) == -signal.SIGTERM and stuck.wait(1) == -signal.SIGKILL and 2.0 <= time.monotonic() - start < 5


def test_runs_wait_for_its_workers_ends_at_one_more_exit_and_no_later():
    """``run`` ends as its last worker does, not at its next reading of the progress (every 10 s); a worker that has
    already exited does not make it read the progress again and again."""

    def exiting_after(seconds: float) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-c", f"import time; time.sleep({seconds})"])

    done, later = exiting_after(0), exiting_after(5)
    done.wait()
    start = time.monotonic()
    workers.wait_any([done, later], 0.5)  # the exited one does not end the wait
    assert later.poll() is None and 0.5 <= time.monotonic() - start < 3
    workers.wait_any([done, later], 60)  # the other one's exit does
    assert later.poll() == 0 and time.monotonic() - start < 9  # not at a next reading of the progress (10 s)


@pytest.mark.parametrize("n_seeds", [80, 1000])  # its output within a buffer's flush at exit (8 KiB), and beyond a pipe's
def test_status_read_through_head_ends_quietly(tmp_path, n_seeds):
    seeds = [str(seed) for seed in range(n_seeds)]
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), "status", "--campaign", "piped", "--storage",
               str(tmp_path / "p.journal"), *_definition("ppo", "opr-e2e", seeds=seeds)]  # fmt: skip
    env = {name: value for name, value in os.environ.items() if name != "PYTHONUNBUFFERED"}  # stdout buffered
    status = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    assert status.stdout.readline().startswith(f"piped: 0/{2 * n_seeds} grid points complete".encode())
    status.stdout.close()  # as head does after its lines
    assert status.wait(timeout=300) == 0 and status.stderr.read() == b""


def test_a_stopped_worker_exits_quietly_and_a_failed_grid_point_is_named(tmp_path, monkeypatch):
    def stopped(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(workers, "work_on_all", stopped)
    saved = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(SystemExit) as exit_status:
            workers.work(["mine"], None)
        # ignored by the OS from here: Python's exit puts the default action back where a Python handler is set
        assert signal.getsignal(signal.SIGINT) == signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, saved[0])
        signal.signal(signal.SIGTERM, saved[1])
    assert exit_status.value.code == workers.STOPPED == 130
    record = logging.LogRecord("optuna", logging.WARNING, "", 0, "Trial 0 failed", None, (KeyboardInterrupt, None, None))
    assert workers._without_stop_traceback(record) and record.exc_info is None  # the warning stays, its stack goes
    raised = logging.LogRecord("optuna", logging.WARNING, "", 0, "Trial 1 failed", None, (ValueError, None, None))
    assert workers._without_stop_traceback(raised) and raised.exc_info is not None


def test_a_zoo_campaign_trains_through_rl_zoo3_on_one_hyperparameter_file():
    conf = "benchmarks/hyperparams/learning.yml"
    tiny = definitions.Campaign("zoo", (TASK,), ("ppo", "pevfa-opr"), (0,), 2048, 1024, 2, conf)
    result = training.train(tiny, TASK, "pevfa-opr", 0)
    assert result["curve"]["steps"] == [1024, 2048] and result["timesteps"] == 2048
    assert f"--algo ppo_pevfa --env {TASK} --seed 0 -n 2048 -conf {conf}" in result["arguments"]["command"]
    assert result["curve"]["cpu_s"] == [result["cpu_seconds"] / 2, result["cpu_seconds"]]  # prorated by steps
    assert result["training_log"]["time/total_timesteps"][-1] == 2048 and result["max_average_return"] > 0
    with pytest.raises(ValueError, match="only protocol 'zoo' takes a conf"):
        definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 2048, 1024, 2, conf)
    with pytest.raises(ValueError, match="No hyperparameter file"):
        definitions.Campaign("zoo", (TASK,), ("ppo",), (0,), 2048, 1024, 2, "benchmarks/hyperparams/none.yml")
    # the file's content belongs to the stored definition: an edited file is another protocol
    assert tiny.definition()["settings"]["ppo conf"] and "conf" not in definitions.CAMPAIGNS["table1"].definition()


def test_an_authors_protocol_trial_trains_on_their_env_evaluates_sampled_actions_and_resumes(tmp_path, monkeypatch):
    tiny = definitions.Campaign("authors", (TASK,), ("opr-e2e",), (0,), 6000, 2000, 2)
    seen = []
    evaluate = training.evaluate_policy

    def recorded(model, env, *args, deterministic=True, **kwargs):
        seen.append((deterministic, env.observation_space.shape, model.num_timesteps))
        if model.num_timesteps == 4000 and not (tmp_path / "stopped").exists():
            (tmp_path / "stopped").touch()
            raise KeyboardInterrupt  # the worker ends after its checkpoint at the first iteration past 2000 steps
        return evaluate(model, env, *args, deterministic=deterministic, **kwargs)

    monkeypatch.setattr(training, "evaluate_policy", recorded)
    folder = tmp_path / "checkpoint"
    with pytest.raises(KeyboardInterrupt):
        training.train(tiny, TASK, "opr-e2e", 0, checkpoint=folder, checkpoint_freq=2000)
    state = json.loads((folder / "state.json").read_text())
    assert 2000 <= state["timesteps"] < 4000  # iterations of whole episodes: the checkpoint at an episode's end
    result = training.train(tiny, TASK, "opr-e2e", 0, checkpoint=folder, checkpoint_freq=2000)
    # InvertedPendulum's 4 state variables and the time feature; every evaluation samples actions
    assert {(deterministic, shape) for deterministic, shape, _ in seen} == {(False, (5,))}
    assert result["curve"]["steps"] == [2000, 4000, 6000] and result["resumed_from"] == state["timesteps"]
    assert result["timesteps"] >= 6000 and "rollout_episodes" in result["arguments"]


def test_the_local_generalization_diagnostic_in_the_authors_protocol_scores_every_state_of_whole_episodes():
    tiny = definitions.Campaign("authors", (TASK,), ("opr-e2e+local-generalization",), (0,), 2000, 2000, 1)
    series = training.train(tiny, TASK, "opr-e2e+local-generalization", 0)["local_generalization"]
    steps = np.array(series["timesteps"])
    assert len(steps) > 5 and steps[-1] >= 2000  # iterations of 5 whole episodes (or 2000 steps), each one logged
    # every rollout ends at an episode's end: each of its states has its Monte-Carlo return
    assert series["n_states"] == np.diff(steps, prepend=0).tolist()
    assert all(np.isfinite(series[key]).all() for key in ("pevfa_before", "pevfa_after", "vfa_before", "vfa_after"))


def use_a_tiny_sac(monkeypatch: pytest.MonkeyPatch, **options: int) -> None:
    """Protocol ``sac`` trains a tiny SAC / SACPeVFA (32x32, batches of 32) with ``options``."""
    small = dict(batch_size=32, policy_kwargs=dict(net_arch=[32, 32]), **options)
    monkeypatch.setitem(definitions.OFF_POLICY, "sac", (*definitions.OFF_POLICY["sac"][:2], small))


def stop_once_at(monkeypatch: pytest.MonkeyPatch, steps: int, marker: pathlib.Path) -> None:
    """The worker ends (KeyboardInterrupt) at the evaluation of ``steps``, once (``marker`` remembers it)."""
    evaluate = training.evaluate_policy

    def stopped(model, *args, **kwargs):
        if model.num_timesteps == steps and not marker.exists():
            marker.touch()
            raise KeyboardInterrupt
        return evaluate(model, *args, **kwargs)

    monkeypatch.setattr(training, "evaluate_policy", stopped)


def test_an_off_policy_trial_trains_sacpevfa_and_resumes_with_its_replay_buffer_and_snapshots(tmp_path, monkeypatch):
    use_a_tiny_sac(monkeypatch, learning_starts=900)
    tiny = definitions.Campaign("sac", (TASK,), ("opr",), (0,), 2000, 500, 2)
    stop_once_at(monkeypatch, 1500, tmp_path / "stopped")
    folder = tmp_path / "checkpoint"
    with pytest.raises(KeyboardInterrupt):
        training.train(tiny, TASK, "opr", 0, checkpoint=folder, checkpoint_freq=1000)
    state = json.loads((folder / "state.json").read_text())
    # one set of files named by the checkpoint's env steps (the first one's removed as the second one was saved)
    names = ["model-1000.zip", "history-1000.npz", "replay_buffer-1000.pkl"]
    assert sorted(p.name for p in folder.iterdir()) == sorted([*names, "state.json"])
    assert [training.checkpoint_file(folder, state, key).name for key in ("model", "history", "replay_buffer")] == names
    loaded, load = [], training.load_checkpoint

    def loading(*args):  # what the resumed model holds as it is loaded
        model, saved = load(*args)
        loaded.append((model.replay_buffer.size(), model.history.n_policies))
        return model, saved

    monkeypatch.setattr(training, "load_checkpoint", loading)
    result = training.train(tiny, TASK, "opr", 0, checkpoint=folder, checkpoint_freq=1000)
    assert result["resumed_from"] == state["timesteps"] == 1000 and result["timesteps"] == 2000
    assert loaded == [(1000, 1)]  # the checkpoint's replay buffer of 1000 transitions and its snapshot
    assert result["curve"]["steps"] == [500, 1000, 1500, 2000] and state["n_policies"] == 1  # the first update's
    arguments = result["arguments"]
    assert arguments["snapshot_freq"] == "1000" and arguments["learning_starts"] == "900"  # the mixin's and SAC's


def test_a_checkpoint_is_one_set_of_files_a_kill_while_saving_leaves_the_previous_one(tmp_path, monkeypatch):
    use_a_tiny_sac(monkeypatch, learning_starts=100)
    model = training.make_model("sac", "opr", make_vec_env(TASK), 0)
    model.learn(200)
    folder = tmp_path / "checkpoint"
    training.save_checkpoint(folder, model, {"timesteps": 200})
    model.learn(100, reset_num_timesteps=False)

    def killed(path):  # the kill comes as the replay buffer is written, after the model and the snapshots
        raise KeyboardInterrupt

    monkeypatch.setattr(model, "save_replay_buffer", killed)
    with pytest.raises(KeyboardInterrupt):
        training.save_checkpoint(folder, model, {"timesteps": 300})
    loaded, state = training.load_checkpoint(folder, "sac", "opr", make_vec_env(TASK))
    assert state["timesteps"] == loaded.num_timesteps == loaded.replay_buffer.size() == 200
    monkeypatch.delattr(model, "save_replay_buffer")
    training.save_checkpoint(folder, model, {"timesteps": 300})
    names = ["history-300.npz", "model-300.zip", "replay_buffer-300.pkl", "state.json"]
    assert sorted(path.name for path in folder.iterdir()) == names  # the previous set and the broken one removed
    # a checkpoint saved before the files were named by their env steps
    state = json.loads((folder / "state.json").read_text())
    for key, name in state.pop("files").items():
        (folder / name).rename(folder / training.UNNAMED_FILES[key])
    (folder / "state.json").write_text(json.dumps(state))
    loaded, _ = training.load_checkpoint(folder, "sac", "opr", make_vec_env(TASK))
    assert loaded.num_timesteps == loaded.replay_buffer.size() == 300
    (folder / "model.zip").unlink()  # a file missing: no checkpoint to go on from, the run starts over
    assert training.load_checkpoint(folder, "sac", "opr", make_vec_env(TASK)) is None


def test_the_off_policy_local_generalization_diagnostic_in_a_trial_and_the_report(tmp_path, monkeypatch):
    use_a_tiny_sac(monkeypatch, learning_starts=200, snapshot_freq=300)
    tiny = definitions.Campaign("sac", (TASK,), ("opr+local-generalization",), (0,), 1500, 500, 2)
    run = {**training.train(tiny, TASK, "opr+local-generalization", 0), "seed": 0}
    series = run["local_generalization"]
    assert series["policy_id"] == [0.0, 1.0, 2.0, 3.0, 4.0]  # a window per snapshot (300 gradient steps from the 201st step)
    assert series["timesteps"][-1] == 1500.0 and min(series["n_states"]) > 0
    assert all(min(series[key]) > 0 for key in ("pevfa_before", "vfa_before", "pevfa_after", "vfa_after"))
    # the report scores windows between snapshots, not an iteration's rollout
    collected = ({TASK: {"opr+local-generalization": [run]}}, {}, [], [tiny])
    text = engine.report.report(["q"], None, "sac", 2, tmp_path / "curves.png", cache={(("q",), None): collected})
    assert f"mean squared error on {engine.report.OFF_POLICY_SCORED}, PeVFA" in text and "Monte-Carlo" not in text
    assert "| task | variant | runs | windows |" in text and f"| {TASK} | opr+local-generalization | 1 | " in text
    assert (tmp_path / "local_generalization.png").stat().st_size > 10_000


def whole_then_stopped(campaign: definitions.Campaign, stop_at: int, checkpoint_freq: int, tmp_path: pathlib.Path,
                       monkeypatch: pytest.MonkeyPatch) -> tuple[dict[str, list[float]], pathlib.Path]:  # fmt: skip
    """The diagnostic's series of the campaign's one run, and the checkpoint folder of the same run stopped at the
    evaluation of ``stop_at`` steps."""
    variant = campaign.variants[0]
    whole = training.train(campaign, TASK, variant, 0)["local_generalization"]
    stop_once_at(monkeypatch, stop_at, tmp_path / "stopped")
    folder = tmp_path / "checkpoint"
    with pytest.raises(KeyboardInterrupt):
        training.train(campaign, TASK, variant, 0, checkpoint=folder, checkpoint_freq=checkpoint_freq)
    return whole, folder


def test_a_diagnostic_trial_goes_on_from_its_checkpoint_with_its_critic_and_series(tmp_path, monkeypatch):
    """The checkpoint holds the diagnostic's conventional critic and the windows scored so far: the resumed run's series
    is the uninterrupted run's up to the checkpoint, then the windows opened after it (the open ones are lost)."""
    import copy

    from sb3_pevfa.diagnostics import QLocalGeneralizationCallback

    use_a_tiny_sac(monkeypatch, learning_starts=200, snapshot_freq=300)
    tiny = definitions.Campaign("sac", (TASK,), ("opr+local-generalization",), (0,), 1500, 500, 1)
    whole, folder = whole_then_stopped(tiny, 1500, 1000, tmp_path, monkeypatch)
    file = training.checkpoint_file(folder, json.loads((folder / "state.json").read_text()), "diagnostic")
    saved = torch.load(file)
    assert saved["timesteps"] == 1000 and [r["policy_id"] for r in saved["results"]] == [0]
    torch.save({**saved, "timesteps": 500}, file)  # another checkpoint's: the run starts over
    assert training.load_checkpoint(folder, "sac", "opr+local-generalization", make_vec_env(TASK)) is None
    torch.save(saved, file)
    started = []  # the conventional critic when the resumed learn starts: the saved one
    init = QLocalGeneralizationCallback._init_callback
    monkeypatch.setattr(
        QLocalGeneralizationCallback,
        "_init_callback",
        lambda self: (init(self), started.append(copy.deepcopy(self.critic.state_dict()))),
    )
    result = training.train(tiny, TASK, "opr+local-generalization", 0, checkpoint=folder, checkpoint_freq=1000)
    assert all(torch.equal(started[0][k], v) for k, v in saved["critic"].items())
    assert result["resumed_from"] == 1000 and result["curve"]["steps"] == [500, 1000, 1500]
    series = result["local_generalization"]
    assert whole["policy_id"] == [0.0, 1.0, 2.0, 3.0, 4.0] and series["policy_id"] == [0.0, 3.0, 4.0]
    assert {key: values[0] for key, values in series.items()} == {key: values[0] for key, values in whole.items()}
    assert not folder.exists()


def test_an_on_policy_diagnostic_logs_the_last_iteration_before_its_checkpoint(tmp_path, monkeypatch):
    """The diagnostic's hooks run before the checkpoint's: the iteration that ends at the checkpoint is in it."""
    tiny = definitions.Campaign("paper", (TASK,), ("opr-e2e+local-generalization",), (0,), 6000, 2000, 1)
    whole, folder = whole_then_stopped(tiny, 6000, 2000, tmp_path, monkeypatch)
    result = training.train(tiny, TASK, "opr-e2e+local-generalization", 0, checkpoint=folder, checkpoint_freq=2000)
    series = result["local_generalization"]
    assert result["resumed_from"] == 4000 and series["timesteps"] == whole["timesteps"] == [2000.0, 4000.0, 6000.0]
    assert {key: values[:2] for key, values in series.items()} == {key: values[:2] for key, values in whole.items()}


# --- deadline.py: a deadline for the workers (run --until) ---------------------------------------------------------
def test_until_reads_a_clock_time_a_date_time_and_a_duration_and_names_its_forms_otherwise():
    from engine.deadline import parse_until

    now = datetime.datetime(2026, 12, 7, 10, 30).timestamp()
    assert parse_until("+90m", now) == now + 5400 and parse_until("+2.5h", now) == now + 9000
    assert parse_until("11:15", now) == datetime.datetime(2026, 12, 7, 11, 15).timestamp()  # later today
    assert parse_until("9:00", now) == datetime.datetime(2026, 12, 8, 9, 0).timestamp()  # passed today: tomorrow's
    assert parse_until("2026-12-09T08:05", now) == datetime.datetime(2026, 12, 9, 8, 5).timestamp()
    with pytest.raises(ValueError, match="has passed"):
        parse_until("2026-12-07T10:00", now)
    passed = datetime.datetime(2026, 12, 7, 10, 0).astimezone().isoformat()  # as run gives it to its workers
    assert parse_until(passed, now, passed=True) == now - 1800  # a worker stops at once
    for wrong in ("25:00", "90m", "+1d", "tomorrow"):
        with pytest.raises(ValueError, match=r"give HH:MM .*, YYYY-MM-DDTHH:MM .*, \+90m or \+2\.5h"):
            parse_until(wrong, now)


def _completed(study: optuna.Study, campaign, point: tuple[str, str, int], wall: float) -> None:
    """A complete trial of ``point`` whose run took ``wall`` seconds, a tenth of them evaluating."""
    distributions = {name: CategoricalDistribution(values) for name, values in campaign.search_space.items()}
    times = {"cpu_seconds": 0.9 * wall, "eval_cpu_seconds": 0.1 * wall, "wall_seconds": 0.9 * wall,
             "eval_wall_seconds": 0.1 * wall}  # fmt: skip
    params = dict(zip(("task", "variant", "seed"), point))
    study.add_trial(optuna.create_trial(state=TrialState.COMPLETE, value=1.0, params=params, distributions=distributions,
                                        user_attrs=times))  # fmt: skip


def test_a_worker_under_a_deadline_takes_only_the_points_expected_to_end_before_it(tmp_path, monkeypatch):
    """A run of the grid took 100 s (its other variant's 200 s on another task): with 60 s left the worker takes no
    new point of either, but the point whose checkpoint has done 70 s of its 100; with more time, the rest."""
    from engine.deadline import Deadline

    tiny = definitions.Campaign("paper", (TASK, "Pendulum-v1"), ("ppo", "opr-e2e"), (0, 1, 2), 4000, 2000, 2)
    journal = str(tmp_path / "deadline.journal")
    study, _ = storage.open_study("deadline", storage.storage_of("deadline", journal), tiny)
    _completed(study, tiny, (TASK, "ppo", 0), 100.0)
    _completed(study, tiny, (TASK, "opr-e2e", 0), 200.0)
    _completed(study, tiny, ("Pendulum-v1", "ppo", 0), 100.0)
    folder = tiny.checkpoint_folder("deadline", (TASK, "ppo", 2))
    folder.mkdir(parents=True)
    (folder / "state.json").write_text(json.dumps({"timesteps": 2000, "wall": 60.0, "eval_wall": 10.0}))
    trained = []

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        trained.append((task, variant, seed))
        wall = 200.0 if variant == "opr-e2e" else 100.0  # as long as the complete runs: the estimates stay
        times = {"cpu_seconds": 0.9 * wall, "eval_cpu_seconds": 0.1 * wall, "wall_seconds": 0.9 * wall,
                 "eval_wall_seconds": 0.1 * wall}  # fmt: skip
        return {"max_average_return": 1.0, "final_return": 1.0, "steps_per_cpu_second": 1.0, **times}

    monkeypatch.setattr(workers, "train", train)
    workers.work_on("deadline", study, tiny, Deadline(time.time() + 60, ["deadline"], journal))
    assert trained == [(TASK, "ppo", 2)]  # 30 s left of its 100; ppo's other points 100 s, opr-e2e's 200 s
    workers.work_on("deadline", study, tiny, Deadline(time.time() + 150, ["deadline"], journal))
    assert sorted(trained[1:]) == [(TASK, "ppo", 1), ("Pendulum-v1", "ppo", 1), ("Pendulum-v1", "ppo", 2)]
    workers.work_on("deadline", study, tiny, Deadline(time.time() + 250, ["deadline"], journal))
    assert len(trained) == 9 and storage.pending(study, tiny) == 0  # opr-e2e on Pendulum-v1: 200 s by the ratio
    assert len(study.get_trials()) == 12 and not [t for t in study.get_trials() if t.state != TrialState.COMPLETE]


def test_with_fill_a_worker_takes_the_points_in_the_campaigns_order_but_protocol_zoos_that_do_not_fit(tmp_path, monkeypatch):
    """30 s left; the runs of campaigns z (protocol zoo) and a take 100 s, b's 10 s. Without ``fill`` no point of z
    or a; with it a's, then b's, as without a deadline (a stop keeps their work), but none of z's (rl-zoo3's training
    keeps no checkpoint)."""
    journal = str(tmp_path / "fill.journal")
    grids = {"a": ("opr-e2e", (0, 1, 2), 100.0), "b": ("ppo", (0, 1), 10.0)}
    for name, (variant, seeds, wall) in grids.items():
        tiny = definitions.Campaign("paper", (TASK,), (variant,), seeds, 4000, 2000, 2)
        study, _ = storage.open_study(name, storage.storage_of(name, journal), tiny)
        _completed(study, tiny, (TASK, variant, seeds[0]), wall)
    zoo = definitions.Campaign("zoo", (TASK,), ("ppo",), (0,), 2048, 1024, 2, "benchmarks/hyperparams/learning.yml")
    storage.open_study("z", storage.storage_of("z", journal), zoo)
    trained = []

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        trained.append((campaign_.protocol, variant, seed))
        wall = 10.0 if variant == "ppo" else 100.0  # as long as the complete runs: the estimates stay
        times = {"cpu_seconds": 0.9 * wall, "eval_cpu_seconds": 0.1 * wall, "wall_seconds": 0.9 * wall,
                 "eval_wall_seconds": 0.1 * wall}  # fmt: skip
        return {"max_average_return": 1.0, "final_return": 1.0, "steps_per_cpu_second": 1.0, **times}

    monkeypatch.setattr(workers, "train", train)
    workers.work_on_all(["z", "a"], journal, until=time.time() + 30)
    assert trained == []
    workers.work_on_all(["z", "a", "b"], journal, until=time.time() + 30, fill=True)
    assert sorted(trained[:2]) == [("paper", "opr-e2e", 1), ("paper", "opr-e2e", 2)]
    assert trained[2:] == [("paper", "ppo", 1)]


def test_a_deadline_leaves_a_waiting_retry_that_would_not_end_before_it():
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1), 4000, 2000, 2)
    study = optuna.create_study(storage=optuna.storages.InMemoryStorage())
    study.sampler = optuna.samplers.GridSampler(tiny.search_space)
    storage.enqueue(study, (TASK, "ppo", 1))
    rng = random.Random(0)
    assert not storage.draw(study, tiny, rng, lambda point: point != (TASK, "ppo", 1))  # not another point instead
    assert storage.draw(study, tiny, rng, lambda point: True) and storage.draw(study, tiny, rng)
    assert len(study.get_trials()) == 1  # the waiting trial starts next: nothing more enqueued
    study.tell(study.ask(), 1.0)
    assert not storage.draw(study, tiny, rng, lambda point: False) and len(study.get_trials()) == 1
    assert storage.draw(study, tiny, rng, lambda point: point == (TASK, "ppo", 0))
    assert study.get_trials()[-1].system_attrs["fixed_params"]["seed"] == 0


def test_a_trial_running_at_the_deadline_stops_as_by_sigterm(tmp_path, monkeypatch):
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0,), 4000, 2000, 2)
    journal = str(tmp_path / "late.journal")
    study, _ = storage.open_study("late", storage.storage_of("late", journal), tiny)

    def train(campaign_, task, variant, seed, trial=None, checkpoint=None, started=None):
        end = time.monotonic() + 60
        while time.monotonic() < end:  # the deadline's alarm asks the stop, which the next iteration takes
            time.sleep(0.05)
            if training.STOP.asked:
                raise KeyboardInterrupt
        raise AssertionError("not stopped")

    monkeypatch.setattr(workers, "train", train)
    saved = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)]
    start = time.monotonic()
    try:
        with pytest.raises(SystemExit) as stopped:
            workers.work(["late"], journal, until=time.time() + 5.0)  # the trial starts within 5 s, on a busy machine too
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for s, handler in zip((signal.SIGINT, signal.SIGTERM, signal.SIGALRM), saved):
            signal.signal(s, handler)
    assert stopped.value.code == workers.STOPPED and time.monotonic() - start < 20
    (trial,) = study.get_trials()
    assert trial.state == TrialState.FAIL and trial.user_attrs["interrupted"] == "stopped"


def test_run_gives_its_workers_the_deadline_and_says_how_many_points_it_left(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(signal, "signal", lambda *args: None)  # run's handlers stay out of the test's process
    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1), 4000, 2000, 2)
    journal = str(tmp_path / "left.journal")
    storage.open_study("left", storage.storage_of("left", journal), tiny)
    commands, real_popen = [], subprocess.Popen

    def popen(command):
        commands.append(command)
        return real_popen(["true"])  # a worker that found nothing to end before the deadline

    monkeypatch.setattr(workers.subprocess, "Popen", popen)
    until = time.time() + 600
    workers.run(["left"], journal, 1, 1800.0, until=until, fill=True)
    (command,) = commands
    assert command[-1] == "--fill"
    from engine.deadline import parse_until

    assert parse_until(command[command.index("--until") + 1]) == pytest.approx(until, abs=1e-3)
    at = datetime.datetime.fromtimestamp(until)
    out = capsys.readouterr().out
    assert (
        f"2 grid points left for a later run (the same command; a stopped trial goes on from its checkpoint): the "
        f"deadline at {at:%Y-%m-%d %H:%M} near: none of them expected to end before it" in out
    )

    # the deadline reached while a worker trained: its trial stopped, run says so and succeeds
    monkeypatch.setattr(workers.subprocess, "Popen", lambda command: real_popen([sys.executable, "-c", stopping]))
    stopping = f"import time; time.sleep(1); raise SystemExit({workers.STOPPED})"
    until = time.time() + 0.5
    workers.run(["left"], journal, 1, 1800.0, until=until)
    at = datetime.datetime.fromtimestamp(until)
    assert (
        f"2 grid points left for a later run (the same command; a stopped trial goes on from its checkpoint): the "
        f"deadline at {at:%Y-%m-%d %H:%M} reached" in capsys.readouterr().out
    )
    with pytest.raises(SystemExit, match="left: stopped; the same run command goes on"):  # stopped before it
        workers.run(["left"], journal, 1, 1800.0, until=time.time() + 600)


def test_a_deadline_reads_the_longer_of_complete_runs_and_a_running_trials_pace(tmp_path):
    """A running trial's pace (its first steps, faster than a whole run's) does not shorten the time that complete
    runs give (here another variant's on the task, scaled by the two variants' ratio elsewhere); it counts where no
    complete run tells the time; a point with no estimate counts as long as the longest run known, and is taken where
    no run is known."""
    from engine.deadline import Deadline

    tiny = definitions.Campaign("paper", (TASK, "Pendulum-v1"), ("ppo", "opr-e2e"), (0, 1, 2), 4000, 2000, 2)
    journal = str(tmp_path / "pace.journal")
    study, _ = storage.open_study("pace", storage.storage_of("pace", journal), tiny)
    point = ("Pendulum-v1", "opr-e2e", 2)

    def fits(left: float, point: tuple[str, str, int]) -> bool:
        return Deadline(time.time() + left, ["pace"], journal).fitting("pace", tiny)(point)

    assert fits(1, point)  # no run known at all
    distributions = {name: CategoricalDistribution(values) for name, values in tiny.search_space.items()}
    progress = {"steps": 2000, "cpu_s": 10.0, "wall_s": 10.0}  # 10 s for half its steps: 20 s a run by its pace
    params = {"task": "Pendulum-v1", "variant": "opr-e2e", "seed": 1}
    study.add_trial(optuna.create_trial(state=TrialState.RUNNING, params=params, distributions=distributions,
                                        user_attrs={"progress": progress}))  # fmt: skip
    assert fits(50, point) and not fits(15, point)  # by the pace alone
    # no run of the variant, nor of another variant on the task: as long as the longest run known (20 s)
    assert fits(25, (TASK, "ppo", 2)) and not fits(15, (TASK, "ppo", 2))
    for task, variant, wall in ((TASK, "ppo", 100.0), (TASK, "opr-e2e", 200.0), ("Pendulum-v1", "ppo", 100.0)):
        _completed(study, tiny, (task, variant, 0), wall)
    assert not fits(50, point) and not fits(190, point) and fits(210, point)  # 100 s x 2: ppo's time, opr-e2e's ratio


def test_run_until_stops_a_real_training_at_the_deadline_and_succeeds(tmp_path):
    """The command line end to end: the deadline reaches the worker process, which stops its training (interrupted,
    to go on from its checkpoint) and exits; run succeeds and says how many grid points are left."""
    journal = tmp_path / "until.journal"
    command = [sys.executable, str(ROOT / "benchmarks" / "campaign.py"), "run", "--campaign", "until", "--storage",
               str(journal), "--workers", "1", "--until", "+0.25m", *_definition("ppo", timesteps=10_000_000)]  # fmt: skip
    start = time.monotonic()
    result = subprocess.run(command, capture_output=True, text=True, timeout=150)  # no stop: 10M steps time out
    assert result.returncode == 0, result.stderr[-3000:]
    assert 15 <= time.monotonic() - start < 120 and "Traceback" not in result.stderr
    assert "1 grid points left for a later run" in result.stdout and "reached" in result.stdout, result.stdout[-2000:]
    (trial,) = _study("until", journal).get_trials()
    assert trial.state == TrialState.FAIL and trial.user_attrs["interrupted"] == "stopped"


def test_a_deadline_reads_the_storage_at_most_once_a_minute(tmp_path, monkeypatch):
    """A worker with nothing that fits looks again every few seconds over every campaign: the runs' times it read
    serve for a minute, then are read again."""
    from engine import deadline as deadline_module

    tiny = definitions.Campaign("paper", (TASK,), ("ppo",), (0, 1), 4000, 2000, 2)
    journal = str(tmp_path / "reads.journal")
    storage.open_study("reads", storage.storage_of("reads", journal), tiny)
    reads, clock = [], [1000.0]
    monkeypatch.setattr(deadline_module, "collect", lambda *args: reads.append(args) or results.collect(*args))
    clock_only_here = types.SimpleNamespace(time=time.time, monotonic=lambda: clock[0])  # not the process's clock
    monkeypatch.setattr(deadline_module, "time", clock_only_here)
    deadline = deadline_module.Deadline(time.time() + 600, ["reads"], journal)
    for _ in range(5):
        assert deadline.fitting("reads", tiny)((TASK, "ppo", 0))
    clock[0] += deadline_module.REREAD_AFTER - 1
    deadline.fitting("reads", tiny)
    assert len(reads) == 1
    clock[0] += 2
    deadline.fitting("reads", tiny)
    assert len(reads) == 2
