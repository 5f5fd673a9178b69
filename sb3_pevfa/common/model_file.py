"""What a PeVFA model's file holds beyond SB3's, and how it loads: the global torch / numpy RNG states, so that a
resumed run can go on bit for bit; the ``policy_kwargs`` a loader gives, completed with those the class adds itself."""

import inspect
import io
import json
import pathlib
import zipfile
from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.save_util import json_to_data

from sb3_pevfa.common.checks import check_argument_names, init_parameters
from sb3_pevfa.common.files import replacing, with_default_suffix

#: The keyword arguments of SB3's ``load`` (``env``, ``device``, ``custom_objects``, ...)
SB3_LOAD_PARAMETERS = set(inspect.signature(BaseAlgorithm.load).parameters) - {"cls", "path", "kwargs"}


def sb3_base(cls: type) -> type:
    """The SB3 class ``cls`` is based on (``PPO``, ``A2C``, ``SAC``, ``TD3``; for a policy, SB3's policy class)."""
    return next(klass for klass in cls.__mro__ if klass.__module__.startswith("stable_baselines3"))


def sb3_algorithm(cls: type) -> str:
    """The name of the SB3 algorithm class ``cls`` is based on (``"PPO"``, ``"A2C"``, ``"SAC"``, ``"TD3"``)."""
    return sb3_base(cls).__name__


