"""Environments of the paper's diagnostics; ``PointWalker-v0`` is registered with Gymnasium on import of sb3_pevfa."""

from gymnasium.envs.registration import register, registry

from sb3_pevfa.envs.point_walker import PointWalkerEnv

if "PointWalker-v0" not in registry:
    register(id="PointWalker-v0", entry_point="sb3_pevfa.envs.point_walker:PointWalkerEnv")

__all__ = ["PointWalkerEnv"]
