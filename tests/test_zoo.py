"""rl-zoo3 and Optuna, through the real rl-zoo3 code paths and real storages, at tiny budgets."""

import importlib.util
import os
import pathlib
import re
import subprocess
import sys

import numpy as np
import optuna
import pytest
import yaml

from sb3_pevfa import A2CPeVFA, PPOPeVFA
from sb3_pevfa.pevfa.arguments import PEVFA_ARGUMENTS
from sb3_pevfa.pevfa.history import PolicyHistory
from sb3_pevfa.rl_zoo import ALGO_NAME, ALGORITHMS, HYPERPARAMS_PATH, HYPERPARAMS_PATHS, register

ROOT = pathlib.Path(__file__).resolve().parent.parent
OFF_POLICY = ("sac_pevfa", "td3_pevfa")
ENV = {**os.environ, "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _run(*args: str, cwd: pathlib.Path) -> str:
    result = subprocess.run([sys.executable, *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout + result.stderr


def _saved_config(path: pathlib.Path) -> dict:
    """The hyperparameters rl-zoo3 saved with a run (an OrderedDict in YAML)."""
    return dict(yaml.load(path.read_text(), Loader=yaml.UnsafeLoader))


def test_register_is_idempotent_and_fills_the_three_tables():
    from rl_zoo3 import ALGOS, hyperparams_opt, utils

    register()
    register()
    assert utils.ALGOS[ALGO_NAME] is PPOPeVFA and utils.ALGOS["a2c_pevfa"] is A2CPeVFA and ALGOS is utils.ALGOS
    for name in ALGORITHMS:
        assert name in hyperparams_opt.HYPERPARAMS_SAMPLER and name in hyperparams_opt.HYPERPARAMS_CONVERTER
        assert list(utils.ALGOS).count(name) == 1


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_shipped_hyperparameters(algo):
    import sb3_pevfa

    path = HYPERPARAMS_PATHS[algo]
    # inside the package (installed with it: package_data), and linked from the checkout's hyperparams/
    assert path.is_file() and path.parent.parent == pathlib.Path(sb3_pevfa.__file__).resolve().parent
    assert (ROOT / "hyperparams" / f"{algo}.yml").read_text() == path.read_text()
    config = yaml.safe_load(path.read_text())
    tasks = ["Hopper", "HalfCheetah", "Walker2d", "Ant", "InvertedPendulum", "InvertedDoublePendulum", "Swimmer", "Humanoid"]
    if algo in OFF_POLICY:  # continuous actions: rl-zoo3's entries but SAC's with gSDE
        expected = {f"{task}-v5" for task in tasks} | {"Pendulum-v1", "LunarLanderContinuous-v3"}
        expected |= {"MountainCarContinuous-v0", "BipedalWalker-v3"} if algo == "td3_pevfa" else set()
    else:
        expected = {f"{task}-v5" for task in tasks} | {
            "CartPole-v1",
            "Pendulum-v1",
            "Acrobot-v1",
            "MountainCarContinuous-v0",
            "LunarLander-v3",
        }
    assert expected <= set(config)
    base = algo.removesuffix("_pevfa")
    zoo = yaml.safe_load((pathlib.Path(__import__("rl_zoo3").__file__).parent / "hyperparams" / f"{base}.yml").read_text())
    if algo in ("ppo_pevfa", "a2c_pevfa"):  # every entry of rl-zoo3's ppo.yml / a2c.yml but PyBullet's and MiniGrid's
        names = {k.replace("-v2", "-v5") for k in zoo if "Bullet" not in k and not k.startswith("MiniGrid-")}
        assert names <= set(config), sorted(names - set(config))
    if algo in OFF_POLICY:  # and of sac.yml / td3.yml but PyBullet's, gSDE's (refused) and FetchReach (third-party)
        names = {k.replace("-v4", "-v5") for k, v in zoo.items() if "Bullet" not in k and not v.get("use_sde")}
        assert names - {"FetchReach-v1"} <= set(config), sorted(names - set(config))
    for env_id, params in config.items():
        assert params["representation"] == "opr"
        # PeVFA's own schedule only where it was measured (docs/notes/2026-12-02-zoo-tuned-history-cadence.md):
        # the tuned MuJoCo entries of PPOPeVFA
        tuned = algo == "ppo_pevfa" and env_id in ("Hopper-v5", "HalfCheetah-v5", "Walker2d-v5")
        assert {k for k in params if k in PEVFA_ARGUMENTS} == {"representation", "embedding_dim"} | (
            {"history_train_freq"} if tuned else set()
        ), env_id
        assert not tuned or params["history_train_freq"] == 160
        names = (env_id, env_id.replace("-v5", "-v4"), env_id.replace("-v5", "-v2"))
        source = next((zoo[k] for k in names if k in zoo), zoo["default"] if algo in OFF_POLICY else None)
        if source is not None:  # the PPO / A2C / SAC / TD3 part is rl-zoo3's, unchanged
            assert {k: v for k, v in params.items() if k not in PEVFA_ARGUMENTS} == {
                **source,
                "n_timesteps": float(source["n_timesteps"]),
            }


@pytest.fixture(scope="module")
def zoo_run(tmp_path_factory):
    """One rl-zoo3 training of ppo_pevfa on CartPole-v1, saving the history as rl-zoo3's replay buffer."""
    folder = tmp_path_factory.mktemp("zoo")
    # a constant learning rate (the zoo's CartPole entry decays it to 0 at the last update): every update is a new policy
    log = _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-n", "768", "-f", str(folder),
               "--seed", "0", "--save-replay-buffer", "--eval-freq", "-1", "--hyperparams", "learning_rate:0.001",
               "--save-freq", "512", cwd=folder)  # fmt: skip
    assert "Loading hyperparameters from: " + str(HYPERPARAMS_PATH) in log
    return folder


def test_zoo_train_enjoy_and_continue_with_history(zoo_run):
    run = zoo_run / "ppo_pevfa" / "CartPole-v1_1"
    assert (run / "CartPole-v1.zip").exists() and (run / "replay_buffer.pkl").exists()
    log = _run("-m", "sb3_pevfa.enjoy", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-f", str(zoo_run), "-n", "200",
               "--no-render", cwd=zoo_run)  # fmt: skip
    assert "Mean reward" in log or "Atari Episode" in log or "Episode Reward" in log
    log = _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-n", "256", "-f", str(zoo_run),
               "-i", str(run / "CartPole-v1.zip"), "--save-replay-buffer", "--eval-freq", "-1", "--hyperparams",
               "learning_rate:0.001", cwd=zoo_run)  # fmt: skip
    assert "Loading replay buffer" in log
    first = PPOPeVFA.load(run / "CartPole-v1.zip")
    first.load_history(run / "replay_buffer.pkl")
    second = PPOPeVFA.load(zoo_run / "ppo_pevfa" / "CartPole-v1_2" / "CartPole-v1.zip")
    second.load_history(zoo_run / "ppo_pevfa" / "CartPole-v1_2" / "replay_buffer.pkl")
    # the continued run kept every policy of the first one and added its own
    assert set(first.history.policy_ids) < set(second.history.policy_ids)
    assert second.history.n_samples == first.history.n_samples + 256
    assert second.history.record_info(0)["num_timesteps"] == 0


def test_zoo_trains_a2c_pevfa_with_its_shipped_hyperparameters(tmp_path):
    log = _run("-m", "sb3_pevfa.train", "--algo", "a2c_pevfa", "--env", "CartPole-v1", "-n", "400", "-f", str(tmp_path),
               "--seed", "0", "--save-replay-buffer", "--eval-freq", "-1", cwd=tmp_path)  # fmt: skip
    assert "Loading hyperparameters from: " + str(HYPERPARAMS_PATHS["a2c_pevfa"]) in log
    run = tmp_path / "a2c_pevfa" / "CartPole-v1_1"
    model = A2CPeVFA.load(run / "CartPole-v1.zip")
    model.load_history(run / "replay_buffer.pkl")
    # rl-zoo3's CartPole entry: 8 envs x 5 steps per update, 10 updates and the final policy
    assert model.n_envs == 8 and model.history.n_samples == 400 and model.history.n_policies == 11


def test_zoo_record_video(zoo_run):
    out = zoo_run / "videos"
    _run("-m", "sb3_pevfa.record_video", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-f", str(zoo_run), "-n", "20",
         "-o", str(out), cwd=zoo_run)  # fmt: skip
    assert list(out.glob("*.mp4"))


def test_zoo_pendulum_and_user_conf_file_wins(tmp_path):
    conf = tmp_path / "mine.yml"
    conf.write_text(
        yaml.safe_dump({"Pendulum-v1": {"policy": "MlpPolicy", "n_timesteps": 1e5, "n_steps": 64, "representation": "spr"}})
    )
    log = _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "Pendulum-v1", "-n", "128", "-f", str(tmp_path),
               "--conf-file", str(conf), "--eval-freq", "-1", cwd=tmp_path)  # fmt: skip
    assert f"Loading hyperparameters from: {conf}" in log
    saved = _saved_config(tmp_path / "ppo_pevfa" / "Pendulum-v1_1" / "Pendulum-v1" / "config.yml")
    assert saved["representation"] == "spr"


