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
