"""The benchmark scripts, and the research notes' scripts, run end to end at a tiny budget and write what the docs cite
(the long runs are not tests)."""

import io
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest
import torch as th
import yaml
from scipy.stats import trim_mean
from stable_baselines3.common.logger import HumanOutputFormat

from sb3_pevfa import REPRESENTATIONS

ROOT = pathlib.Path(__file__).parents[1]
NOTES = ROOT / "docs" / "notes" / "scripts"  # scripts of one research note each


def _run(*args: str, cwd: pathlib.Path) -> str:
    result = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=600, cwd=cwd)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    return result.stdout


def test_learning_benchmark_through_the_zoo(tmp_path):
    out = tmp_path / "learning"
    stdout = _run(str(ROOT / "benchmarks" / "learning.py"), "--env", "InvertedPendulum-v5", "--variants", "ppo", "pevfa-opr",
                  "--seeds", "0", "1", "--timesteps", "2048", "--eval-freq", "1024", "--eval-episodes", "2",
                  "--out", str(out), "--plot", str(tmp_path / "curves.png"), cwd=ROOT)  # fmt: skip
    runs = {path.stem: json.loads(path.read_text()) for path in out.glob("*.json")}
    assert set(runs) == {f"InvertedPendulum-v5_{v}_seed{s}" for v in ("ppo", "pevfa-opr") for s in (0, 1)}
    ppo, pevfa = runs["InvertedPendulum-v5_ppo_seed0"], runs["InvertedPendulum-v5_pevfa-opr_seed0"]
    assert [c["timesteps"] for c in ppo["curve"]] == [1024, 2048]
    assert len(ppo["episode_returns"][0]) == 2
    # one config file for both algorithms; only the algorithm differs
    assert "--algo ppo " in ppo["command"] and "--algo ppo_pevfa " in pevfa["command"]
    shared = [command.split(" --env ")[1].split(" -f ")[0] for command in (ppo["command"], pevfa["command"])]
    assert shared[0].replace("_ppo_", "_") == shared[1].replace("_pevfa-opr_", "_")
    assert "| ppo | 2 |" in stdout and "| pevfa-opr | 2 |" in stdout and "95 % CI" in stdout
    # per second too: each run's CPU time and each evaluation's wall-clock time
    assert ppo["cpu_time_s"] > 0 and 0 < ppo["curve"][0]["wall_s"] < ppo["curve"][1]["wall_s"] <= ppo["wall_time_s"]
    assert "Per second (budgets: ppo's mean run" in stdout and "| pevfa-opr |" in stdout.split("Per second")[1]
    assert "best-so-far at the baseline's CPU time" in stdout
    assert (tmp_path / "curves.png").stat().st_size > 0
    # finished runs are skipped on a second call
    settings = ["--env", "InvertedPendulum-v5", "--variants", "ppo", "--seeds", "0", "--eval-episodes", "2", "--out", str(out)]
    again = _run(str(ROOT / "benchmarks" / "learning.py"), *settings, "--timesteps", "2048", "--eval-freq", "1024", cwd=ROOT)
    assert "max" not in again.split("**")[0]  # no run message before the report
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine import commands

    differ = r"holds runs of other settings.*seed0.json \(timesteps 2048 not 4096, eval_freq 1024 not 20000\)"
    with pytest.raises(SystemExit, match=differ):
        commands.learning_main([*settings, "--timesteps", "4096"])  # never reported as runs of other settings
    with pytest.raises(SystemExit):
        commands.learning_main(["--report", "--out", str(tmp_path / "nothing")])  # a usage error, no folder made
    assert not (tmp_path / "nothing").exists()
    # the training logs of the same runs: kept compactly, and reported around each run's peak
    report = _run(str(ROOT / "benchmarks" / "training_logs.py"), "--out", str(out), "--env", "InvertedPendulum-v5",
                  "--plot", str(tmp_path / "logs.png"), cwd=ROOT)  # fmt: skip
    logs = {path.stem: json.loads(path.read_text()) for path in (out / "logs").glob("*.json")}
    assert set(logs) == set(runs)
    # two evaluation tables and the final one (a single 2048-step rollout logs no update: SB3 logs it at the next)
    assert logs["InvertedPendulum-v5_pevfa-opr_seed0"]["time/total_timesteps"] == [1024, 2048, 2048]
    assert "| pevfa-opr | 2 |" in report and "| ppo | 2 |" in report and (tmp_path / "logs.png").stat().st_size > 0