def test_zoo_optimize_then_rerun_a_trial(tmp_path):
    storage = tmp_path / "study.log"
    log = _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-optimize", "--n-trials", "2",
               "-n", "256", "--search-space", "small", "--storage", str(storage), "--study-name", "zoo", "--n-evaluations",
               "1", "--eval-episodes", "2", "-f", str(tmp_path), "--no-optim-plots", "--seed", "1", cwd=tmp_path)  # fmt: skip
    assert "Number of finished trials:  2" in log
    study = optuna.load_study(
        storage=optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(storage))), study_name="zoo"
    )
    params = study.trials[1].params
    assert {"representation", "history_train_freq", "critic_learning_rate", "n_steps_pow"} <= set(params)
    # rl-zoo3 skips --trial-id 0 (it tests `if trial_id`): re-run trial 1
    _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-n", "128", "--search-space", "small",
         "--storage", str(storage), "--study-name", "zoo", "--trial-id", "1", "-f", str(tmp_path / "rerun"),
         "--eval-freq", "-1", cwd=tmp_path)  # fmt: skip
    saved = _saved_config(next((tmp_path / "rerun").rglob("config.yml")))
    assert saved["representation"] == params["representation"]
    assert saved["critic_learning_rate"] == pytest.approx(params["critic_learning_rate"])
    assert saved["n_steps"] == 2 ** params["n_steps_pow"]


