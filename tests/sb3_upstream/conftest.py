"""SB3's own generic tests (vendored from SB3 v2.9.2, see the header of each file) with SB3's ``SAC`` and ``TD3``
replaced by :class:`~sb3_pevfa.SACPeVFA` and :class:`~sb3_pevfa.TD3PeVFA`, their cases only.

- **Aliasing.** While pytest imports a test module of this folder, ``stable_baselines3.SAC`` / ``.TD3`` (and
  ``stable_baselines3.sac.SAC``, ``stable_baselines3.td3.TD3``) are the PeVFA classes, so the module's
  ``from stable_baselines3 import SAC, TD3`` binds them; SB3's names are restored right after, so the rest of the
  suite (e.g. ``tests/test_sac_pevfa.py``, which compares against SB3's SAC) sees SB3's classes.
- **Selection.** Only the cases of SAC or TD3 run: a test parametrized over algorithm classes runs for SACPeVFA and
  TD3PeVFA only; any other test runs only if its code names ``SAC`` or ``TD3``. The rest are deselected.
- **Failures** are strict xfails with their reason and exception, in :data:`XFAIL`: the design differences
  (docs/off-policy.md: no gSDE) and one PeVFA behaviour that differs from SB3's (a small critic's
  value read from an earlier snapshot's). Slow cases are deselected, in :data:`SLOW` with their reason.
- **Not vendored**: SB3's other test files; they do not run SAC or TD3 (buffers, envs, VecEnvs, logger, utils,
  distributions, preprocessing).

This folder is a package (``__init__.py``) so that its conftest does not take the module name ``conftest`` from
``tests/conftest.py`` (which ``tests/test_sb3_generic.py`` imports as ``conftest``).
"""

import inspect
import pathlib
import re
import types

import pytest
import stable_baselines3
import stable_baselines3.sac
import stable_baselines3.td3
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_pevfa import SACPeVFA, TD3PeVFA

HERE = pathlib.Path(__file__).resolve().parent
OURS = (SACPeVFA, TD3PeVFA)
ALIASES = {
    (stable_baselines3, "SAC"): SACPeVFA,
    (stable_baselines3, "TD3"): TD3PeVFA,
    (stable_baselines3.sac, "SAC"): SACPeVFA,
    (stable_baselines3.td3, "TD3"): TD3PeVFA,
}

_SDE = "design: use_sde=True is refused (a PeVFA records actors of linear layers; docs/off-policy.md)"

_SNAPSHOT_VALUES = (
    "PeVFA behaviour (reported): the snapshots' updates also fit the first snapshot's soft value (the initial actor: "
    "more entropy, a higher soft Q), and with this test's 16-unit critic and 500 steps the live actor's Q(s0) reads "
    "some of it: 51.1 for the true 50, outside the test's 1.0 by a thin 0.08 (52.4 with 256 transitions per 2 "
    "gradient steps; 50.5-50.7 without snapshot updates, history_train_freq=0)"
)

#: The messages of the design refusals (an xfail's exception must say it, not only be of its type)
_NO_SDE = r"use_sde=True is not supported"

#: (node id pattern, matched with re.search, reason, the exception expected, a pattern its message matches): strict
#: xfails
XFAIL: list[tuple[str, str, type[BaseException] | tuple[type[BaseException], ...], str]] = [
    (r"test_save_load\.py::test_save_load_policy\[True-(Mlp|Cnn)Policy-SACPeVFA\]", _SDE, ValueError, _NO_SDE),
    (r"test_sde\.py::test_state_dependent_noise\[True-", _SDE, ValueError, _NO_SDE),
    (r"test_her\.py::test_save_load\[True-SACPeVFA\]", _SDE, ValueError, _NO_SDE),
    (r"test_spaces\.py::test_sde_multi_dim$", _SDE, ValueError, _NO_SDE),
    (r"test_run\.py::test_offpolicy_multi_env\[SACPeVFA\]", _SDE + " (SB3's test turns it on for SAC)", ValueError, _NO_SDE),
    (
        r"test_gae\.py::test_infinite_horizon\[True-SACPeVFA\]",
        _SNAPSHOT_VALUES,
        AssertionError,
        r"assert \S+ < 1\.0\s+\+\s+where \S+ = abs\(",  # |1 / (1 - gamma) - value| < 1.0
    ),
]