def test_best_so_far_by_wall_clock_and_by_cpu_time():
    """An evaluation's CPU time is its run's prorated by steps: by hand on a run of 3 evaluations."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine.zoo_report import best_so_far_at, budgets, per_second

    def run(returns, cpu, wall):
        curve = [dict(timesteps=t, mean_return=r, wall_s=w) for t, r, w in zip((100, 200, 300), returns, wall)]
        return dict(timesteps=300, cpu_time_s=cpu, wall_time_s=wall[-1], curve=curve)

    ppo = run([1.0, 2.0, 3.0], cpu=30.0, wall=[10.0, 20.0, 30.0])
    slow = run([5.0, 1.0, 9.0], cpu=60.0, wall=[5.0, 10.0, 40.0])  # CPU at its evaluations: 20, 40, 60
    assert budgets([ppo]) == {"wall": 30.0, "cpu": 30.0}
    assert best_so_far_at(slow, 30.0) == 5.0 and best_so_far_at(slow, 30.0, "cpu") == 5.0
    assert best_so_far_at(slow, 40.0) == 9.0 and best_so_far_at(slow, 40.0, "cpu") == 5.0
    assert best_so_far_at(slow, 10.0, "cpu") == float("-inf")
    rows = [line for line in per_second({"ppo": [ppo], "slow": [slow]}, "ppo") if line.startswith("| slow")]
    assert rows == ["| slow | 8 ± 0 | 5 | 0.75x / 0.50x | 5 ± 0 | 5 | 5 ± 0 | 5 |"]


def test_paired_per_second_view_budgets_each_seed_by_its_baseline_run():
    """--paired: each run against the baseline run of its seed (its machine), by hand; a seed without one is left out."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine.zoo_report import best_so_far_at, per_second, task_scores

    def run(seed, returns, cpu, wall):
        curve = [dict(timesteps=t, mean_return=r, wall_s=w) for t, r, w in zip((100, 200, 300), returns, wall)]
        return dict(seed=seed, timesteps=300, cpu_time_s=cpu, wall_time_s=wall[-1], curve=curve)

    # seed 1 ran on a machine 3x slower than seed 0
    ppo = [run(0, [1.0, 2.0, 3.0], 30.0, [10.0, 20.0, 30.0]), run(1, [1.0, 2.0, 3.0], 90.0, [30.0, 60.0, 90.0])]
    # listed out of seed order: pairs go by seed, not by position
    slow = [run(1, [5.0, 1.0, 9.0], 90.0, [30.0, 60.0, 90.0]), run(2, [7.0, 7.0, 7.0], 1.0, [1.0, 2.0, 3.0]),
            run(0, [5.0, 1.0, 9.0], 60.0, [5.0, 10.0, 40.0])]  # fmt: skip
    variants = {"ppo": ppo, "slow": slow}
    paired = [line for line in per_second(variants, "ppo", paired=True) if line.startswith("| slow")]
    # speed 1x / 1x of seed 1's PPO and 0.75x / 0.5x of seed 0's; best-so-far within 90 s and 30 s: 9 and 5
    assert paired == ["| slow | 5 ± 2 | 4 | 0.88x / 0.75x | 7 ± 1 | 9, 5 | 7 ± 1 | 9, 5 |"]
    views = task_scores({"Task": variants}, "ppo", paired=True)
    assert views["best-so-far at the baseline's CPU time"]["slow"]["Task"].tolist() == [9.0, 5.0]
    assert views["best-so-far at the baseline's time"]["slow"]["Task"].tolist() == [9.0, 5.0]
    # unpaired, the budget is PPO's mean run (60 s) for every seed: seed 0 gets its whole run, seed 1 two thirds
    unpaired = task_scores({"Task": variants}, "ppo")["best-so-far at the baseline's CPU time"]["slow"]["Task"]
    assert unpaired.tolist() == [5.0, 7.0, 9.0]
    # a run's last evaluation is inside its own CPU time (456.000964 * 300032 / 300032 rounds above it)
    last = dict(seed=0, timesteps=300032, cpu_time_s=456.000964, curve=[dict(timesteps=300032, mean_return=1.0)])
    assert best_so_far_at(last, last["cpu_time_s"], "cpu") == 1.0


