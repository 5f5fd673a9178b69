"""Argument checks with messages that name the valid choices."""

import inspect
from collections.abc import Callable
from typing import Any


def check_keyword_arguments(target: Callable[..., Any], kwargs: dict[str, Any], what: str, skip: int) -> None:
    """A ValueError naming the valid settings when ``kwargs`` holds one that ``target`` does not take.

    :param skip: Leading parameters of ``target`` that are not settings (filled by the caller)
    """
    valid = list(inspect.signature(target).parameters)[skip:]
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise ValueError(f"Unknown {what} {unknown}, valid choices: {valid}")


def check_policy_class(model: Any, base: type) -> None:
    """A TypeError unless the model's policy class is ``base`` or a subclass (not SB3's own policy, nor another
    algorithm's, as a file of another algorithm brings), naming the aliases the model takes."""
    if not (isinstance(model.policy_class, type) and issubclass(model.policy_class, base)):
        raise TypeError(
            f"{type(model).__name__} needs its PeVFA policy (one of {sorted(model.policy_aliases)} or a subclass of "
            f"{base.__name__}), got {model.policy_class}"
        )
