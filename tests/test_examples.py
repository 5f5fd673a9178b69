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
    path = ROOT / "examples" / example
    if example.endswith(".sh"):
        command = ["bash", str(path)]
        env.update(TINY="1", LOGS=str(tmp_path))
    elif example == "optuna_search.py":
        command = [sys.executable, str(path), "--tiny", "--seed", "0", "--out", str(tmp_path)]
    else:
        command = [sys.executable, str(path), "--tiny", "--out", str(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    if example == "optuna_search.py":
        assert "best of 2 trials" in result.stdout
        drawn = {p.name for p in (tmp_path / "plots").glob("optimization_history.*")}
        assert drawn == {"optimization_history.html", "optimization_history.png"}
    assert list(tmp_path.glob(OUTPUTS[example])), sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))[:50]
