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


def run_zoo_script(script: Callable[[], None], argv: list[str] | None = None, default_config: bool = False) -> None:
    """Run an rl-zoo3 command-line function with ``ppo_pevfa`` registered and rl-zoo3's flags unchanged.

    :param default_config: Add ``--conf-file`` pointing at the shipped hyperparameters when a PeVFA algorithm
        (``--algo ppo_pevfa``, ``a2c_pevfa``, ``sac_pevfa``, ``td3_pevfa``) is trained without one (a user's
        ``--conf-file`` wins)
    """
    from sb3_pevfa.rl_zoo.hyperparams_opt import SEARCH_SPACE

    register()
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--search-space", choices=["full", "small"], default="full")
    parser.add_argument("--algo", default=None)
    ours, _ = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    args = [arg for arg in (sys.argv[1:] if argv is None else argv)]
    if "--search-space" in args:
        index = args.index("--search-space")
        del args[index : index + 2]
    SEARCH_SPACE["name"] = ours.search_space
    if {"-h", "--help"} & set(args):  # rl-zoo3's help follows and exits; our flag first
        print(
            "sb3-pevfa adds to rl-zoo3's flags:\n  --search-space {full,small}\n"
            "                        PeVFA search space of -optimize: 'full' (default) or 'small' (a tiny one for tests)\n"
            f"  (--algo {' / '.join(ALGORITHMS)} read {HYPERPARAMS_PATHS[ALGO_NAME].parent} unless --conf-file is given)\n"
        )
    if default_config and ours.algo in HYPERPARAMS_PATHS and not {"--conf-file", "-conf"} & set(args):
        args += ["--conf-file", str(HYPERPARAMS_PATHS[ours.algo])]
    sys.argv = [sys.argv[0], *args]
    script()
