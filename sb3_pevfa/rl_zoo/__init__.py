"""rl-zoo3 integration: ``ppo_pevfa``, ``a2c_pevfa``, ``sac_pevfa`` and ``td3_pevfa`` in rl-zoo3's tables without a
fork (see :func:`register`)."""

import argparse
import pathlib
import sys
from collections.abc import Callable

from sb3_pevfa.a2c_pevfa import A2CPeVFA
from sb3_pevfa.ppo_pevfa import PPOPeVFA
from sb3_pevfa.sac_pevfa import SACPeVFA
from sb3_pevfa.td3_pevfa import TD3PeVFA

ALGO_NAME = "ppo_pevfa"
#: The PeVFA algorithms under their rl-zoo3 names.
ALGORITHMS = {ALGO_NAME: PPOPeVFA, "a2c_pevfa": A2CPeVFA, "sac_pevfa": SACPeVFA, "td3_pevfa": TD3PeVFA}
#: The shipped hyperparameters of each algorithm (installed with the package).
HYPERPARAMS_PATHS = {
    name: pathlib.Path(__file__).resolve().parent.parent / "hyperparams" / f"{name}.yml" for name in ALGORITHMS
}
HYPERPARAMS_PATH = HYPERPARAMS_PATHS[ALGO_NAME]
#: The off-policy ones (a replay buffer)
OFF_POLICY_ALGORITHMS = ("sac_pevfa", "td3_pevfa")
#: rl-zoo3's entries that the shipped hyperparameters leave out, because the algorithm refuses them: why
LEFT_OUT = {
    "sac_pevfa": dict.fromkeys(
        ("MountainCarContinuous-v0", "BipedalWalker-v3", "CarRacing-v3", "NeckEnvRelative-v2", "donkey-generated-track-v0"),
        "rl-zoo3's SAC entry explores with gSDE (use_sde=True), which SACPeVFA does not take (its snapshots are actors "
        "of linear layers)",
    ),
}


def left_out(algo: str, env: str | None) -> str | None:
    """Why the shipped hyperparameters of ``algo`` have no entry for ``env`` where rl-zoo3's have one (its own
    fallback, the shipped ``default``, would otherwise train it in settings other than rl-zoo3's entry); None where
    they have one, or rl-zoo3 has none either."""
    import rl_zoo3
    import yaml

    shipped = yaml.safe_load(HYPERPARAMS_PATHS[algo].read_text()) if algo in HYPERPARAMS_PATHS else {}
    if env is None or not shipped or env in shipped:
        return None
    if env in LEFT_OUT.get(algo, {}):
        return LEFT_OUT[algo][env]
    base = algo.removesuffix("_pevfa")
    if env not in yaml.safe_load((pathlib.Path(rl_zoo3.__file__).parent / "hyperparams" / f"{base}.yml").read_text()):
        return None
    versions = [name for name in shipped if name.rpartition("-v")[0] == env.rpartition("-v")[0]]
    if versions:  # rl-zoo3's entry of an older version, shipped for the current one
        return f"rl-zoo3's {base}.yml entry for it is shipped as {versions[0]}'s"
    return (f"rl-zoo3's {base}.yml entry for it is left out (PyBullet's, MiniGrid's and third-party tasks are not "
            "dependencies of the package), and the shipped 'default' would train it otherwise")  # fmt: skip


def register() -> None:
    """Add the PeVFA algorithms (:data:`ALGORITHMS`) to rl-zoo3's algorithm table (``rl_zoo3.utils.ALGOS``), Optuna sampler
    table and trial converter table (``rl_zoo3.hyperparams_opt``). These module-level dicts are shared by ``train``, ``enjoy``,
    ``record_video`` and the experiment manager, so one call is enough; calling it again changes nothing."""
    from rl_zoo3 import hyperparams_opt, utils

    from sb3_pevfa.rl_zoo.hyperparams_opt import CONVERTERS, SAMPLERS

    for name, algorithm in ALGORITHMS.items():
        utils.ALGOS[name] = algorithm
        hyperparams_opt.HYPERPARAMS_SAMPLER[name] = SAMPLERS[name]
        hyperparams_opt.HYPERPARAMS_CONVERTER[name] = CONVERTERS[name]