def test_critic_learning_rate_variants_scale_each_entrys_rate(tmp_path):
    """``critic_learning_rate_scale`` becomes a ``critic_learning_rate`` per task, from that task's config entry."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine.zoo import variant_options

    conf = tmp_path / "conf.yml"
    conf.write_text("A-v0:\n  learning_rate: 2.5e-05\nB-v0:\n  n_steps: 32\nC-v0:\n  learning_rate: lin_3e-4\n")
    assert variant_options("pevfa-opr-critic-lr-x10", "A-v0", conf) == {"critic_learning_rate": 2.5e-04}
    assert variant_options("pevfa-opr-critic-lr-x10", "B-v0", conf) == {"critic_learning_rate": 3e-03}  # PPO's default
    control = variant_options("pevfa-none-no-history-critic-lr-x10", "A-v0", conf)
    assert control == {"representation": "none", "history_train_freq": 0, "critic_learning_rate": 2.5e-04}
    assert variant_options("pevfa-opr", "A-v0", conf) == {} and variant_options("ppo", "A-v0", conf) is None
    with pytest.raises(ValueError, match="constant learning_rate"):
        variant_options("pevfa-opr-critic-lr-x10", "C-v0", conf)
    # a variant's policy_kwargs join the entry's (rl-zoo3 would replace them: the tuned 256x256 networks lost)
    conf.write_text("A-v0:\n  policy_kwargs: dict(net_arch=[8], activation_fn=nn.ReLU)\nB-v0:\n  n_steps: 32\n")
    merged = variant_options("pevfa-opr-elu", "A-v0", conf)["policy_kwargs"]
    expected = dict(net_arch=[8], activation_fn=th.nn.ReLU, critic_activation_fn=th.nn.ELU)
    assert eval(merged, {"nn": th.nn, "dict": dict}) == expected
    assert variant_options("pevfa-opr-elu", "B-v0", conf) == {"policy_kwargs": "dict(critic_activation_fn=nn.ELU)"}


def test_speed_encoder_and_memory_benchmarks(tmp_path):
    _run(str(ROOT / "benchmarks" / "speed.py"), "--env", "CartPole-v1", "--steps", "256", "--warmup", "512", "--repeats", "2",
         "--out", str(tmp_path), "--cache", str(tmp_path / "cache"), cwd=ROOT)  # fmt: skip
    speed = json.loads((tmp_path / "CartPole-v1_warmup512.json").read_text())
    assert len(speed["ppo_steps_per_s"]) == len(speed["pevfa_steps_per_s"]) == 2 and speed["ratio_median"] > 0
    assert set(speed["pevfa_shares"]) >= {"rollout", "on-policy update", "history update"}
    log = _run(str(NOTES / "fast_path.py"), "--algo", "ppo_pevfa", "a2c_pevfa", "--env", "CartPole-v1",
               "--warmup", "256", "--repeats", "1", "--rollouts", "1", "--out", str(tmp_path / "fast.json"),
               cwd=ROOT)  # fmt: skip
    fast = json.loads((tmp_path / "fast.json").read_text())
    assert [r["algo"] for r in fast] == ["ppo_pevfa", "a2c_pevfa"] and "| ppo_pevfa | CartPole-v1 |" in log
    # --rollouts 1: one rollout per measurement, 2048 steps for PPO and 5 for A2C (their defaults)
    assert [r["steps_per_measurement"] for r in fast] == [2048, 5]
    for r in fast:
        for piece in ("rollout", "update"):
            sb3, quick = (r[f"{piece}_{path}_ms_per_step"]["median"] for path in ("sb3", "fast"))
            assert sb3 > 0 and quick > 0 and r[f"{piece}_saved_ms_per_step"] == pytest.approx(sb3 - quick)
    _run(str(ROOT / "benchmarks" / "encoder_cost.py"), "--env", "CartPole-v1", "--policies", "1", "3", "--repeats", "2",
         "--out", str(tmp_path / "encoder.json"), cwd=ROOT)  # fmt: skip
    rows = json.loads((tmp_path / "encoder.json").read_text())["rows"]
    assert {row["representation"] for row in rows} == set(REPRESENTATIONS)
    _run(str(NOTES / "history_memory.py"), "--env", "CartPole-v1", "--steps", "4096", "8192",
         "--out", str(tmp_path / "memory.json"), cwd=ROOT)  # fmt: skip
    memory = json.loads((tmp_path / "memory.json").read_text())["rows"]
    assert memory[0]["mb"] < memory[1]["mb"] and memory[1]["policies"] == 4


def test_zoo_speed_benchmark_counts_the_snapshots_each_update_draws(tmp_path):
    out = tmp_path / "speed.json"
    options = '{"snapshot_freq": 10}'  # the first snapshot at the first gradient step, then one per 10
    log = _run(str(ROOT / "benchmarks" / "speed_zoo.py"), "--setting", "sac-hopper", "--steps", "300", "--repeats", "1",
               "--eval-episodes", "1", "--overrides", '{"learning_starts": 100}', "--options", options, "--out", str(out),
               cwd=ROOT)  # fmt: skip
    summary = json.loads(out.read_text())
    base, pevfa = summary["runs"]["base"][0], summary["runs"]["pevfa"][0]
    assert summary["ratio_median"] == pytest.approx(pevfa["steps_per_cpu_s"] / base["steps_per_cpu_s"])
    assert "snapshots_per_update" not in base and pevfa["batch_policies"] == 8
    # 200 gradient steps (env steps 101-300), a snapshots' update per 4 of them: at step g, 1 + g // 10 snapshots exist
    drawn = [min(8, 1 + step // 10) for step in range(4, 201, 4)]
    assert pevfa["snapshots_per_update"] == pytest.approx(np.mean(drawn))
    assert "1 of the SACPeVFA runs drew" in log  # short of a long run's 8: said
    _run(str(ROOT / "benchmarks" / "speed_zoo.py"), "--setting", "a2c-cartpole", "--steps", "200", "--repeats", "1",
         "--eval-episodes", "1", "--out", str(out), cwd=ROOT)  # fmt: skip
    assert all("snapshots_per_update" not in run for runs in json.loads(out.read_text())["runs"].values() for run in runs)


def test_denormals_benchmark_runs_every_variant(tmp_path):
    out, conf = tmp_path / "denormals.json", tmp_path / "conf.yml"
    conf.write_text("CartPole-v1:\n  policy: MlpPolicy\n  n_steps: 64\n  batch_size: 32\n")
    stdout = _run(str(NOTES / "denormals.py"), "--env", "CartPole-v1", "--timesteps", "128", "--conf", str(conf),
                  "--out", str(out), cwd=tmp_path)  # fmt: skip
    rows = json.loads(out.read_text())
    assert [r["variant"] for r in rows] == ["ppo", "ppo-flush-denormal", "pevfa", "pevfa-no-flush-denormal"]
    assert all(r["timesteps"] == 128 and r["cpu_s"] > 0 and 0.0 <= r["denormal_fraction"] < 1.0 for r in rows)
    assert "| conf, CartPole-v1, 0k | ppo | 0 |" in stdout
    assert [r["denormal_fraction"] for r in rows if r["variant"] in ("ppo-flush-denormal", "pevfa")] == [0.0, 0.0]
    report = _run(str(NOTES / "denormals.py"), "--report", str(out), str(out), cwd=tmp_path)
    assert "| conf, CartPole-v1, 0k | pevfa | 0, 0 |" in report  # the same runs twice
    assert "the same mean return of their last 100 training episodes: 2 of 2." in report  # one pair per algorithm


def test_profile_benchmark_reports_both_algorithms(tmp_path):
    stdout = _run(str(ROOT / "benchmarks" / "profile_iteration.py"), "--env", "CartPole-v1", "--iterations", "2", cwd=tmp_path)
    rows = {line.split("|")[1].strip(): line.split("|")[2:4] for line in stdout.splitlines() if line.startswith("| ")}
    assert {"CPU time (s)", "rollout", "PPO update", "history updates"} <= set(rows)
    # PPO has none; PPOPeVFA trains on the history once past its 5000 learning-start steps (3 x 2048 here)
    assert float(rows["history updates"][0]) == 0.0 < float(rows["history updates"][1])


def test_profile_benchmark_reads_a_zoo_entry(tmp_path):
    """``--conf``: the env's entry of an rl-zoo3 file, as the zoo builds it (VecNormalize, n_envs, policy_kwargs)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from profile_iteration import zoo_entry
    from stable_baselines3.common.vec_env import VecNormalize

    conf = tmp_path / "conf.yml"
    conf.write_text(
        "CartPole-v1:\n  normalize: true\n  n_envs: 2\n  policy: MlpPolicy\n  n_timesteps: 1e4\n  n_steps: 32\n"
        "  policy_kwargs: dict(activation_fn=nn.ReLU, net_arch=dict(pi=[8], vf=[8]))\n"
    )
    env, kwargs = zoo_entry(conf, "CartPole-v1")
    assert isinstance(env, VecNormalize) and env.num_envs == 2
    assert kwargs["n_steps"] == 32 and set(kwargs) == {"n_steps", "policy_kwargs"}
    assert kwargs["policy_kwargs"]["net_arch"] == {"pi": [8], "vf": [8]}
    assert zoo_entry(None, "CartPole-v1") == ("CartPole-v1", {})
    stdout = _run(str(ROOT / "benchmarks" / "profile_iteration.py"), "--env", "CartPole-v1", "--iterations", "1",
                  "--conf", str(conf), cwd=tmp_path)  # fmt: skip
    assert "| CPU time (s) |" in stdout


