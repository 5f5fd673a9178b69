import csv
import os
import pathlib
import shutil
import socket
import subprocess
import tempfile

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure

th.set_num_threads(1)

#: Tiny PeVFA budget: 64-step rollouts, historical updates from the start.
FAST = dict(n_steps=64, batch_size=32, n_epochs=2, history_learning_starts=0, history_train_freq=16, seed=0)


class DictPendulum(gym.ObservationWrapper):
    """Pendulum with a Dict observation of two vector keys."""

    def __init__(self):
        super().__init__(gym.make("Pendulum-v1"))
        self.observation_space = gym.spaces.Dict(
            {"angle": gym.spaces.Box(-1, 1, (2,), np.float32), "speed": gym.spaces.Box(-8, 8, (1,), np.float32)}
        )

    def observation(self, observation):
        return {"angle": observation[:2], "speed": observation[2:]}


@pytest.fixture(autouse=True)
def distribution_argument_checks():
    """Each test starts with torch.distributions' argument checks on, as a process that never compiled: the first
    ``torch.compile`` (SB3's own save/load test) turns them off for the whole process (torch._dynamo's patch), and a
    NaN reaching a distribution would then pass silently in every later test of that pytest worker."""
    th.distributions.Distribution.set_default_validate_args(True)


def _can_flush_denormals() -> bool:
    flushed = th.set_flush_denormal(True)
    th.set_flush_denormal(False)
    return flushed


#: Skips a test of flushed denormals on a CPU that cannot flush them (``torch.set_flush_denormal``)
needs_denormal_flush = pytest.mark.skipif(
    not _can_flush_denormals(), reason="this CPU cannot flush denormals (torch.set_flush_denormal)"
)


def read_progress(folder: pathlib.Path) -> list[dict[str, str]]:
    with open(folder / "progress.csv") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture
def csv_logger(tmp_path):
    return configure(str(tmp_path / "logs"), ["csv"]), tmp_path / "logs"


def actor_parameters(policy) -> th.Tensor:
    return policy.layout.flatten(policy)


def module_parameters(module) -> th.Tensor:
    return th.cat([p.detach().flatten().clone() for p in module.parameters()])


#: PeVFA options under which a PeVFA algorithm is its SB3 base: no representation, no history, SB3's critic shape
AS_SB3 = dict(representation="none", history_train_freq=0, n_state_action_pairs=0)


def sb3_twin_runs(sb3_model, pevfa_model, timesteps: int) -> None:
    """Give the PeVFA model the SB3 model's weights, train both from the same global seeds, and check that they end
    with the same weights (SB3's ``value_net`` is the PeVFA head's ``output``)."""

    def renamed(key: str) -> str:
        return key.replace("value_net.", "value_net.output.", 1) if key.startswith("value_net.") else key

    weights = {renamed(k): v for k, v in sb3_model.policy.state_dict().items()}
    missing, unexpected = pevfa_model.policy.load_state_dict(weights, strict=False)
    assert not unexpected and all(k.startswith("behaviour") or k == "has_behaviour" for k in missing)
    for model in (sb3_model, pevfa_model):
        th.manual_seed(1)
        np.random.seed(1)
        model.learn(timesteps)
    assert pevfa_model._n_updates == sb3_model._n_updates
    for name, value in sb3_model.policy.state_dict().items():
        np.testing.assert_allclose(pevfa_model.policy.state_dict()[renamed(name)].numpy(), value.numpy(), atol=1e-5)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def postgres_url():
    """A throw-away PostgreSQL server on 127.0.0.1 (Debian's postgresql package; .ci/run installs it)."""
    tmp_path = pathlib.Path(tempfile.mkdtemp(prefix="sb3-pevfa-pg-"))  # outside pytest's 0700 folders
    candidates = sorted(pathlib.Path("/usr/lib/postgresql").glob("*/bin"))
    bindir = candidates[-1] if candidates else None
    initdb = bindir / "initdb" if bindir else shutil.which("initdb")
    pg_ctl = bindir / "pg_ctl" if bindir else shutil.which("pg_ctl")
    if not initdb or not pg_ctl or not pathlib.Path(initdb).exists():
        pytest.skip("No PostgreSQL server binaries (initdb, pg_ctl): install Debian's 'postgresql' package to run this test")
    as_user: list[str] = []
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root: use the package's postgres user
        if shutil.which("runuser") is None:
            pytest.skip("Running as root without runuser: cannot start PostgreSQL as an unprivileged user")
        as_user = ["runuser", "-u", "postgres", "--"]
        shutil.chown(tmp_path, "postgres")
    data, port = tmp_path / "pgdata", _free_port()
    started = subprocess.run(
        [*as_user, str(initdb), "-D", str(data), "-A", "trust", "-U", "postgres"], capture_output=True, text=True
    )
    if started.returncode == 0:
        options = f"-p {port} -k {tmp_path} -c listen_addresses=127.0.0.1"
        command = [*as_user, str(pg_ctl), "-D", str(data), "-o", options, "-l", str(tmp_path / "pg.log"), "-w", "start"]
        started = subprocess.run(command, capture_output=True, text=True)
    if started.returncode != 0:
        shutil.rmtree(tmp_path, ignore_errors=True)
        pytest.skip(f"Could not start a PostgreSQL server: {started.stderr.strip()[-500:]}")
    try:
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=port, user="postgres", dbname="postgres", autocommit=True) as connection:
            connection.execute("CREATE DATABASE optuna")
        yield f"postgresql://postgres@127.0.0.1:{port}/optuna"
    finally:
        subprocess.run([*as_user, str(pg_ctl), "-D", str(data), "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(tmp_path, ignore_errors=True)
