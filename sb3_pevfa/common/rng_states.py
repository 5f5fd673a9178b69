"""The global torch / numpy RNG states saved with a model, so that a resumed run can go on bit for bit."""

import io
import pathlib
from typing import Any

import numpy as np
import torch as th


class RngStatesInFile:
    """Mixin of an SB3 algorithm (listed before its SB3 base): ``save`` stores the global torch and numpy RNG states
    with the model, ``load(..., restore_rng_state=True)`` sets them back."""

    def save(self, path: str | pathlib.Path | io.BufferedIOBase, exclude=None, include=None) -> None:
        self._rng_states = {"torch": th.get_rng_state(), "numpy": np.random.get_state()}
        try:
            super().save(path, exclude=exclude, include=include)  # type: ignore[misc]
        finally:
            del self._rng_states

    @classmethod
    def load(cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, restore_rng_state: bool = False, **kwargs: Any):
        """SB3's ``load``. The global torch / numpy RNGs are left as SB3 leaves them (it seeds them with the model's
        seed, if any, while it rebuilds the model).

        :param restore_rng_state: Set the global torch / numpy RNG states to the saving process's, so that learning
            on (with the model's history or replay buffer, and seeded environments) continues bit for bit as the
            saved run would have
        """
        model = super().load(path, *args, **kwargs)  # type: ignore[misc]
        rng_states = model.__dict__.pop("_rng_states", None)
        if restore_rng_state:
            if rng_states is None:
                raise ValueError(f"{path} holds no RNG states (saved by another version): load without restore_rng_state")
            th.set_rng_state(rng_states["torch"])
            np.random.set_state(rng_states["numpy"])
        return model