def test_history_step_benchmark_times_every_setting(tmp_path):
    stdout = _run(
        str(NOTES / "history_step.py"), "--env", "CartPole-v1", "--arch", "8", "--policies", "3",
        "--steps", "2", cwd=tmp_path,
    )  # fmt: skip
    rows = [line.split("|")[1:3] for line in stdout.splitlines() if line.startswith("| ") and "samples" in line]
    assert [label.strip() for label, _ in rows] == [
        "64 samples, uniform", "64 samples, 8 policies", "256 samples, uniform", "256 samples, 8 policies",
        "256 samples, 4 policies", "512 samples, 8 policies",
    ]  # fmt: skip
    assert all(float(ms) > 0 for _, ms in rows)


def test_objective_step_benchmark_times_every_batch(tmp_path):
    stdout = _run(
        str(NOTES / "objective_step.py"), "--env", "CartPole-v1", "--arch", "8", "--policies", "3",
        "--steps", "2", cwd=tmp_path,
    )  # fmt: skip
    rows = [line.split("|")[1:5] for line in stdout.splitlines()[2:] if line.startswith("| ")]  # below the header
    assert [label.strip() for label, *_ in rows] == ["32 policies", "64 policies", "128 policies"]
    for _, ms, every_10, every_40 in rows:  # ms per step x steps per rollout (ms printed to 0.01, the rest to 1)
        assert float(ms) > 0 and abs(float(every_10) - 2048 / 10 * float(ms)) <= 0.5 + 2048 / 10 * 0.005
        assert abs(float(every_40) - 2048 / 40 * float(ms)) <= 0.5 + 2048 / 40 * 0.005


