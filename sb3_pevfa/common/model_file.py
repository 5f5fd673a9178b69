"""What a PeVFA model's file holds beyond SB3's, and how it loads: the global torch / numpy RNG states, so that a
resumed run can go on bit for bit; the ``policy_kwargs`` a loader gives, completed with those the class adds itself."""

import io
import pathlib
from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.save_util import load_from_zip_file


class ModelFile:
    """Mixin of an SB3 algorithm (listed before its SB3 base): ``save`` stores the global torch and numpy RNG states
    with the model, ``load(..., restore_rng_state=True)`` sets them back; ``load(..., policy_kwargs=...)`` takes the
    ``policy_kwargs`` the constructor took (SB3 checks them against the stored ones, which hold the class's own
    entries too)."""

    #: The entries the class adds to ``policy_kwargs`` itself (its PeVFA arguments)
    added_policy_kwargs: ClassVar[tuple[str, ...]] = ()

    def save(self, path: str | pathlib.Path | io.BufferedIOBase, exclude=None, include=None) -> None:
        self._rng_states = {"torch": th.get_rng_state(), "numpy": np.random.get_state()}
        try:
            super().save(path, exclude=exclude, include=include)  # type: ignore[misc]
        finally:
            del self._rng_states

    @classmethod
    def load(cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, restore_rng_state: bool = False, **kwargs: Any):
        """SB3's ``load``. The global torch / numpy RNGs are left as SB3 leaves them (it seeds them with the model's
        seed, if any, while it rebuilds the model). A ``policy_kwargs`` given is completed with the stored entries
        the class added (``added_policy_kwargs``) that it lacks, before SB3 compares it with the stored one.

        :param restore_rng_state: Set the global torch / numpy RNG states to the saving process's, so that learning
            on (with the model's history or replay buffer, and seeded environments) continues bit for bit as the
            saved run would have
        """
        if kwargs.get("policy_kwargs") is not None:
            kwargs["policy_kwargs"] = cls._completed_policy_kwargs(path, kwargs["policy_kwargs"], kwargs)
        model = super().load(path, *args, **kwargs)  # type: ignore[misc]
        rng_states = model.__dict__.pop("_rng_states", None)
        if restore_rng_state:
            if rng_states is None:
                raise ValueError(f"{path} holds no RNG states (saved by another version): load without restore_rng_state")
            th.set_rng_state(rng_states["torch"])
            np.random.set_state(rng_states["numpy"])
        return model

    @classmethod
    def _completed_policy_kwargs(cls, path: Any, given: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
        data, _, _ = load_from_zip_file(path, device=kwargs.get("device", "auto"),
                                        custom_objects=kwargs.get("custom_objects"), print_system_info=False)  # fmt: skip
        stored = (data or {}).get("policy_kwargs") or {}
        return {**{name: stored[name] for name in cls.added_policy_kwargs if name in stored}, **given}