def _two_workers(storage: str, cwd: pathlib.Path, study_name: str = "shared") -> optuna.Study:
    command = [sys.executable, str(ROOT / "examples" / "optuna_search.py"), "--storage", storage, "--study-name", study_name,
               "--n-trials", "2", "--timesteps", "128", "--n-evaluations", "1", "--eval-episodes", "1",
               "--search-space", "small"]  # fmt: skip
    # the recipe: create the study (and the database schema) once, then start the workers
    loaded_storage = (
        optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(storage))
        if storage.endswith(".log")
        else storage
    )
    optuna.create_study(storage=loaded_storage, study_name=study_name, direction="maximize")
    workers = [
        subprocess.Popen([*command, "--out", str(cwd / f"worker{i}")], cwd=cwd, env=ENV, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
        for i in range(2)
    ]  # fmt: skip
    ran = []  # the trial numbers each worker reports (Optuna's log: "Trial <n> finished" / "pruned")
    for worker in workers:
        output, _ = worker.communicate(timeout=600)
        assert worker.returncode == 0, output[-3000:]
        ran.append({int(n) for n in re.findall(r"Trial (\d+) (?:finished|pruned)", output)})
    study = optuna.load_study(storage=loaded_storage, study_name=study_name)
    assert len(study.trials) == 4
    assert len(ran[0]) == len(ran[1]) == 2 and ran[0] | ran[1] == {0, 1, 2, 3}  # two workers, one study
    assert all(t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED) for t in study.trials)
    return study


def test_optuna_example_keeps_the_entrys_envs_and_normalization(tmp_path, monkeypatch):
    """The example's trials run through rl-zoo3's ExperimentManager: Acrobot-v1's entry (16 envs, VecNormalize) is
    kept, where the former hand-written objective built one unnormalized env."""
    spec = importlib.util.spec_from_file_location("optuna_search", ROOT / "examples" / "optuna_search.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    seen, learn = [], PPOPeVFA.learn

    def spy(self, *args, **kwargs):
        seen.append((self.n_envs, type(self.get_vec_normalize_env()).__name__, self.representation))
        return learn(self, *args, **kwargs)

    monkeypatch.setattr(PPOPeVFA, "learn", spy)
    monkeypatch.setattr(sys, "argv", [sys.argv[0]])
    monkeypatch.chdir(tmp_path)
    example.main(["--env", "Acrobot-v1", "--tiny", "--seed", "0", "--out", str(tmp_path)])
    study = optuna.load_study(  # the example's default storage and study name
        study_name="ppo_pevfa-Acrobot-v1",
        storage=optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(tmp_path / "study.log"))),
    )
    assert seen == [(16, "VecNormalize", trial.params["representation"]) for trial in study.trials]


