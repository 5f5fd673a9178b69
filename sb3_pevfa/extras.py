"""The optional extras of the package (``pip install -e ".[diagnostics]"`` in the repository's checkout): what each
one installs, and a clear message where one is missing, in place of a bare ``ModuleNotFoundError`` from deep inside
an import."""

import importlib.util
import sys

#: extra -> the modules it installs (the ones this package, its examples and its rl-zoo3 commands import)
EXTRAS: dict[str, tuple[str, ...]] = {
    "diagnostics": ("matplotlib", "sklearn", "scipy", "tensorboard"),
    "zoo": ("rl_zoo3", "sb3_contrib", "optuna", "requests", "seaborn", "pandas", "plotly"),
    "mujoco": ("mujoco",),
    "box2d": ("Box2D",),
}
#: Gymnasium's env packages -> the extra their envs need
ENV_EXTRAS = {"gymnasium.envs.mujoco": "mujoco", "gymnasium.envs.box2d": "box2d"}


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a broken or blocked install counts as missing
        return False


def missing_extra(extra: str, what: str, modules: tuple[str, ...] | None = None) -> str | None:
    """The message to show where ``extra`` is not installed (None where it is): what needs it, the missing modules
    and the command that installs them.

    :param modules: The extra's modules that ``what`` needs (default: all of them)"""
    if extra not in EXTRAS:
        raise ValueError(f"Unknown extra {extra!r}, valid choices: {sorted(EXTRAS)}")
    missing = [module for module in modules or EXTRAS[extra] if not _installed(module)]
    if not missing:
        return None
    return (
        f"{what} needs the '{extra}' extra (missing: {', '.join(missing)}): pip install -e \".[{extra}]\" in the "
        "repository's checkout"
    )


def require_extra(extra: str, what: str, modules: tuple[str, ...] | None = None) -> None:
    """Raise ``ModuleNotFoundError`` with :func:`missing_extra`'s message where ``extra`` (or the given ``modules``
    of it) is not installed."""
    message = missing_extra(extra, what, modules)
    if message is not None:
        raise ModuleNotFoundError(message)


def exit_without_extra(extra: str, what: str) -> None:
    """For scripts: exit with :func:`missing_extra`'s message (one line, no traceback) where ``extra`` is missing."""
    message = missing_extra(extra, what)
    if message is not None:
        sys.exit(message)


def exit_without_env_extra(env_id: str, what: str) -> None:
    """For scripts: :func:`exit_without_extra` for the extra that Gymnasium's ``env_id`` needs (MuJoCo, Box2D), if any."""
    import gymnasium

    entry_point = str(gymnasium.spec(env_id).entry_point)
    for package, extra in ENV_EXTRAS.items():
        if entry_point.startswith(package + "."):
            exit_without_extra(extra, what)