def test_aggregate_iqm_bootstrap_and_profiles_by_hand():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine import aggregate

    baseline = {"a": np.array([10.0, 30.0]), "b": np.array([1.0, 1.0, 4.0])}  # means 20 and 2
    scores = aggregate.normalized({"a": np.array([20.0, 40.0, 60.0]), "b": np.array([2.0, 8.0])}, baseline)
    np.testing.assert_allclose(scores["a"], [1, 2, 3])
    np.testing.assert_allclose(scores["b"], [1, 4])
    # pooled runs 1, 1, 2, 3, 4: the middle half (trimmed 25 % at each end: 1 run each) is 1, 2, 3
    assert aggregate.iqm(scores) == pytest.approx(2.0)
    # scipy's trim_mean to the bit, for every size a report meets (1 to 40 runs, tasks of unequal seeds)
    rng = np.random.default_rng(0)
    for size in range(1, 41):
        runs = {"a": rng.normal(size=size), "b": rng.lognormal(size=1 + size % 3)}
        assert aggregate.iqm(runs) == float(trim_mean(np.concatenate([runs["a"], runs["b"]]), 0.25))
    assert np.isnan(aggregate.iqm({"a": np.array([1.0, 2, 3, np.nan, 5, 6, 7, 8])}))  # as scipy's: not trimmed away
    assert aggregate.mean(scores) == pytest.approx((2.0 + 2.5) / 2)
    low, high = aggregate.stratified_bootstrap_ci(scores, aggregate.mean, reps=500)
    assert 1.0 < low < aggregate.mean(scores) < high < 3.5
    # every task's seeds resampled within the task: all-equal scores give a zero-width interval
    assert aggregate.stratified_bootstrap_ci({"a": np.ones(3), "b": np.full(2, 2.0)}, aggregate.mean) == (1.5, 1.5)
    # tasks weigh equally: task a has 2 of 3 runs above 1.5, task b 1 of 2
    np.testing.assert_allclose(aggregate.performance_profile(scores, np.array([0.5, 1.5, 5.0])), [1.0, (2 / 3 + 1 / 2) / 2, 0])
    assert aggregate.performance_profile({"a": [2.0], "b": np.float64(0.0)}, [1.0]).tolist() == [0.5]  # lists, one score