@pytest.mark.parametrize("kind", ["journal", "sqlite"])
def test_two_workers_share_one_study(tmp_path, kind):
    storage = str(tmp_path / "study.log") if kind == "journal" else f"sqlite:///{tmp_path / 'study.db'}"
    _two_workers(storage, tmp_path)


def test_two_workers_share_one_study_on_postgresql(tmp_path, postgres_url):
    study = _two_workers(postgres_url, tmp_path, study_name="pg")
    assert study.best_trial is not None or all(t.state == optuna.trial.TrialState.PRUNED for t in study.trials)


def test_history_file_keeps_the_zoo_name(tmp_path):
    history = PolicyHistory(
        __import__("gymnasium").spaces.Box(-1, 1, (2,)),
        __import__("gymnasium").spaces.Discrete(2),
        n_params=3,
        n_state_action_pairs=0,
    )
    history.save(tmp_path / "replay_buffer.pkl")
    assert (tmp_path / "replay_buffer.pkl").exists() and not (tmp_path / "replay_buffer.pkl.npz").exists()


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
@pytest.mark.parametrize("space", ["full", "small"])
def test_sampler_and_converter_agree(space, algo):
    """What a trial trains with (sampler) is what --trial-id rebuilds from its stored parameters (converter)."""
    from sb3_pevfa.rl_zoo.hyperparams_opt import CONVERTERS, SAMPLERS, SEARCH_SPACE

    SEARCH_SPACE["name"] = space
    try:
        study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
        for _ in range(20):
            trial = study.ask()
            sampled = SAMPLERS[algo](trial, 1, 1, {"using_her_replay_buffer": False})
            converted = CONVERTERS[algo](trial.params)
            # TD3: the converter keeps rl-zoo3's noise_type / noise_std, which its experiment manager turns into the
            # action noise that the sampler builds
            noise_type, noise_std = converted.pop("noise_type", None), converted.pop("noise_std", None)
            noise = sampled.pop("action_noise", None)
            assert converted == sampled
            kinds = {None: None, "normal": "NormalActionNoise", "ornstein-uhlenbeck": "OrnsteinUhlenbeckActionNoise"}
            assert kinds[noise_type] == (type(noise).__name__ if noise is not None else None)
            assert noise is None or np.allclose(noise._sigma, noise_std)
            sampled = {**sampled, **({"action_noise": noise} if noise is not None else {})}
            if algo in OFF_POLICY:
                model = ALGORITHMS[algo]("MlpPolicy", "Pendulum-v1", **sampled)
            else:
                kwargs = {k: v for k, v in sampled.items() if k != "n_steps"}
                model = ALGORITHMS[algo]("MlpPolicy", "CartPole-v1", **kwargs, n_steps=64)
            assert model.policy.representation_name == sampled["representation"]
            study.tell(trial, 0.0)
    finally:
        SEARCH_SPACE["name"] = "full"


def test_zoo_checkpoints_keep_the_history_of_their_moment(zoo_run):
    """--save-freq saves the history with each checkpoint, and -i <checkpoint> continues with that history, not the
    run's final replay_buffer.pkl beside it."""
    run = zoo_run / "ppo_pevfa" / "CartPole-v1_1"
    assert (run / "rl_model_512_steps.zip").exists() and (run / "rl_model_replay_buffer_512_steps.pkl").exists()
    saved = PPOPeVFA.load(run / "rl_model_512_steps.zip").history
    final = PPOPeVFA.load(run / "CartPole-v1.zip")
    final.load_history(run / "replay_buffer.pkl")
    # CartPole-v1's entry: 8 envs x 32 steps; the checkpoint came in the second rollout's last step
    assert saved.n_samples == 256 and final.history.n_samples == 768
    before = set((zoo_run / "ppo_pevfa").iterdir())
    log = _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1", "-n", "256", "-f", str(zoo_run),
               "-i", str(run / "rl_model_512_steps.zip"), "--save-replay-buffer", "--eval-freq", "-1", "--hyperparams",
               "learning_rate:0.001", cwd=zoo_run)  # fmt: skip
    assert "Loading the history saved with the checkpoint at 512 steps" in log
    (continued,) = set((zoo_run / "ppo_pevfa").iterdir()) - before
    model = PPOPeVFA.load(continued / "CartPole-v1.zip")
    model.load_history(continued / "replay_buffer.pkl")
    assert model.history.n_samples == 256 + 256
    np.testing.assert_array_equal(model.history.samples()[0][:256], saved.samples()[0])


