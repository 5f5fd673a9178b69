"""Argument checks with messages that name the valid choices."""

import difflib
import inspect
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np


def check_keyword_arguments(target: Callable[..., Any], kwargs: dict[str, Any], what: str, skip: int) -> None:
    """A ValueError naming the valid settings when ``kwargs`` holds one that ``target`` does not take.

    :param skip: Leading parameters of ``target`` that are not settings (filled by the caller)
    """
    valid = list(inspect.signature(target).parameters)[skip:]
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise ValueError(f"Unknown {what} {unknown}, valid choices: {valid}")


def check_argument_names(given: Iterable[str], valid: Iterable[str], where: str) -> None:
    """A TypeError naming the first of ``given`` that is not in ``valid`` and the public valid names closest to it,
    as Python names an unexpected keyword argument (``where``: ``"SACPeVFA()"``, ``"SACPeVFA.load()"``)."""
    valid = set(valid)
    public = sorted(name for name in valid if not name.startswith("_"))
    for name in given:
        if name not in valid:
            close = difflib.get_close_matches(name, public, n=3)
            hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else f"; valid: {public}"
            raise TypeError(f"{where} got an unexpected keyword argument {name!r}{hint}")


def init_parameters(cls: type) -> set[str]:
    """The keyword parameters ``cls(...)`` takes: those of its ``__init__`` and, through ``**kwargs``, of each base
    class's ``__init__`` up to the first without ``**kwargs``."""
    names: set[str] = set()
    for klass in cls.__mro__:
        if "__init__" not in vars(klass) or klass is object:
            continue
        parameters = inspect.signature(klass.__init__).parameters.values()  # type: ignore[misc]
        names |= {p.name for p in parameters if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)} - {"self"}
        if not any(p.kind == p.VAR_KEYWORD for p in parameters):
            break
    return names


def check_policy_class(model: Any, base: type) -> None:
    """A TypeError unless the model's policy class is ``base`` or a subclass (not SB3's own policy, nor another
    algorithm's, as a file of another algorithm brings), naming the aliases the model takes."""
    if not (isinstance(model.policy_class, type) and issubclass(model.policy_class, base)):
        sb3 = getattr(model.policy_class, "__module__", "").startswith("stable_baselines3")
        raise TypeError(
            f"{type(model).__name__} needs its PeVFA policy (one of {sorted(model.policy_aliases)} or a subclass of "
            f"{base.__name__}), got {model.policy_class}"
            + (" (SB3's own policy; a file saved by SB3's algorithm loads with that algorithm's class)" if sb3 else "")
        )


def is_int(value: Any) -> bool:
    """An int or a numpy integer, not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def check_layer_sizes(name: str, value: Any) -> tuple[int, ...]:
    """``value``, a sequence of positive ints (layer sizes: a list, tuple or array), as a tuple; a ValueError naming
    ``name`` otherwise."""
    sizes = tuple(value) if isinstance(value, Iterable) and not isinstance(value, (str, bytes)) else None
    if sizes is None or not all(is_int(size) and size > 0 for size in sizes):
        raise ValueError(f"{name} must be a list of positive ints (layer sizes), got {value!r}")
    return tuple(int(size) for size in sizes)


def check_dict(name: str, value: Any) -> dict[str, Any]:
    """``value`` (a mapping, or None for none) as a new dict; a TypeError naming ``name`` otherwise."""
    if not isinstance(value, Mapping | None):
        raise TypeError(f"{name} must be a dict, got {type(value).__name__}")
    return dict(value or {})
