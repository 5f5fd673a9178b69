"""The documentation site builds with warnings as errors (the documented command), so docstrings and pages can't rot."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).parents[1]


def test_docs_build_without_warnings(tmp_path):
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(ROOT / "docs"), str(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-5000:]
    pages = {path.stem for path in tmp_path.glob("*.html")}
    assert {"index", "install", "quickstart", "algorithm", "representations", "history", "zoo", "diagnostics",
            "benchmarks", "api", "changelog"} <= pages  # fmt: skip
    api = (tmp_path / "api.html").read_text()
    assert "sb3_pevfa.PPOPeVFA" in api and "predict_values" in api  # autodoc found the docstrings
