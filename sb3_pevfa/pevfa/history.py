"""The policy history: the record of every recorded policy, and a FIFO of (observation, value target, policy id)."""

import copy
import io
import json
import os
import pathlib
import zipfile
import zlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim, get_obs_shape
from stable_baselines3.common.vec_env import VecNormalize

from sb3_pevfa.common.files import replacing
from sb3_pevfa.pevfa.normalization import reward_scale
from sb3_pevfa.pevfa.records import RECORD_FIELDS, ActorLayout, rows, state_dim
from sb3_pevfa.pevfa.targets import lambda_returns

#: Version of the file format written by :meth:`PolicyHistory.save`.
HISTORY_FORMAT_VERSION = 4
#: Versions :meth:`PolicyHistory.load` reads (1: records were called ``policy/<field>``; 2: no transitions; 3: no
#: raw observations for VecNormalize).
_READABLE_VERSIONS = (1, 2, 3, 4)
#: Signature entries that older files lack, and the value they then mean
_SIGNATURE_DEFAULTS = {"transitions": False, "renormalize": False, "actor_mean_activation": None}
#: Rows normalised and evaluated at a time when targets are recomputed (bounds the temporaries)
NORMALIZE_CHUNK = 16384

ObsBatch = np.ndarray | dict[str, np.ndarray]


