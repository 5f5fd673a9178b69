"""SB3's ``set_training_mode`` in one pass over the modules: a policy whose critic holds an encoder has many small
modules, and SB3 switches the mode twice per env step in SAC and TD3 (``predict``, then ``train``)."""

from typing import Any

from torch import nn


class OnePassTrainingMode:
    """Mixin of an SB3 policy (listed before its SB3 base): ``set_training_mode`` skipped where the mode is already
    set, else the ``training`` flag of every module under :meth:`_mode_roots` set in one pass, without
    ``nn.Module.train``'s recursion, where every such module's ``train`` is ``nn.Module``'s (else SB3's method runs).

    The modules are listed at the first change of mode and again after a module attribute of the policy is assigned
    (a module replaced deeper in the tree needs ``_plain_modules = None``)."""

    _plain_modules: list[nn.Module] | None = None
    training: bool

    def _mode_roots(self) -> tuple[nn.Module, ...]:
        """The modules whose trees the mode covers, the policy's own flag apart: all of them."""
        return (self,)  # type: ignore[return-value]

    def set_training_mode(self, mode: bool) -> None:
        if not isinstance(mode, bool):
            raise ValueError(f"training mode is expected to be a bool, got {mode!r}")
        if mode == self.training:
            return
        if self._plain_modules is None:
            modules = list(dict.fromkeys(m for root in self._mode_roots() for m in root.modules()))
            plain = all(type(module).train is nn.Module.train for module in modules)
            self.__dict__["_plain_modules"] = modules if plain else []
        if not self._plain_modules:
            super().set_training_mode(mode)  # type: ignore[misc]
            return
        for module in self._plain_modules:
            module.__dict__["training"] = mode
        self.__dict__["training"] = mode

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, nn.Module):  # a module added or replaced: list them again at the next change of mode
            self.__dict__["_plain_modules"] = None
        super().__setattr__(name, value)

    def __getstate__(self) -> dict[str, Any]:
        return {**super().__getstate__(), "_plain_modules": None}  # type: ignore[misc]