@pytest.mark.parametrize("command", ["enjoy", "record_video"])
def test_enjoy_and_record_video_load_the_off_policy_algorithms_with_one_transitions_buffer(tmp_path, monkeypatch, command):
    """rl-zoo3's enjoy and record_video pass buffer_size=1 to the off-policy algorithms they list (SAC, TD3, ...), not
    to ours: the package's commands load them so too (rl-zoo3's call, its arguments), and leave rl-zoo3's table as
    it was."""
    import runpy

    import rl_zoo3.enjoy
    from rl_zoo3 import ALGOS

    import sb3_pevfa.enjoy
    import sb3_pevfa.record_video
    from sb3_pevfa import SACPeVFA

    SACPeVFA("MlpPolicy", "Pendulum-v1", buffer_size=5000, policy_kwargs=dict(net_arch=[8])).save(tmp_path / "sac")
    PPOPeVFA("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8])).save(tmp_path / "ppo")
    loaded = []

    def zoo_script(*_: object, **__: object) -> None:  # rl-zoo3's load: its custom objects, device and seed
        for name in ("sac_pevfa", "ppo_pevfa"):
            kwargs = dict(seed=0, **(dict(buffer_size=1) if name in ("sac", "td3") else {}))  # rl-zoo3's own list
            model = ALGOS[name].load(tmp_path / name.partition("_")[0], custom_objects={"learning_rate": 0.0},
                                     device="cpu", **kwargs)  # fmt: skip
            loaded.append(model)

    monkeypatch.setattr(rl_zoo3.enjoy, "enjoy", zoo_script)
    monkeypatch.setattr(runpy, "run_module", zoo_script)
    monkeypatch.setattr(sys, "argv", [command])
    {"enjoy": sb3_pevfa.enjoy, "record_video": sb3_pevfa.record_video}[command].main(["--algo", "sac_pevfa"])
    assert loaded[0].buffer_size == 1 and loaded[0].replay_buffer.buffer_size == 1 and type(loaded[0]) is SACPeVFA
    assert type(loaded[1]) is PPOPeVFA
    assert ALGOS["sac_pevfa"] is SACPeVFA and ALGOS["td3_pevfa"].__name__ == "TD3PeVFA"  # restored
    assert ALGOS["sac_pevfa"].load(tmp_path / "sac").buffer_size == 5000  # elsewhere (training's -i): as saved


@pytest.mark.parametrize(
    "given",
    [["--conf-file", "mine.yml"], ["--conf-file=mine.yml"], ["--conf", "mine.yml"], ["-conf=mine.yml"], []],
)
def test_the_users_conf_file_in_any_form_rl_zoo3_reads_wins_and_our_flag_is_read_in_both(given, monkeypatch):
    """What reaches rl-zoo3's parser: the user's --conf-file however written (else the shipped file), and
    --search-space, ours, removed (train only: enjoy's parser has no such flag to hide)."""
    from sb3_pevfa.rl_zoo import hyperparams_opt, run_zoo_script

    seen = []
    monkeypatch.setattr(sys, "argv", ["train"])
    monkeypatch.setitem(hyperparams_opt.SEARCH_SPACE, "name", "full")
    run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", *given, "--search-space=small"], True)
    shipped = ["--conf-file", str(HYPERPARAMS_PATHS["sac_pevfa"])]
    assert seen[0] == ["--algo", "sac_pevfa", *given, *(shipped if not given else [])]
    assert hyperparams_opt.SEARCH_SPACE["name"] == "small"
    run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", "--search-space", "small"], False)
    assert seen[1] == ["--algo", "sac_pevfa", "--search-space", "small"]  # enjoy: rl-zoo3 says it is unknown
    # an entry left out of the shipped file: why, rather than rl-zoo3's "Hyperparameters not found"
    with pytest.raises(SystemExit, match=r"SAC entry explores with gSDE .* Give an entry of your own with --conf-file"):
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", "--env", "BipedalWalker-v3"], True)
    with pytest.raises(SystemExit, match="No shipped sac_pevfa hyperparameters for MountainCarContinuous-v0"):
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo=sac_pevfa", "--env=MountainCarContinuous-v0"], True)
    run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "td3_pevfa", "--env", "BipedalWalker-v3"], True)
    # rl-zoo3's entries the shipped files leave out: why, rather than training them with the shipped default
    bullet = r"for HalfCheetahBulletEnv-v0: rl-zoo3's td3.yml entry for it is left out \(PyBullet's, MiniGrid's and"
    with pytest.raises(SystemExit, match=bullet):
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "td3_pevfa", "--env", "HalfCheetahBulletEnv-v0"], True)
    with pytest.raises(SystemExit, match=r"for Hopper-v4: rl-zoo3's sac.yml entry for it is shipped as Hopper-v5's\."):
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", "--env", "Hopper-v4"], True)
    with pytest.raises(SystemExit, match=r"for MiniGrid-DoorKey-5x5-v0: rl-zoo3's ppo.yml entry for it is left out"):
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "ppo_pevfa", "--env", "MiniGrid-DoorKey-5x5-v0"], True)
    run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", "--env", "Reacher-v5"], True)  # default
    if given:  # with an entry of the user's, it runs
        run_zoo_script(lambda: seen.append(sys.argv[1:]), ["--algo", "sac_pevfa", "--env", "BipedalWalker-v3", *given], True)
    assert len(seen) == 4 + bool(given)