def _rollout_tail(array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """The last ``len(array)`` samples of a ``(n_steps, n_envs)`` rollout in its shape, zeros in front (an evicted
    front: the lambda-return recursion runs backwards, so the kept samples do not read it)."""
    out = np.zeros(int(np.prod(shape)), np.float32)
    out[len(out) - len(array) :] = array
    return out.reshape(shape)


def _check_finite(array: np.ndarray, what: str) -> None:
    """A ValueError at the first NaN or infinity: one would poison every critic trained on the history."""
    if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
        index = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        raise ValueError(f"The history refuses non-finite {what}: {array[index]} at index {index}")


class _Ring:
    """Named numpy arrays sharing one FIFO ring index; grows geometrically up to ``max_size`` rows."""

    def __init__(self, specs: dict[str, tuple[tuple[int, ...], np.dtype]], max_size: int):
        self.specs = specs
        self.max_size = max_size
        self.capacity = 0
        self.start = 0
        self.size = 0
        self.arrays: dict[str, np.ndarray] = {name: np.zeros((0, *shape), dtype) for name, (shape, dtype) in specs.items()}

    def positions(self, logical: np.ndarray) -> np.ndarray:
        """Storage positions of logical indices (0 is the oldest row)."""
        return (self.start + logical) % max(self.capacity, 1)

    def _grow(self, needed: int) -> None:
        new_capacity = min(self.max_size, max(2 * self.capacity, needed, 1024))
        order = self.positions(np.arange(self.size))
        for name, (shape, dtype) in self.specs.items():
            array = np.zeros((new_capacity, *shape), dtype)
            array[: self.size] = self.arrays[name][order]
            self.arrays[name] = array
        self.capacity, self.start = new_capacity, 0

    def drop_front(self, n: int) -> dict[str, np.ndarray]:
        """Remove the ``n`` oldest rows and return them."""
        n = min(n, self.size)
        dropped = self.get(np.arange(n))
        self.start = (self.start + n) % max(self.capacity, 1)
        self.size -= n
        return dropped

    def append(self, rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Append rows (keeping the newest ``max_size``); returns the rows evicted to make room."""
        n = len(next(iter(rows.values())))
        if n > self.max_size:
            rows = {name: array[-self.max_size :] for name, array in rows.items()}
            n = self.max_size
        evicted = self.drop_front(self.size + n - self.max_size) if self.size + n > self.max_size else {}
        if self.size + n > self.capacity:
            self._grow(self.size + n)
        where = self.positions(np.arange(self.size, self.size + n))
        for name, array in rows.items():
            self.arrays[name][where] = array
        self.size += n
        return evicted

    def get(self, logical: np.ndarray) -> dict[str, np.ndarray]:
        where = self.positions(logical)
        return {name: array[where] for name, array in self.arrays.items()}

    @property
    def nbytes(self) -> int:
        return sum(array.nbytes for array in self.arrays.values())


class PolicyHistory:
    """History of policies for PeVFA (paper Algorithm 2).

    Per policy its record (flat actor parameters, state-action pairs, random code) is kept, never an
    embedding: embeddings are recomputed by the current encoder whenever they are needed. Beside it, a FIFO of
    ``(observation, value target, policy id)`` samples, bounded by ``buffer_size`` samples and, through the
    policies it refers to, by ``max_policies``. Evicting a policy evicts its samples (always the oldest).

    :param observation_space: Observation space (Dict spaces are stored key by key)
    :param action_space: Action space
    :param n_params: Size of the flat actor parameter vector
    :param n_state_action_pairs: State-action pairs recorded per policy (0 for none)
    :param code_dim: Size of the random code per policy (0 unless ``random`` representation)
    :param buffer_size: Maximum number of samples (paper: 200k)
    :param max_policies: Maximum number of policies kept
    :param seed: Seed of the sampling RNG (the model passes its own seed)
    :param representation: Name of the representation this history feeds (checked on load)
    :param layout: The actor's parameter layout (every layer's shape is checked on load)
    :param transitions: Also keep each sample's reward and episode start, and each rollout's last observations, so
        that value targets can be recomputed (:meth:`recompute_targets`)
    :param renormalize: Keep raw observations and each sample's reward scale, and hand everything out in the
        statistics of :attr:`normalizer` (a ``VecNormalize``) at the time of reading (:mod:`~sb3_pevfa.pevfa.normalization`)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        n_params: int,
        n_state_action_pairs: int = 200,
        code_dim: int = 0,
        buffer_size: int = 200_000,
        max_policies: int = 10_000,
        seed: int | None = None,
        representation: str | None = None,
        layout: ActorLayout | None = None,
        transitions: bool = False,
        renormalize: bool = False,
    ):
        for name, value in (("buffer_size", buffer_size), ("max_policies", max_policies)):
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if n_state_action_pairs < 0 or code_dim < 0:
            raise ValueError("n_state_action_pairs and code_dim must be >= 0")
        self.observation_space = observation_space
        self.action_space = action_space
        self.n_params = int(n_params)
        self.n_state_action_pairs = int(n_state_action_pairs)
        self.code_dim = int(code_dim)
        self.buffer_size = int(buffer_size)
        self.max_policies = int(max_policies)
        self.representation = representation
        if layout is not None and layout.n_params != self.n_params:
            raise ValueError(f"n_params={n_params} does not match the actor layout's {layout.n_params}")
        self.layout = layout
        self.transitions = bool(transitions)
        self.renormalize = bool(renormalize)
        #: The VecNormalize whose statistics reads are expressed in (``renormalize``; set by the algorithm)
        self.normalizer: VecNormalize | None = None
        #: SPR probe states are stored raw (``renormalize``): VecNormalize takes Box and Dict spaces, and every key it
        #: normalises becomes a float Box, whose flattened form holds the observation itself
        self.raw_states = self.renormalize and isinstance(observation_space, (spaces.Box, spaces.Dict))
        self.rng = np.random.default_rng(seed)
        self._obs_keys = list(observation_space.spaces) if isinstance(observation_space, spaces.Dict) else None
        self.reset()

    # ------------------------------------------------------------------ construction
    def _obs_specs(self) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        def spec(space: spaces.Space) -> tuple[tuple[int, ...], np.dtype]:
            # integer Box spaces (images) keep their dtype; everything else is float32, as in SB3's rollout buffers
            integer_box = isinstance(space, spaces.Box) and np.issubdtype(space.dtype, np.integer)
            return get_obs_shape(space), np.dtype(space.dtype if integer_box else np.float32)

        if self._obs_keys is None:
            return {"obs": spec(self.observation_space)}
        return {f"obs/{key}": spec(self.observation_space.spaces[key]) for key in self._obs_keys}

    def reset(self) -> None:
        """Forget every policy and sample."""
        specs = self._obs_specs()
        specs["targets"] = ((), np.dtype(np.float32))
        specs["policy_ids"] = ((), np.dtype(np.int64))
        if self.transitions:
            specs["rewards"] = ((), np.dtype(np.float32))
            specs["episode_starts"] = ((), np.dtype(np.float32))
        if self.renormalize:
            specs["reward_scales"] = ((), np.dtype(np.float32))
            if self.transitions:
                specs["raw_rewards"] = ((), np.dtype(np.float32))
                specs["raw_bootstraps"] = ((), np.dtype(np.float32))
        self._samples = _Ring(specs, self.buffer_size)
        #: per policy: the observations after its rollout and whether they start episodes (``transitions``)
        self._bootstraps: dict[int, dict[str, np.ndarray]] = {}
        self._policies: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        self._record_info: dict[int, dict[str, int | float]] = {}
        self._sample_counts: dict[int, int] = {}
        self._cumulative_counts: np.ndarray | None = None  # of _sample_counts, for sample_grouped; None: stale
        self._next_id = 0
        self._record_nbytes = 0  # kept up to date: summing 10k records at every iteration is not free

    @property
    def signature(self) -> dict[str, Any]:
        """What a saved history must match to be loaded into this one."""
        return {
            "observation_shapes": {name: list(shape) for name, (shape, _) in self._obs_specs().items()},
            "state_dim": state_dim(self.observation_space),
            "action_dim": get_action_dim(self.action_space),
            "action_space": type(self.action_space).__name__,
            "n_params": self.n_params,
            "n_state_action_pairs": self.n_state_action_pairs,
            "code_dim": self.code_dim,
            "representation": self.representation,
            "observation_space": str(self.observation_space),
            "action_space_details": str(self.action_space),
            "actor_linear_shapes": None if self.layout is None else [list(shape) for shape in self.layout.linear_shapes],
            "actor_log_std_shape": None if self.layout is None else list(self.layout.log_std_shape),
            "actor_mean_activation": None
            if self.layout is None or self.layout.mean_activation_fn is None
            else self.layout.mean_activation_fn.__name__,
            "transitions": self.transitions,
            "renormalize": self.renormalize,
        }

    # ------------------------------------------------------------------ policies
    @property
    def n_policies(self) -> int:
        return len(self._policies)

    @property
    def policy_ids(self) -> list[int]:
        return list(self._policies)

    @property
    def latest_policy_id(self) -> int | None:
        return next(reversed(self._policies)) if self._policies else None

    def record_info(self, policy_id: int) -> dict[str, int | float]:
        """Numbers about a record: ``num_timesteps`` (and ``n_updates``) of the model when the policy was recorded,
        and ``episode_return`` (mean return of the episodes that ended during its rollout) once known."""
        return dict(self._record_info[policy_id])

    @property
    def latest_recorded(self) -> int:
        """The ``num_timesteps`` of the latest recorded policy (0 where none is)."""
        return _latest_num_timesteps(self._record_info.values())

    def sample_count(self, policy_id: int) -> int:
        """Number of stored samples of a policy."""
        return self._sample_counts[policy_id]

    def update_record_info(self, policy_id: int, **info: int | float) -> None:
        """Attach numbers to a recorded policy (saved with the history)."""
        self._record_info[policy_id].update(info)

    def add_record(self, record: dict[str, np.ndarray], **info: int | float) -> int:
        """Store one policy's record (see :func:`~sb3_pevfa.pevfa.records.record_policy`) and numbers about it
        (``record_info``); returns its id."""
        expected = {
            "params": (self.n_params,),
            "states": (self.n_state_action_pairs, state_dim(self.observation_space)),
            "actions": (self.n_state_action_pairs, get_action_dim(self.action_space)),
            "codes": (self.code_dim,),
        }
        for name in RECORD_FIELDS:
            if tuple(record[name].shape) != expected[name]:
                raise ValueError(f"Policy record field {name!r} has shape {record[name].shape}, expected {expected[name]}")
            _check_finite(record[name], f"policy record field {name!r}")
        policy_id = self._next_id
        self._next_id += 1
        self._policies[policy_id] = {name: np.asarray(record[name], dtype=np.float32) for name in RECORD_FIELDS}
        self._record_nbytes += sum(array.nbytes for array in self._policies[policy_id].values())
        self._record_info[policy_id] = dict(info)
        self._sample_counts[policy_id] = 0
        self._cumulative_counts = None
        while len(self._policies) > self.max_policies:
            oldest = next(iter(self._policies))
            self._forget_samples(self._samples.drop_front(self._sample_counts[oldest]))
            self._record_nbytes -= sum(array.nbytes for array in self._policies[oldest].values())
            del self._policies[oldest], self._record_info[oldest], self._sample_counts[oldest]
            self._bootstraps.pop(oldest, None)
        return policy_id

    def sample_policy_ids(self, n: int) -> np.ndarray:
        """``n`` distinct recorded policies drawn uniformly (all of them if fewer are recorded)."""
        ids = np.fromiter(self._policies, dtype=np.int64, count=len(self._policies))
        return ids if n >= len(ids) else self.rng.choice(ids, size=n, replace=False)

    def records(
        self, policy_ids: np.ndarray | list[int], fields: tuple[str, ...] = RECORD_FIELDS, raw: bool = False
    ) -> dict[str, np.ndarray]:
        """Stacked records of the given policies: ``{field: (P, ...)}``; fields not in ``fields`` are left empty
        (size 0 along their first data axis), which saves copying what a representation does not read.

        :param raw: SPR's probe states as stored (raw under ``renormalize``), not in today's statistics"""
        records = [self._policies[int(pid)] for pid in policy_ids]
        data = {}
        for name in RECORD_FIELDS:
            if name in fields:
                data[name] = np.stack([record[name] for record in records])
            else:
                shape = records[0][name].shape
                data[name] = np.zeros((len(records), 0, *shape[1:]), np.float32)
        if self.raw_states and not raw and "states" in fields and data["states"].size:  # probe states, today's statistics
            data["states"] = self.normalized_states(data["states"])
        return data

    def normalized_states(self, states: np.ndarray) -> np.ndarray:
        """Raw flattened probe states ``(..., state_dim)`` in today's statistics: what flattening the normalised
        observations gives. A Dict's flattened state is its keys' flattened parts in the space's order; each
        normalised key's part (a Box: flattening keeps its raw values) goes through ``normalize_obs``."""
        flat = states.reshape(-1, states.shape[-1])
        if self._obs_keys is None:
            normalized = self.normalized(flat.reshape(-1, *self.observation_space.shape))
            return np.asarray(normalized, np.float32).reshape(states.shape)
        env, parts, start = self._require_normalizer(), {}, 0
        for key in self._obs_keys:
            size = state_dim(self.observation_space.spaces[key])
            parts[key] = slice(start, start + size)
            start += size
        keys = [key for key in self._obs_keys if key in env.norm_obs_keys] if env.norm_obs else []
        shapes = {key: self.observation_space.spaces[key].shape for key in keys}
        normalized = env.normalize_obs({key: flat[:, parts[key]].reshape(-1, *shapes[key]) for key in keys})
        result = flat.astype(np.float32)  # a copy
        for key in keys:
            result[:, parts[key]] = normalized[key].reshape(len(flat), -1)
        return result.reshape(states.shape)

    # ------------------------------------------------------------------ samples
    @property
    def n_samples(self) -> int:
        return self._samples.size

    def _forget_samples(self, dropped: dict[str, np.ndarray]) -> None:
        if not dropped:
            return
        self._cumulative_counts = None
        ids, counts = np.unique(dropped["policy_ids"], return_counts=True)
        for policy_id, count in zip(ids.tolist(), counts.tolist()):
            self._sample_counts[policy_id] -= count
            if self._sample_counts[policy_id] == 0:
                self._bootstraps.pop(policy_id, None)  # no sample left to bootstrap

    def add_samples(
        self,
        observations: ObsBatch,
        targets: np.ndarray,
        policy_id: int,
        rewards: np.ndarray | None = None,
        episode_starts: np.ndarray | None = None,
        last_observations: ObsBatch | None = None,
        last_episode_starts: np.ndarray | None = None,
        rollout_shape: tuple[int, int] | None = None,
        reward_scales: np.ndarray | None = None,
        raw_rewards: np.ndarray | None = None,
        raw_bootstraps: np.ndarray | None = None,
    ) -> None:
        """Append samples of one policy. Observations have a leading batch axis (any extra leading axes are flattened).

        With ``transitions``, also the rollout's ``rewards`` and ``episode_starts`` ``(n_steps, n_envs)`` (the
        observations in the same step-major order) and the ``last_observations`` / ``last_episode_starts`` of its
        ``n_envs`` environments after the last step; ``rollout_shape`` (default: the rewards' shape) says which
        rollout the samples end, if they are only its last steps.

        With ``renormalize``, the observations are raw, and ``reward_scales`` gives the reward scale each target is in;
        with transitions also, ``raw_rewards`` and ``raw_bootstraps`` (the time-limit bootstraps folded into
        ``rewards``, in raw reward units)."""
        renormalized = self._renormalize_rows(reward_scales, raw_rewards, raw_bootstraps)
        given = [x is not None for x in (rewards, episode_starts, last_observations, last_episode_starts)]
        if any(given) != self.transitions or (self.transitions and not all(given)):
            raise ValueError(
                f"This history {'keeps' if self.transitions else 'does not keep'} transitions: pass rewards, "
                "episode_starts, last_observations and last_episode_starts " + ("all" if self.transitions else "none")
            )
        if policy_id not in self._policies:
            raise KeyError(f"Unknown policy id {policy_id}: record the policy first")
        if policy_id != self.latest_policy_id:
            raise ValueError("Samples must come from the latest recorded policy (the FIFO is ordered by policy)")
        targets = np.asarray(targets, dtype=np.float32).reshape(-1)
        _check_finite(targets, "value targets")
        rows: dict[str, np.ndarray] = {}
        for name, array, (_, dtype) in self._obs_rows(observations):
            rows[name] = array.astype(dtype, copy=False)
            _check_finite(rows[name], f"observations {name!r}")
            if len(rows[name]) != len(targets):
                raise ValueError(f"{len(rows[name])} observations for {len(targets)} targets")
        rows["targets"] = targets
        rows["policy_ids"] = np.full(len(targets), policy_id, dtype=np.int64)
        for name, array in renormalized.items():
            if len(array) != len(targets):
                raise ValueError(f"{len(array)} {name} for {len(targets)} targets")
            rows[name] = array
        if self.transitions:
            rewards = np.asarray(rewards, dtype=np.float32)
            shape = tuple(int(n) for n in (rewards.shape if rollout_shape is None else rollout_shape))
            if len(shape) != 2 or rewards.size != len(targets) or np.prod(shape) < len(targets):
                raise ValueError(
                    f"rewards must hold one value per sample ({len(targets)}) of a (n_steps, n_envs) rollout, got "
                    f"rewards of shape {rewards.shape} and rollout_shape {rollout_shape}"
                )
            rows["rewards"], rows["episode_starts"] = rewards.reshape(-1), np.asarray(episode_starts, np.float32).reshape(-1)
            if self._sample_counts[policy_id]:
                raise ValueError(f"Policy {policy_id} has samples already: with transitions, one rollout per record")
            # copies: a VecEnv may reuse its observation buffers
            bootstrap = {name: np.array(a, dtype) for name, a, (_, dtype) in self._obs_rows(last_observations)}
            bootstrap["last_episode_starts"] = np.array(last_episode_starts, np.float32).reshape(-1)
            for name, array in [("rewards", rows["rewards"]), *bootstrap.items()]:
                _check_finite(array, name)
            bootstrap["rollout_shape"] = np.array(shape)
        self._forget_samples(self._samples.append(rows))
        if self.transitions:
            self._bootstraps[policy_id] = bootstrap
        self._sample_counts[policy_id] += min(len(targets), self.buffer_size)
        self._cumulative_counts = None

    def _renormalize_rows(self, *arrays: np.ndarray | None) -> dict[str, np.ndarray]:
        """The sample fields of ``renormalize`` (reward scales; raw rewards and bootstraps with transitions), checked."""
        names = ("reward_scales", "raw_rewards", "raw_bootstraps")
        wanted = [self.renormalize, self.renormalize and self.transitions, self.renormalize and self.transitions]
        if [array is not None for array in arrays] != wanted:
            raise ValueError(
                "reward_scales (and, with transitions, raw_rewards and raw_bootstraps) go with a history that "
                f"renormalizes, and only there; this one has renormalize={self.renormalize}, transitions={self.transitions}"
            )
        fields = {name: np.asarray(a, np.float32).reshape(-1) for name, a in zip(names, arrays) if a is not None}
        for name, array in fields.items():
            _check_finite(array, name)
        return fields

    def _obs_rows(self, observations: ObsBatch) -> list[tuple[str, np.ndarray, tuple[tuple[int, ...], np.dtype]]]:
        """``(storage name, array, spec)`` of each observation field, reshaped to ``(-1, *shape)``."""
        fields = []
        for name, spec in self._obs_specs().items():
            array = observations if self._obs_keys is None else observations[name.split("/", 1)[1]]
            fields.append((name, np.asarray(array).reshape(-1, *spec[0]), spec))
        return fields

    def _observations(self, rows: dict[str, np.ndarray]) -> ObsBatch:
        if self._obs_keys is None:
            return rows["obs"]
        return {key: rows[f"obs/{key}"] for key in self._obs_keys}

    def _require_normalizer(self) -> VecNormalize:
        if self.normalizer is None:
            raise ValueError(
                "This history keeps raw observations for a VecNormalize env (renormalize=True), but none is attached "
                "(history.normalizer): give the model its VecNormalize env (VecNormalize.load) before it reads the history"
            )
        return self.normalizer

    def normalized(self, observations: ObsBatch) -> ObsBatch:
        """Stored (raw) observations in today's statistics (unchanged unless ``renormalize``)."""
        return self._require_normalizer().normalize_obs(observations) if self.renormalize else observations

    def _current(self, rows: dict[str, np.ndarray]) -> tuple[ObsBatch, np.ndarray]:
        """Observations and value targets of ``rows`` in today's statistics (as stored unless ``renormalize``)."""
        if not self.renormalize:
            return self._observations(rows), rows["targets"]
        ratio = rows["reward_scales"] / np.float32(reward_scale(self._require_normalizer()))
        return self.normalized(self._observations(rows)), (rows["targets"] * ratio).astype(np.float32)

    def sample(self, batch_size: int, exclude_policy: int | None = None) -> tuple[ObsBatch, np.ndarray, np.ndarray] | None:
        """Uniform mini-batch ``(observations, targets, policy_ids)``, or None when no sample is eligible.

        :param exclude_policy: The latest policy, whose samples are left out (Algorithm 2 trains on
            policies 0..t-1 here; the current one has its own on-policy update)
        """
        n_valid = self._samples.size
        if exclude_policy is not None and exclude_policy == self.latest_policy_id:
            n_valid -= self._sample_counts[exclude_policy]
        if n_valid <= 0:
            return None
        rows = self._samples.get(self.rng.integers(n_valid, size=batch_size))
        return *self._current(rows), rows["policy_ids"]

    def sample_grouped(
        self, batch_size: int, n_policies: int, exclude_policy: int | None = None
    ) -> tuple[ObsBatch, np.ndarray, np.ndarray] | None:
        """Mini-batch of ``n_policies`` policies x ``batch_size / n_policies`` samples (the remainder spread over
        the first ones), or None when no sample is eligible.

        The policies are drawn with replacement in proportion to their sample counts and the samples uniformly
        within each, so every eligible sample has the same chance per slot as in :meth:`sample`: the expected loss
        is the same, and a batch reads at most ``n_policies`` records instead of up to ``batch_size``.
        """
        if self._cumulative_counts is None:
            counts = np.fromiter(self._sample_counts.values(), dtype=np.int64, count=len(self._sample_counts))
            self._cumulative_counts = np.cumsum(counts)  # the FIFO is ordered by policy: its samples are contiguous
        ends = self._cumulative_counts
        counts = np.diff(ends, prepend=0)
        n_valid = self._samples.size
        if exclude_policy is not None and exclude_policy == self.latest_policy_id:
            n_valid -= counts[-1]  # the latest policy's samples are the newest: the eligible ones are [0, n_valid)
        if n_valid <= 0:
            return None
        # the policies of uniformly drawn samples: each policy in proportion to its sample count
        chosen = np.searchsorted(ends, self.rng.integers(n_valid, size=n_policies), side="right")
        per_policy = np.full(n_policies, batch_size // n_policies)
        per_policy[: batch_size % n_policies] += 1
        offsets = self.rng.random(batch_size) * np.repeat(counts[chosen], per_policy)
        logical = np.repeat(ends[chosen] - counts[chosen], per_policy) + offsets.astype(np.int64)
        rows = self._samples.get(logical)
        return *self._current(rows), rows["policy_ids"]

    def sample_observations(self, n: int, raw: bool = False) -> ObsBatch | None:
        """``n`` observations drawn uniformly from the FIFO (probe states of SPR), or None if it is empty.

        :param raw: As stored (raw under ``renormalize``) instead of in today's statistics"""
        if self._samples.size == 0:
            return None
        observations = self._observations(self._samples.get(self.rng.integers(self._samples.size, size=n)))
        return observations if raw else self.normalized(observations)

    def recompute_targets(
        self,
        value_fn: Callable[[ObsBatch, np.ndarray], np.ndarray],
        gamma: float,
        gae_lambda: float,
        exclude_policy: int | None = None,
    ) -> int:
        """Replace the value targets of every sample by lambda-returns of its own policy under ``value_fn``.

        :param value_fn: ``(observations, policy_ids) -> values (n,)``: the current critic at each policy's chi
        :param exclude_policy: A policy left as it is (the latest, whose samples the on-policy update trains on)
        :return: The number of samples whose targets were recomputed
        """
        if not self.transitions:
            raise ValueError("recompute_targets needs a history that keeps transitions (transitions=True)")
        counts = [(pid, self._sample_counts[pid]) for pid in self._policies]
        starts = np.cumsum([0] + [count for _, count in counts])
        chosen = [(pid, start, count) for (pid, count), start in zip(counts, starts) if count and pid != exclude_policy]
        if not chosen:
            return 0
        logical = np.concatenate([np.arange(start, start + count) for _, start, count in chosen])
        rows = self._samples.get(logical)
        values = self._values(value_fn, self._observations(rows), rows["policy_ids"])
        boots = [self._bootstraps[pid] for pid, _, _ in chosen]
        last_obs = {name: np.concatenate([b[name] for b in boots]) for name in self._obs_specs()}
        last_ids = np.concatenate([np.full(len(b["last_episode_starts"]), pid) for (pid, _, _), b in zip(chosen, boots)])
        last_values = self._values(value_fn, self._observations(last_obs), last_ids)
        rewards = rows["rewards"]
        if self.renormalize:  # today's reward normalisation of the raw rewards, and the bootstraps rescaled
            normalizer = self._require_normalizer()
            rewards = normalizer.normalize_reward(rows["raw_rewards"]) + rows["raw_bootstraps"] / reward_scale(normalizer)
        # the rollouts of one shape go through one stacked recursion
        groups: dict[tuple[int, ...], list[tuple[slice, slice, dict[str, np.ndarray]]]] = {}
        offset, last_offset = 0, 0
        for (_, _, count), bootstrap in zip(chosen, boots):
            shape = tuple(int(x) for x in bootstrap["rollout_shape"])
            groups.setdefault(shape, []).append(
                (slice(offset, offset + count), slice(last_offset, last_offset + shape[1]), bootstrap)
            )
            offset, last_offset = offset + count, last_offset + shape[1]
        targets = np.empty_like(values)
        for shape, members in groups.items():

            def stacked(array: np.ndarray, shape: tuple[int, ...] = shape, members: list = members) -> np.ndarray:
                return np.stack([_rollout_tail(array[part], shape) for part, _, _ in members])

            returns = lambda_returns(
                stacked(rewards),
                stacked(values),
                stacked(rows["episode_starts"]),
                np.stack([last_values[last] for _, last, _ in members]),
                np.stack([bootstrap["last_episode_starts"] for _, _, bootstrap in members]),
                gamma,
                gae_lambda,
            )
            for (part, _, _), rollout in zip(members, returns):
                targets[part] = rollout.reshape(-1)[len(rollout.reshape(-1)) - (part.stop - part.start) :]
        _check_finite(targets, "recomputed value targets")
        self._samples.arrays["targets"][self._samples.positions(logical)] = targets
        if self.renormalize:  # the new targets are in today's reward scale
            self._samples.arrays["reward_scales"][self._samples.positions(logical)] = reward_scale(self._require_normalizer())
        return len(targets)

    def _values(self, value_fn: Callable[[ObsBatch, np.ndarray], np.ndarray], observations: ObsBatch, policy_ids: np.ndarray):
        """``value_fn`` of stored observations in today's statistics, :data:`NORMALIZE_CHUNK` rows at a time: under
        ``renormalize``, normalising the whole FIFO at once would hold several float64 copies of it."""
        values = []
        for start in range(0, len(policy_ids), NORMALIZE_CHUNK):
            part = slice(start, start + NORMALIZE_CHUNK)
            chunk = rows(observations, part)
            values.append(np.asarray(value_fn(self.normalized(chunk), policy_ids[part]), np.float32).reshape(-1))
        return np.concatenate(values) if values else np.zeros(0, np.float32)

    def samples(self, raw: bool = False) -> tuple[ObsBatch, np.ndarray, np.ndarray]:
        """All samples, oldest first: ``(observations, targets, policy_ids)`` in today's statistics.

        :param raw: As stored (raw observations, targets in the scale of their rollout, under ``renormalize``)"""
        rows = self._samples.get(np.arange(self._samples.size))
        observations, targets = (self._observations(rows), rows["targets"]) if raw else self._current(rows)
        return observations, targets, rows["policy_ids"]

    # ------------------------------------------------------------------ bookkeeping
    @property
    def nbytes(self) -> int:
        """Memory held by the history, in bytes."""
        return self._samples.nbytes + self._record_nbytes

    @property
    def max_nbytes(self) -> int:
        """Memory the history can grow to, in bytes: ``buffer_size`` samples and ``max_policies`` records."""
        sample = sum(int(np.prod(shape, dtype=np.int64)) * dtype.itemsize for shape, dtype in self._samples.specs.values())
        pair = state_dim(self.observation_space) + get_action_dim(self.action_space)
        record = 4 * (self.n_params + self.n_state_action_pairs * pair + self.code_dim)  # float32 fields
        return self.buffer_size * sample + self.max_policies * record

    def __len__(self) -> int:
        return self.n_samples

    def __repr__(self) -> str:
        # a history of records only (SACPeVFA's and TD3PeVFA's snapshots: the replay buffer holds the transitions)
        samples = f"samples={self.n_samples}/{self.buffer_size}, " if self.buffer_size > 1 else ""
        return f"PolicyHistory(policies={self.n_policies}/{self.max_policies}, {samples}memory={self.nbytes / 2**20:.1f} MiB)"

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | pathlib.Path | io.IOBase) -> None:
        """Save as a numpy ``.npz`` archive (format version, signature, RNG state, records and samples).

        A path without a suffix gets ``.npz``; a path with one is used as given (e.g. rl-zoo3's ``replay_buffer.pkl``).
        The file is written to a temporary file beside it and then renamed, so a failed save leaves an existing file
        as it was. A file-like object (e.g. ``io.BytesIO``) is written to directly.
        """
        ids = self.policy_ids
        meta = {
            "format_version": HISTORY_FORMAT_VERSION,
            "signature": self.signature,
            "rng_state": self.rng.bit_generator.state,
            "next_id": self._next_id,
            "policy_ids": ids,
            "record_info": [self._record_info[pid] for pid in ids],
        }
        arrays = {f"record/{name}": array for name, array in self.records(ids, raw=True).items()} if ids else {}
        arrays.update({f"sample/{name}": array for name, array in self._samples.get(np.arange(self.n_samples)).items()})
        for policy_id, bootstrap in self._bootstraps.items():
            arrays.update({f"bootstrap/{policy_id}/{name}": array for name, array in bootstrap.items()})
        if not isinstance(path, (str, os.PathLike)):
            np.savez(path, meta=np.array(json.dumps(meta)), **arrays)
            return
        path = pathlib.Path(path)
        if not path.suffix:
            path = path.with_suffix(".npz")
        with replacing(path) as temporary, open(temporary, "wb") as handle:  # a file handle: numpy adds no suffix
            np.savez(handle, meta=np.array(json.dumps(meta)), **arrays)

    def load(self, path: str | pathlib.Path | io.IOBase) -> "PolicyHistory":
        """Load a history saved by :meth:`save` (a path or a file-like object); the file must match this history's
        signature. The file is read and checked in full before this history is replaced: a failed load leaves it as
        it was. This history's bounds apply: if the file holds more, the newest records and samples are kept.
        """
        if isinstance(path, (str, os.PathLike)):
            path = pathlib.Path(path)
            if not path.exists() and not path.suffix:
                path = path.with_suffix(".npz")
        meta, arrays = _read_archive(path)
        version = meta.get("format_version")
        if version not in _READABLE_VERSIONS:
            raise ValueError(
                f"History file {path} has format version {version}, this sb3-pevfa reads versions {_READABLE_VERSIONS}"
            )
        found_signature = meta["signature"]
        mismatches = {
            key: (found_signature.get(key), value)
            for key, value in self.signature.items()
            # format 1 files hold fewer keys: those they have are checked; a history without a layout takes any
            if (version > 1 or key in found_signature or key in _SIGNATURE_DEFAULTS)
            and not (key.startswith("actor_") and self.layout is None)
            and found_signature.get(key, _SIGNATURE_DEFAULTS.get(key)) != value
        }
        if mismatches:
            details = ", ".join(
                f"{key}: file has {found_signature.get(key, _SIGNATURE_DEFAULTS.get(key))!r}, model expects {wanted!r}"
                for key, (_, wanted) in mismatches.items()
            )
            hint = ""
            if "renormalize" in mismatches and not found_signature.get("renormalize", False):
                hint = (
                    "; a history recorded as its rollouts saw a VecNormalize env loads into a model built or "
                    "loaded with history_normalization='rollout'"
                )
            elif "renormalize" in mismatches:  # the file's samples are raw, read through the model's VecNormalize
                hint = (
                    "; a history recorded under a VecNormalize env loads into a model on that VecNormalize (load the "
                    "model with env=VecNormalize.load(statistics_path, venv)) and history_normalization='current'"
                )
            raise ValueError(f"History file {path} does not match this model ({details}){hint}")
        try:
            loaded = self._from_arrays(meta, arrays, version)
        except KeyError as error:
            raise ValueError(f"History file {path} is incomplete: it has no {error} (a truncated or edited file?)") from None
        self.__dict__.update(loaded.__dict__)
        return self

    def _from_arrays(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], version: int) -> "PolicyHistory":
        """A copy of this history (same spaces and bounds) holding the records and samples of a file's arrays."""
        prefix, info_key = ("policy" if version == 1 else "record"), _info_key(version)
        loaded = copy.copy(self)  # same spaces and bounds, its own storage: this history stays intact until the end
        loaded.rng = np.random.default_rng()
        loaded.reset()
        for i, (policy_id, info) in enumerate(zip(meta["policy_ids"], meta[info_key])):
            loaded._next_id = policy_id
            loaded.add_record({name: arrays[f"{prefix}/{name}"][i] for name in RECORD_FIELDS}, **info)
            mask = arrays["sample/policy_ids"] == policy_id
            if mask.any():
                observations = self._observations({name: arrays[f"sample/{name}"][mask] for name in self._obs_specs()})
                transitions = {}
                if self.transitions:
                    bootstrap = {name: arrays[f"bootstrap/{policy_id}/{name}"] for name in self._obs_specs()}
                    transitions = dict(
                        rewards=arrays["sample/rewards"][mask],
                        episode_starts=arrays["sample/episode_starts"][mask],
                        last_observations=self._observations(bootstrap),
                        last_episode_starts=arrays[f"bootstrap/{policy_id}/last_episode_starts"],
                        rollout_shape=tuple(arrays[f"bootstrap/{policy_id}/rollout_shape"]),
                    )
                if self.renormalize:
                    transitions["reward_scales"] = arrays["sample/reward_scales"][mask]
                    if self.transitions:
                        transitions["raw_rewards"] = arrays["sample/raw_rewards"][mask]
                        transitions["raw_bootstraps"] = arrays["sample/raw_bootstraps"][mask]
                loaded.add_samples(observations, arrays["sample/targets"][mask], policy_id, **transitions)
        loaded._next_id = meta["next_id"]
        loaded.rng.bit_generator.state = meta["rng_state"]
        return loaded