def test_training_logs_parse_sb3s_own_tables():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine import training_logs

    stream = io.StringIO()
    output = HumanOutputFormat(stream)
    for table in (
        {"time/total_timesteps": 2048, "train/explained_variance": 0.5, "pevfa/value_chi_gradient": 1e-3},
        {"eval/mean_reward": 10.0, "time/total_timesteps": 4096},  # an evaluation: no training keys
        {"time/total_timesteps": 4096, "train/explained_variance": -0.25, "train/std": 0.9},
    ):
        output.write(table, dict.fromkeys(table))
    logs = training_logs.parse_log("progress bar noise\n" + stream.getvalue())
    assert logs["time/total_timesteps"] == [2048, 4096, 4096]
    np.testing.assert_array_equal(logs["train/explained_variance"], [0.5, np.nan, -0.25])
    np.testing.assert_array_equal(logs["pevfa/value_chi_gradient"], [1e-3, np.nan, np.nan])
    grid = np.array([2048.0, 3072.0, 4096.0])
    np.testing.assert_allclose(training_logs.interpolated(grid, logs, "train/explained_variance"), [0.5, 0.125, -0.25])


def test_normalize_memory_benchmark_shows_the_chunks_bound():
    out = _run(str(NOTES / "normalize_memory.py"), "--samples", "100000", "--obs-dim", "16", cwd=ROOT)
    peaks = [float(line.split("peak ")[1].split(" MiB")[0]) for line in out.splitlines()]
    assert len(peaks) == 2 and peaks[1] < peaks[0] / 3  # 16384-row chunks against the whole history at once