def test_help_shows_our_flag_and_the_python_way_of_the_docs_works(tmp_path):
    assert "--search-space {full,small}" in _run("-m", "sb3_pevfa.train", "--help", cwd=tmp_path)
    # docs/zoo.md: register, then rl-zoo3's own train() with the shipped hyperparameters as --conf-file
    code = (
        "import sys, sb3_pevfa.rl_zoo as zoo\n"
        "zoo.register()\n"
        "sys.argv = ['train', '--algo', 'ppo_pevfa', '--env', 'CartPole-v1', '--conf-file', str(zoo.HYPERPARAMS_PATH),"
        " '-n', '256', '-f', 'logs', '--eval-freq', '-1']\n"
        "from rl_zoo3.train import train\n"
        "train()\n"
    )
    _run("-c", code, cwd=tmp_path)
    assert (tmp_path / "logs" / "ppo_pevfa" / "CartPole-v1_1" / "CartPole-v1.zip").exists()


ENTRIES = sorted(yaml.safe_load(HYPERPARAMS_PATH.read_text()))


@pytest.mark.parametrize("entry", ENTRIES)
def test_every_shipped_entry_builds_a_model(entry, tmp_path):
    """rl-zoo3's experiment manager builds (does not train) PPOPeVFA from each entry whose env is installed here:
    its PPO settings as written, its PeVFA ones; ``default`` through an env without an entry (CartPole-v0)."""
    import argparse

    import gymnasium as gym
    from rl_zoo3.exp_manager import ExperimentManager

    env_id = {"default": "CartPole-v0", "atari": "PongNoFrameskip-v4"}.get(entry, entry)
    try:
        gym.make(env_id).close()
    except (gym.error.DependencyNotInstalled, gym.error.NameNotFound, gym.error.NamespaceNotFound, ImportError) as error:
        pytest.skip(f"{env_id} cannot be made here: {error}")
    register()
    manager = ExperimentManager(argparse.Namespace(), ALGO_NAME, env_id, str(tmp_path), n_timesteps=1000, eval_freq=-1,
                                config=str(HYPERPARAMS_PATH), verbose=0)  # fmt: skip
    try:
        model, _ = manager.setup_experiment()
    except gym.error.DependencyNotInstalled as error:  # CarRacing-v3's zoo wrappers resize frames with OpenCV
        pytest.skip(f"{env_id}'s zoo wrappers cannot be made here: {error}")
    params = yaml.safe_load(HYPERPARAMS_PATH.read_text())[entry]
    assert isinstance(model, PPOPeVFA) and model.representation == params["representation"]
    assert model.n_steps == params.get("n_steps", 2048) and model.n_envs == params.get("n_envs", 1)
    assert model.batch_size == params.get("batch_size", 64) and model.gamma == params.get("gamma", 0.99)
    model.env.close()