def _info_key(version: int | None) -> str:
    """The meta data's list of record infos in a history file of format ``version``."""
    return "policy_info" if version == 1 else "record_info"


def _latest_num_timesteps(infos: Any) -> int:
    """The largest ``num_timesteps`` of record infos (0 where there are none)."""
    return max((int(info.get("num_timesteps", 0)) for info in infos), default=0)


def latest_recorded(path: str | pathlib.Path) -> int | None:
    """The ``num_timesteps`` of the latest policy recorded in a history file, from its meta data alone; None where
    the file is missing or is not a history file."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            meta = json.loads(str(archive["meta"]))
        return _latest_num_timesteps(meta[_info_key(meta.get("format_version"))])
    except (OSError, ValueError, KeyError, TypeError, AttributeError, zipfile.BadZipFile, zlib.error):
        return None


def _read_archive(path: pathlib.Path | io.IOBase) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The meta data and arrays of a history file; anything else (empty, truncated, text, another archive) is a
    ValueError that names the file. Nothing is ever unpickled."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            if not hasattr(archive, "files") or "meta" not in archive.files:
                raise KeyError("meta")
            meta = json.loads(str(archive["meta"]))
            if not isinstance(meta, dict):
                raise TypeError("meta")
            return meta, {name: archive[name] for name in archive.files if name != "meta"}
    except (EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile, zlib.error) as error:
        raise ValueError(
            f"{path} is not a policy history file: save_history() / PolicyHistory.save() write a numpy .npz archive "
            f"of the records and samples with a 'meta' entry, and this file could not be read as one "
            f"({type(error).__name__})"
        ) from None