class ModelFile:
    """Mixin of an SB3 algorithm (listed before its SB3 base): ``save`` stores the global torch and numpy RNG states
    with the model, ``load(..., restore_rng_state=True)`` sets them back; ``load(..., policy_kwargs=...)`` takes the
    ``policy_kwargs`` the constructor took (SB3 checks them against the stored ones, which hold the class's own
    entries too)."""

    #: The entries the class adds to ``policy_kwargs`` from its own arguments (its PeVFA arguments)
    added_policy_kwargs: ClassVar[tuple[str, ...]] = ()
    #: The entries it adds with defaults of its own where ``policy_kwargs`` lacks them
    default_policy_kwargs: ClassVar[dict[str, Any]] = {}

    def save(self, path: str | pathlib.Path | io.BufferedIOBase, exclude=None, include=None) -> None:
        """SB3's ``save``, with the RNG states; a file path is written whole or not at all (a failed save leaves an
        existing file as it was)."""
        self._rng_states = {"torch": th.get_rng_state(), "numpy": np.random.get_state()}
        self._sb3_algorithm = sb3_algorithm(type(self))
        try:
            if isinstance(path, (str, pathlib.Path)) and not with_default_suffix(path, "zip").is_dir():
                with replacing(with_default_suffix(path, "zip")) as temporary:
                    super().save(temporary, exclude=exclude, include=include)  # type: ignore[misc]
            else:  # a file object, or a folder (SB3 saves beside it)
                super().save(path, exclude=exclude, include=include)  # type: ignore[misc]
        finally:
            del self._rng_states, self._sb3_algorithm

    @classmethod
    def load(cls, path: str | pathlib.Path | io.BufferedIOBase, *args: Any, restore_rng_state: bool = False, **kwargs: Any):
        """SB3's ``load``. The global torch / numpy RNGs are left as SB3 leaves them (it seeds them with the model's
        seed, if any, while it rebuilds the model). A ``policy_kwargs`` given is completed as the constructor
        completes it (``added_policy_kwargs`` from ``load``'s keyword arguments, else the file's;
        ``default_policy_kwargs`` where the file has them) before SB3 compares it with the stored one.

        :param restore_rng_state: Set the global torch / numpy RNG states to the saving process's, so that learning
            on (with the model's history or replay buffer, and seeded environments) continues bit for bit as the
            saved run would have
        """
        custom_objects = args[2] if len(args) > 2 else kwargs.get("custom_objects")  # SB3's (env, device, ...)
        env = args[0] if args else kwargs.get("env")
        if isinstance(env, str):  # SB3 would say Gym is missing
            raise ValueError(
                f"{cls.__name__}.load() takes an env, not the id {env!r} (the constructor takes ids): pass "
                f"make_vec_env({env!r}) or gymnasium.make({env!r}), or env=None"
            )
        text, data = cls._stored_data(path)
        if text is not None:  # else SB3's load says why the file cannot be read
            # SB3 sets any keyword argument on the model; here, as in the constructor, a name must be an argument of
            # the class or an attribute the file holds (a misspelt one would be set and never read)
            valid = init_parameters(cls) | set(data) | SB3_LOAD_PARAMETERS | {"restore_rng_state"}  # for its suggestions
            check_argument_names(kwargs, valid, f"{cls.__name__}.load()")
            saved_by = data.get("_sb3_algorithm", sb3_algorithm(cls))  # files of earlier versions: not stored
            if saved_by != sb3_algorithm(cls):  # PPOPeVFA's and A2CPeVFA's share their policy class
                raise TypeError(
                    f"{path} holds a model of an algorithm based on SB3's {saved_by}; {cls.__name__} is based on "
                    f"{sb3_algorithm(cls)}: load it with that algorithm's class"
                )
            given = {name: kwargs[name] for name in cls.added_policy_kwargs if name in kwargs}
            if given or kwargs.get("policy_kwargs") is not None:
                stored = json_to_data(text, custom_objects=custom_objects).get("policy_kwargs") or {}
                if kwargs.get("policy_kwargs") is None:
                    cls._check_policy_arguments(given, stored)
                else:
                    kwargs["policy_kwargs"] = cls._completed_policy_kwargs(stored, kwargs["policy_kwargs"], kwargs)
        model = super().load(path, *args, **kwargs)  # type: ignore[misc]
        rng_states = model.__dict__.pop("_rng_states", None)
        model.__dict__.pop("_sb3_algorithm", None)
        if restore_rng_state:
            if rng_states is None:
                raise ValueError(f"{path} holds no RNG states (saved by another version): load without restore_rng_state")
            th.set_rng_state(rng_states["torch"])
            np.random.set_state(rng_states["numpy"])
        return model

    def _get_policy_from_name(self, policy_name: str) -> type:
        """SB3's, whose ValueError names the valid choices."""
        if policy_name in self.policy_aliases:  # type: ignore[attr-defined]
            return self.policy_aliases[policy_name]  # type: ignore[attr-defined]
        valid = sorted(self.policy_aliases)  # type: ignore[attr-defined]
        raise ValueError(f"Unknown policy {policy_name!r} for {type(self).__name__}, valid choices: {valid}")

    def _require_env(self) -> None:
        """A ValueError, before learning, where the model has no env (SB3 asserts it without a message)."""
        if self.env is None:  # type: ignore[attr-defined]
            raise ValueError(
                f"{type(self).__name__} has no env to learn on (a model loaded with env=None): pass env= to load(), "
                "or call model.set_env(env) before learn()"
            )

    @staticmethod
    def _check_policy_arguments(given: dict[str, Any], stored: dict[str, Any]) -> None:
        """A ValueError where a policy argument given to ``load`` (``representation``, ...; rl-zoo3's ``-i`` passes its
        entry's) differs from the file's (``stored``): the model keeps the policy it was saved with, so the argument
        would be kept unread. Files without them (SB3's own) are left to the class's check of its policy."""
        for name, value in given.items():
            if name in stored and value != stored[name]:
                raise ValueError(
                    f"load got {name}={value!r}, the file's policy was built with {stored[name]!r}: a model keeps the "
                    f"policy it was saved with (with rl-zoo3's -i, which passes its hyperparameters' {name}, give the "
                    f"file's with -params {name}:{stored[name]!r})"
                )

    @staticmethod
    def _stored_data(path: Any) -> tuple[str, dict[str, Any]] | tuple[None, None]:
        """The JSON text of the attributes stored in the model file ``path`` and its entries, undecoded; ``None``
        where the file cannot be read."""
        if isinstance(path, (str, pathlib.Path)) and not pathlib.Path(path).exists():
            path = f"{path}.zip"  # as SB3 looks for it
        try:
            with zipfile.ZipFile(path) as archive:  # the stored data alone (a file object is left open)
                text = archive.read("data").decode()
            return text, json.loads(text)
        except (OSError, KeyError, ValueError, zipfile.BadZipFile):
            return None, None

    @classmethod
    def _completed_policy_kwargs(cls, stored: dict[str, Any], given: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
        """``given`` completed as the constructor completes ``policy_kwargs``, from ``load``'s keyword arguments, else
        from the file's ``stored`` entries."""
        added = {
            name: kwargs.get(name, stored.get(name)) for name in cls.added_policy_kwargs if name in kwargs or name in stored
        }
        defaults = {name: value for name, value in cls.default_policy_kwargs.items() if name in stored}
        return {**defaults, **added, **given}