def test_headless_enjoy_and_video_of_a_mujoco_task(tmp_path):
    """docs/zoo.md's headless way: enjoy with --no-render; record_video of a MuJoCo task with MUJOCO_GL=egl."""
    probe = "import gymnasium as gym; e = gym.make('InvertedPendulum-v5', render_mode='rgb_array'); e.reset(); e.render()"
    egl = {**ENV, "MUJOCO_GL": "egl"}
    if subprocess.run([sys.executable, "-c", probe], env=egl, capture_output=True, timeout=120).returncode != 0:
        pytest.skip("MuJoCo cannot render with EGL here (Debian: apt-get install libegl1 libegl-mesa0)")
    _run("-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "InvertedPendulum-v5", "-n", "64", "-f", str(tmp_path),
         "--eval-freq", "-1", cwd=tmp_path)  # fmt: skip
    # 1000 steps: at least one whole episode (the task's time limit), where 50 could end none (an untrained policy
    # balances the pole for 20 to 60 steps) and print nothing
    log = _run("-m", "sb3_pevfa.enjoy", "--algo", "ppo_pevfa", "--env", "InvertedPendulum-v5", "-f", str(tmp_path),
               "-n", "1000", "--no-render", cwd=tmp_path)  # fmt: skip
    assert "Episode Reward:" in log and "Mean reward:" in log
    out = tmp_path / "videos"
    result = subprocess.run([sys.executable, "-m", "sb3_pevfa.record_video", "--algo", "ppo_pevfa", "--env",
                             "InvertedPendulum-v5", "-f", str(tmp_path), "-n", "20", "-o", str(out)], cwd=tmp_path,
                            env=egl, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert list(out.glob("*.mp4"))


OFF_POLICY_ENTRIES = [
    (algo, entry) for algo in OFF_POLICY for entry in sorted(yaml.safe_load(HYPERPARAMS_PATHS[algo].read_text()))
]


@pytest.mark.parametrize(("algo", "entry"), OFF_POLICY_ENTRIES)
def test_every_shipped_off_policy_entry_builds_a_model(algo, entry, tmp_path):
    """rl-zoo3's experiment manager builds SACPeVFA / TD3PeVFA from each entry whose env is installed here, with the
    entry's SAC / TD3 settings and its representation."""
    import argparse

    import gymnasium as gym
    from rl_zoo3.exp_manager import ExperimentManager

    env_id = {"default": "Reacher-v5"}.get(entry, entry)  # an env without an entry of its own
    try:
        gym.make(env_id).close()
    except (gym.error.DependencyNotInstalled, gym.error.NameNotFound, ImportError) as error:
        pytest.skip(f"{env_id} cannot be made here: {error}")
    register()
    manager = ExperimentManager(argparse.Namespace(), algo, env_id, str(tmp_path), n_timesteps=1000, eval_freq=-1,
                                config=str(HYPERPARAMS_PATHS[algo]), verbose=0)  # fmt: skip
    model, _ = manager.setup_experiment()
    params = yaml.safe_load(HYPERPARAMS_PATHS[algo].read_text())[entry]
    assert isinstance(model, ALGORITHMS[algo]) and model.policy.representation_name == params["representation"]
    assert model.learning_starts == params.get("learning_starts", 100) and model.gamma == params.get("gamma", 0.99)
    assert model.batch_size == params.get("batch_size", 256) and model.buffer_size == params.get("buffer_size", 1_000_000)
    model.env.close()


@pytest.mark.parametrize("algo", OFF_POLICY)
def test_zoo_trains_and_continues_off_policy_pevfa_with_its_snapshots(algo, tmp_path):
    """--save-replay-buffer saves the snapshots beside the replay buffer, and -i continues with both."""
    args = ["--env", "Pendulum-v1", "-f", str(tmp_path), "--seed", "0", "--save-replay-buffer", "--eval-freq", "-1",
            "--hyperparams", "learning_starts:100", "snapshot_freq:50", "buffer_size:5000"]  # fmt: skip
    log = _run("-m", "sb3_pevfa.train", "--algo", algo, "-n", "300", *args, cwd=tmp_path)
    assert "Loading hyperparameters from: " + str(HYPERPARAMS_PATHS[algo]) in log
    run = tmp_path / algo / "Pendulum-v1_1"
    first = ALGORITHMS[algo].load(run / "Pendulum-v1.zip")
    first.load_replay_buffer(run / "replay_buffer.pkl")
    assert first.history.policy_ids == [0, 1, 2, 3, 4] and first.replay_buffer.size() == 300  # 200 gradient steps
    # rl-zoo3 learns on with reset_num_timesteps: learning_starts again, then 100 gradient steps
    _run("-m", "sb3_pevfa.train", "--algo", algo, "-n", "200", "-i", str(run / "Pendulum-v1.zip"), *args, cwd=tmp_path)
    second = ALGORITHMS[algo].load(tmp_path / algo / "Pendulum-v1_2" / "Pendulum-v1.zip")
    second.load_replay_buffer(tmp_path / algo / "Pendulum-v1_2" / "replay_buffer.pkl")
    assert second.history.policy_ids == [0, 1, 2, 3, 4, 5, 6] and second.replay_buffer.size() == 500
    np.testing.assert_array_equal(second.history.records([3])["params"], first.history.records([3])["params"])


def test_zoo_optimizes_sac_pevfa_then_reruns_a_trial(tmp_path):
    storage = tmp_path / "study.log"
    log = _run("-m", "sb3_pevfa.train", "--algo", "sac_pevfa", "--env", "Pendulum-v1", "-optimize", "--n-trials", "2",
               "-n", "200", "--search-space", "small", "--storage", str(storage), "--study-name", "zoo",
               "--n-evaluations", "1", "--eval-episodes", "1", "-f", str(tmp_path), "--no-optim-plots", "--seed", "1",
               "--hyperparams", "learning_starts:50", cwd=tmp_path)  # fmt: skip
    assert "Number of finished trials:  2" in log
    study = optuna.load_study(
        storage=optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(storage))), study_name="zoo"
    )
    params = study.trials[1].params
    assert {"representation", "snapshot_freq", "history_train_freq", "batch_size_pow", "tau"} <= set(params)
    _run("-m", "sb3_pevfa.train", "--algo", "sac_pevfa", "--env", "Pendulum-v1", "-n", "100", "--search-space", "small",
         "--storage", str(storage), "--study-name", "zoo", "--trial-id", "1", "-f", str(tmp_path / "rerun"),
         "--eval-freq", "-1", "--hyperparams", "learning_starts:50", cwd=tmp_path)  # fmt: skip
    saved = _saved_config(next((tmp_path / "rerun").rglob("config.yml")))
    assert saved["representation"] == params["representation"] and saved["snapshot_freq"] == params["snapshot_freq"]
    assert saved["batch_size"] == 2 ** params["batch_size_pow"] and saved["tau"] == pytest.approx(params["tau"])


