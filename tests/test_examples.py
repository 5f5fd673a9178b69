"""Every example runs with its tiny-budget switch, so none can rot."""

import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).parents[1]
EXAMPLES = sorted(path.name for path in (ROOT / "examples").iterdir() if path.suffix in (".py", ".sh"))

#: What each example must leave in its output folder (beyond running without error)
OUTPUTS = {
    "local_generalization.py": "*.png",
    "global_generalization.py": "*.png",
    "embedding_maps.py": "*.png",
    "zero_shot_values.py": "*.png",
    "quickstart.py": "history.npz",
    "off_policy.py": "replay_buffer.snapshots.npz",
    "train_pevfa.py": "model.zip",
    "custom_representation.py": "*/progress.csv",
    "zoo_commands.sh": "plots/*.png",
    "optuna_search.py": "plots/optimization_history.png",
}


def test_every_example_is_covered():
    assert set(EXAMPLES) == set(OUTPUTS)


@pytest.mark.parametrize("example", EXAMPLES)
def test_example_runs_tiny(tmp_path, example):
    env = {**os.environ, "MPLBACKEND": "Agg"}
    path, out = ROOT / "examples" / example, tmp_path / "out"  # a folder the example makes
    if example.endswith(".sh"):
        command = ["bash", str(path)]
        env.update(TINY="1", LOGS=str(out))
    elif example == "optuna_search.py":
        command = [sys.executable, str(path), "--tiny", "--seed", "0", "--out", str(out)]
    else:
        command = [sys.executable, str(path), "--tiny", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    assert "does not exist. Will create it" not in result.stderr  # SB3's warning where a script saves blind
    if example == "optuna_search.py":
        assert "best of 2 trials" in result.stdout
        drawn = {p.name for p in (out / "plots").glob("optimization_history.*")}
        assert drawn == {"optimization_history.html", "optimization_history.png"}
    assert list(out.glob(OUTPUTS[example])), sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))[:50]
    if example == "off_policy.py":  # the diagnostic's state saved beside the model, for its resume
        assert (out / "diagnostic.pt").exists()
    if example == "train_pevfa.py":  # the steps it trained, not the ones asked for
        assert "after 1024 steps" in result.stdout
    if example == "zero_shot_values.py":
        assert "a smoke run (--tiny)" in result.stdout
    if example == "zoo_commands.sh":  # the training curve is drawn (coloured pixels), not an empty frame
        drawn = sorted(out.glob("plots/training_*.png"))
        assert drawn, sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*.png"))
        for png in drawn:
            assert _coloured_pixels(png) > 100, png


def _coloured_pixels(png: pathlib.Path) -> int:
    """Pixels of a figure that are neither white, black nor grey (its axes and labels): its curves and points."""
    import matplotlib.image

    rgb = matplotlib.image.imread(png)[..., :3]
    return int(((rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.2).sum())


#: What needs an extra: the command, the extra, one of its modules to hide
NEEDS_EXTRA = [
    (["examples/embedding_maps.py", "--tiny"], "diagnostics", "sklearn"),
    (["examples/global_generalization.py", "--tiny"], "diagnostics", "scipy"),
    (["examples/local_generalization.py", "--tiny"], "diagnostics", "matplotlib"),
    (["examples/zero_shot_values.py", "--tiny"], "diagnostics", "scipy"),
    (["examples/off_policy.py", "--tiny"], "diagnostics", "scipy"),
    (["examples/off_policy.py", "--tiny"], "mujoco", "mujoco"),  # its default env
    (["examples/train_pevfa.py", "--tiny", "--env", "Hopper-v5"], "mujoco", "mujoco"),
    (["examples/train_pevfa.py", "--tiny", "--env", "LunarLanderContinuous-v3"], "box2d", "Box2D"),
    (["examples/optuna_search.py", "--tiny"], "zoo", "rl_zoo3"),
    (["-m", "sb3_pevfa.train", "--algo", "ppo_pevfa", "--env", "CartPole-v1"], "zoo", "rl_zoo3"),
    (["-m", "sb3_pevfa.enjoy", "--algo", "ppo_pevfa", "--env", "CartPole-v1"], "zoo", "optuna"),
    (["-m", "sb3_pevfa.record_video", "--algo", "ppo_pevfa", "--env", "CartPole-v1"], "zoo", "rl_zoo3"),
    (["-c", "import sb3_pevfa.diagnostics"], "diagnostics", "scipy"),
]


@pytest.mark.parametrize(("command", "extra", "hidden"), NEEDS_EXTRA)
def test_without_its_extra_a_command_says_which_to_install(tmp_path, command, extra, hidden):
    """A module of the extra is hidden (as if not installed): one line naming the extra and its install command."""
    (tmp_path / "sitecustomize.py").write_text(
        "import sys\n\n\nclass Hide:\n    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] == {hidden!r}:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}')\n\n\nsys.meta_path.insert(0, Hide())\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, *command], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert result.returncode == 1
    install = f'pip install -e ".[{extra}]" in the repository\'s checkout'
    assert f"needs the '{extra}' extra (missing: {hidden}): {install}" in result.stderr
    if command[0] != "-c":  # a script: that line alone; an import in the user's code: a ModuleNotFoundError saying it
        assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    else:
        assert "ModuleNotFoundError: sb3_pevfa.diagnostics needs" in result.stderr


def test_embedding_maps_of_sacpevfas_snapshots_from_a_saved_model(tmp_path):
    """--algo picks the class of the saved model and its history (the snapshots, save_history's file)."""
    from sb3_pevfa import SACPeVFA

    model = SACPeVFA("MlpPolicy", "Pendulum-v1", learning_starts=100, snapshot_freq=50, batch_size=32,
                     policy_kwargs=dict(net_arch=[16]), seed=0)  # fmt: skip
    model.learn(400)  # 300 gradient steps: 1 + 6 snapshots
    model.save(tmp_path / "model")
    model.save_history(tmp_path / "snapshots")
    files = ["--model", str(tmp_path / "model.zip"), "--history", str(tmp_path / "snapshots.npz")]
    command = [sys.executable, str(ROOT / "examples" / "embedding_maps.py"), "--algo", "sac_pevfa", *files,
               "--out", str(tmp_path / "out")]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env={**os.environ, "MPLBACKEND": "Agg"})
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    assert "7 policies mapped" in result.stdout and (tmp_path / "out" / "embedding_maps.png").exists()