def test_training_logs_per_window_of_steps_by_hand(tmp_path):
    """Signals and evaluations averaged per window of env steps, then over the seeds that reached it: by hand."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine import training_logs

    (tmp_path / "logs").mkdir()
    steps = [1000, 2000, 3000, 4000]
    runs = (  # stds per logged step, evaluations (steps, returns), the run's length
        ([0.9, 0.8, 0.7, 0.6], [(1000, 10), (2000, 30), (4000, 30)], 4000),
        ([0.5, 0.5, 0.3, np.nan], [(2000, 20), (4000, 60)], 4000),
        ([0.1, 0.1, 0.1, 0.1], [(2000, 1000), (3000, 1000)], 3000),  # ended before the second window's end
    )
    for seed, (stds, evaluations, timesteps) in enumerate(runs):
        name = f"Hopper-v5_ppo_seed{seed}.json"
        curve = [{"timesteps": t, "mean_return": r} for t, r in evaluations]
        (tmp_path / name).write_text(json.dumps({"variant": "ppo", "curve": curve, "timesteps": timesteps}))
        logs = {key: [np.nan] * 4 for key in training_logs.KEYS}
        logs.update({"time/total_timesteps": steps, "train/std": stds})
        (tmp_path / "logs" / name).write_text(json.dumps(logs))
    report = training_logs.window_report(tmp_path, "Hopper-v5", [4000, 2000, 2000])  # sorted, duplicates dropped
    header = next(line for line in report.splitlines() if line.startswith("| variant")).split(" | ")
    rows = [line.split(" | ") for line in report.splitlines() if line.startswith("| ppo")]
    # window 1, three seeds: returns mean(10, 30) = 20, 20, 1000 -> 346.7; std 0.85, 0.5, 0.1 -> 0.4833
    # window 2, the two seeds that reached 4000: returns 30, 60 -> 45; std 0.65, 0.3 (NaN left out) -> 0.475
    assert [row[1] for row in rows] == ["0k-2k", "2k-4k"]
    assert [row[header.index("seeds")] for row in rows] == ["3", "2"]
    assert [row[header.index("eval return")] for row in rows] == ["347", "45"]
    assert [row[header.index("std")] for row in rows] == ["0.483", "0.475"]
    assert [row[header.index("approx_kl")] for row in rows] == ["nan", "nan"]  # logged by no run
    assert "2.5k-5k" in training_logs.window_report(tmp_path, "Hopper-v5", [2500, 5000])  # labels keep fractions
    with pytest.raises(ValueError, match="positive"):
        training_logs.window_report(tmp_path, "Hopper-v5", [0, 2000])


def test_training_logs_peak_and_fall_by_hand(tmp_path):
    """Peak, final (last three evaluations), the runs falling > 20 %, the best mean of three consecutive evaluations
    (over the runs with three), the swing from one evaluation to the next over the second half and one evaluation's
    standard error there."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from engine import training_logs

    runs = (
        [10, 100, 20, 30, 40, 61],  # second half [30, 40, 61]: swing mean(10, 21) = 15.5
        [0, 60, 0, 60, 30],  # second half [0, 60, 30]: swing mean(60, 30) = 45
        [50, 70, 64],  # a smoothed peak, too short for a swing
        [50, 70],  # too short for either
    )
    for seed, returns in enumerate(runs):
        curve = [{"timesteps": 10_000 * (i + 1), "mean_return": r} for i, r in enumerate(returns)]
        spread = 10 * (seed + 1)  # two episodes r -+ spread: std spread, standard error spread / sqrt 2
        episodes = [[r - spread, r + spread] for r in returns]
        result = {"variant": "ppo", "curve": curve, "episode_returns": episodes}
        (tmp_path / f"Hopper-v5_ppo_seed{seed}.json").write_text(json.dumps(result))
    report = training_logs.report(tmp_path, "Hopper-v5")
    header = next(line for line in report.splitlines() if line.startswith("| variant | seeds")).split(" | ")
    row = dict(zip(header, next(line for line in report.splitlines() if line.startswith("| ppo")).split(" | ")))
    # peaks 100, 60, 70, 70 (mean 75) at 20k; finals 43.67, 30, 61.33, 60 (mean 48.75)
    assert [row["seeds"], row["peak"], row["at step (mean)"], row["final"]] == ["4", "75", "20k", "49"]
    assert [row["fall"], row["runs falling > 20 %"]] == ["-35 %", "2 of 4"]
    # smoothed peaks of the first three: mean(100, 20, 30) = 50, mean(60, 0, 60) = 40, 61.33 (mean 50.44); their
    # finals' mean 45: -11 %
    assert [row["smoothed peak"], row["fall from it"]] == ["50", "-11 %"]
    # swings 15.5 and 45 (mean 30.25); standard errors 10 / sqrt 2 and 20 / sqrt 2 (mean 10.6), runs of four or more
    assert [row["swing"], row["eval s.e. |"]] == ["30", "11 |"]
    assert training_logs.percent(1.0001) == "0 %" and training_logs.percent(0.9) == "-10 %"
    assert training_logs.thousands(1_000_000) == "1M" and training_logs.thousands(2500) == "2.5k"


@pytest.mark.parametrize(
    "name, key, base_value, value",
    [("learning_entropy.yml", "ent_coef", 0.0, 0.01), ("learning_lr_linear.yml", "learning_rate", 3e-4, "lin_0.0003")],
)
def test_fall_test_configs_change_one_hyperparameter_of_the_learning_config(name, key, base_value, value):
    """The fall tests' configs change one PPO hyperparameter of learning.yml, for both algorithms, on each task they
    list."""
    base = yaml.safe_load((ROOT / "benchmarks/hyperparams/learning.yml").read_text())
    changed = yaml.safe_load((ROOT / "benchmarks/hyperparams" / name).read_text())
    assert {"Hopper-v5", "Walker2d-v5"} <= set(changed)
    for env_id, entry in changed.items():
        assert base[env_id][key] == base_value and entry[key] == value, env_id
        assert {**entry, key: base[env_id][key]} == base[env_id], env_id