OBJECTIVES = {"e2e": (), "cl": ("cl",), "aux": ("aux",), "cl+aux": ("cl", "aux")}


@pytest.mark.parametrize("space", ["full", "small"])
@pytest.mark.parametrize("algo", ["ppo_pevfa", "a2c_pevfa"])
def test_on_policy_samplers_reach_the_kwargs(space, algo, monkeypatch):
    """What a trial samples reaches the model's arguments: a history of 2**pow samples larger than one rollout of all
    envs, the critic's learning rate (log scale), the objectives of OPR and SPR, the small space's fixed starts."""
    from sb3_pevfa.rl_zoo.hyperparams_opt import SAMPLERS, SEARCH_SPACE

    monkeypatch.setitem(SEARCH_SPACE, "name", space)
    n_envs, low = 16, (10 if space == "small" else 14)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(40):
        trial = study.ask()
        sampled = SAMPLERS[algo](trial, 1, n_envs, {})
        raw = trial.params
        rollout = sampled["n_steps"] * n_envs
        assert sampled["history_buffer_size"] == 2 ** raw["history_buffer_size_pow"]
        pow_low = trial.distributions["history_buffer_size_pow"].low
        if 2 ** trial.distributions["history_buffer_size_pow"].high > rollout:
            assert 2**pow_low > rollout
            assert sampled["history_buffer_size"] > rollout
            assert pow_low == low or 2 ** (pow_low - 1) <= rollout  # the smallest history larger than a rollout
        assert sampled["critic_learning_rate"] == raw["critic_learning_rate"]
        assert trial.distributions["critic_learning_rate"].log
        assert sampled["history_train_freq"] == raw["history_train_freq"]
        assert ("objectives" in raw) == (raw["representation"] in ("opr", "spr"))
        assert sampled["representation_objectives"] == OBJECTIVES[raw.get("objectives", "e2e")]
        if space == "small":
            assert sampled["history_learning_starts"] == 0
            assert sampled["objective_kwargs"] == {o: {"learning_starts": 0} for o in sampled["representation_objectives"]}
        else:
            assert "history_learning_starts" not in sampled
        study.tell(trial, 0.0)