class LoadsWithoutReplayBuffer:
    """An algorithm class whose ``load`` builds a replay buffer of one transition (what rl-zoo3's ``enjoy`` and
    ``record_video`` pass to the off-policy algorithms they list, which the PeVFA ones are not among)."""

    def __init__(self, algorithm: type):
        self.algorithm = algorithm

    def __getattr__(self, name: str) -> object:
        return getattr(self.algorithm, name)

    def load(self, *args: object, **kwargs: object) -> object:
        kwargs.setdefault("buffer_size", 1)
        return self.algorithm.load(*args, **kwargs)


def run_zoo_script(
    script: Callable[[], None], argv: list[str] | None = None, default_config: bool = False, watch: bool = False
) -> None:
    """Run an rl-zoo3 command-line function with ``ppo_pevfa`` registered and rl-zoo3's flags unchanged.

    :param default_config: Training: add ``--conf-file`` pointing at the shipped hyperparameters when a PeVFA algorithm
        (``--algo ppo_pevfa``, ``a2c_pevfa``, ``sac_pevfa``, ``td3_pevfa``) is trained without one (a user's
        ``--conf-file`` or ``-conf``, in any form rl-zoo3's parser reads, wins), and read the package's
        ``--search-space`` flag (``--search-space small`` or ``--search-space=small``)
    :param watch: ``enjoy`` and ``record_video``: the off-policy PeVFA algorithms load with a replay buffer of one
        transition, as rl-zoo3 loads SAC and TD3 there (not the saved ``buffer_size``'s memory)
    """
    from sb3_pevfa.rl_zoo.hyperparams_opt import SEARCH_SPACE

    register()
    args = list(sys.argv[1:] if argv is None else argv)
    # what rl-zoo3's parser would read: its own flags, abbreviations and "--flag=value" included
    zoo = argparse.ArgumentParser(add_help=False)
    zoo.add_argument("--algo", default=None)
    zoo.add_argument("-conf", "--conf-file", dest="conf_file", default=None)
    zoo.add_argument("--env", default=None)
    given, _ = zoo.parse_known_args(args)
    if default_config:
        ours = argparse.ArgumentParser(prog="sb3_pevfa.train", add_help=False, allow_abbrev=False)  # a flag rl-zoo3 lacks
        ours.add_argument("--search-space", choices=["full", "small"], default="full")
        search, args = ours.parse_known_args(args)
        SEARCH_SPACE["name"] = search.search_space
        if {"-h", "--help"} & set(args):  # rl-zoo3's help follows and exits; our flag first
            print(
                "sb3-pevfa adds to rl-zoo3's flags:\n  --search-space {full,small}\n"
                "                        PeVFA search space of -optimize: 'full' (default) or 'small' (a tiny one for tests)\n"
                f"  (--algo {' / '.join(ALGORITHMS)} read {HYPERPARAMS_PATHS[ALGO_NAME].parent} unless --conf-file is given)\n"
            )
        if given.algo in HYPERPARAMS_PATHS and given.conf_file is None:
            why = left_out(given.algo, given.env)
            if why is not None:
                raise SystemExit(f"No shipped {given.algo} hyperparameters for {given.env}: {why}. Give an entry of your "
                                 "own with --conf-file.")  # fmt: skip
            args += ["--conf-file", str(HYPERPARAMS_PATHS[given.algo])]
    sys.argv = [sys.argv[0], *args]
    from rl_zoo3 import utils

    watched = {name: utils.ALGOS[name] for name in OFF_POLICY_ALGORITHMS} if watch else {}
    utils.ALGOS.update({name: LoadsWithoutReplayBuffer(algorithm) for name, algorithm in watched.items()})
    try:
        script()
    finally:
        utils.ALGOS.update(watched)