EXPECTED_MESSAGE = pytest.StashKey[str]()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """An xfail whose exception does not say its design refusal (``XFAIL``'s message pattern) fails."""
    report = yield
    message = item.stash.get(EXPECTED_MESSAGE, None)
    xfailed = message is not None and getattr(report, "wasxfail", None) is not None and call.excinfo is not None
    if xfailed and not any(re.search(message, str(error)) for error in _chain(call.excinfo.value)):
        report.outcome, report.longrepr = "failed", f"expected a refusal matching {message!r}, got {call.excinfo.value!r}"
        del report.wasxfail
    return report


def _chain(error: BaseException | None) -> list[BaseException]:
    """An exception and those it was raised from or during (pytest.warns' failure over the refusal it met)."""
    chain: list[BaseException] = []
    while error is not None and error not in chain:
        chain.append(error)
        error = error.__cause__ or error.__context__
    return chain


#: (node id pattern, reason): cases left out for time
SLOW: list[tuple[str, str]] = [
    (
        r"test_save_load\.py::test_save_load_large_model$",
        "25-30 s and ~2.5 GB (a TD3 of three 8192-unit layers, over 2 GB saved)",
    ),
]

#: Node id patterns of SAC and TD3 cases that the rules below miss (their parameter is a name, not the class)
INCLUDE = [r"test_tensorboard\.py::test_tensorboard\[(sac|td3)\]"]


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "expensive: SB3's mark of its expensive tests")


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector: pytest.Collector):
    """Import this folder's test modules with SB3's SAC and TD3 aliased to the PeVFA classes."""
    if not (isinstance(collector, pytest.Module) and collector.path.parent == HERE):
        return (yield)
    saved = {key: getattr(*key) for key in ALIASES}
    for (module, name), cls in ALIASES.items():
        setattr(module, name, cls)
    try:
        return (yield)
    finally:
        for (module, name), cls in saved.items():
            setattr(module, name, cls)


def _algorithms(value: object) -> set[type]:
    """The algorithm classes in a parameter value (classes, or in tuples, lists and dicts of them)."""
    if inspect.isclass(value) and issubclass(value, BaseAlgorithm):
        return {value}
    if isinstance(value, (tuple, list)):
        return set().union(*map(_algorithms, value)) if value else set()
    if isinstance(value, dict):
        return _algorithms(list(value.values()))
    return set()


def _names(code: types.CodeType) -> set[str]:
    """The global names a function's code (and the code nested in it) reads."""
    names = set(code.co_names)
    for constant in code.co_consts:
        if isinstance(constant, types.CodeType):
            names |= _names(constant)
    return names


def _involves_ours(item: pytest.Item) -> bool:
    if any(re.search(pattern, item.nodeid) for pattern in INCLUDE):
        return True
    callspec = getattr(item, "callspec", None)
    algorithms = _algorithms(list(callspec.params.values())) if callspec else set()
    if algorithms:
        return bool(algorithms & set(OURS))
    function = getattr(item, "function", None)
    return function is not None and bool(_names(function.__code__) & {"SAC", "TD3"})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    kept, deselected = [], []
    for item in items:
        if item.path.parent != HERE:
            kept.append(item)
            continue
        module = item.module
        for name, cls in (("SAC", SACPeVFA), ("TD3", TD3PeVFA)):
            assert getattr(module, name, cls) is cls, f"{module.__name__}.{name} is not {cls.__name__}"
        if not _involves_ours(item) or any(re.search(pattern, item.nodeid) for pattern, _ in SLOW):
            deselected.append(item)
            continue
        for pattern, reason, raises, message in XFAIL:
            if re.search(pattern, item.nodeid):
                item.add_marker(pytest.mark.xfail(strict=True, reason=reason, raises=raises))
                item.stash[EXPECTED_MESSAGE] = message
                break
        kept.append(item)
    if deselected:
        config.hook.pytest_deselected(items=deselected)
        items[:] = kept
