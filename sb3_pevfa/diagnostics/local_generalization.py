"""Local generalization (paper Sec. 3.2, Fig. 3b / 8, App. B.2): is V(s, chi_{pi_t}) closer to pi_t's returns than
a conventional V(s), before and after the iteration's critic update?"""

import copy
import csv
import pathlib
import weakref
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.utils import obs_as_tensor
from torch import nn
from torch.nn import functional as F

from sb3_pevfa.diagnostics.plotting import pyplot, save_figure
from sb3_pevfa.pevfa.policies import init_normal_fan_in
from sb3_pevfa.pevfa.records import PolicyRecord, flatten_observations, state_dim

#: The four error curves, in ``pevfa/local_gen/<name>``.
ERROR_KEYS = ("pevfa_before", "pevfa_after", "vfa_before", "vfa_after")


def monte_carlo_returns(rewards: np.ndarray, episode_starts: np.ndarray, last_dones: np.ndarray, gamma: float):
    """Discounted returns of a rollout ``(n_steps, n_envs)`` and the mask of the states whose episode ended inside
    the rollout (only those have a complete Monte-Carlo return). Rewards are SB3's, which include its time-out
    bootstrap."""
    n_steps = len(rewards)
    returns = np.zeros_like(rewards, dtype=np.float64)
    complete = np.zeros_like(rewards, dtype=bool)
    next_return, next_complete = np.zeros(rewards.shape[1]), np.zeros(rewards.shape[1], dtype=bool)
    next_start = last_dones.astype(bool)
    for step in reversed(range(n_steps)):
        returns[step] = rewards[step] + gamma * next_return * (1.0 - next_start)
        complete[step] = next_start | next_complete  # an episode of this env ends at or after this step
        next_return, next_complete, next_start = returns[step], complete[step], episode_starts[step].astype(bool)
    return returns, complete


class ResumableDiagnostic(BaseCallback):
    """A diagnostic whose conventional critic and results can be saved beside a model's checkpoint and go on in the
    run that resumes it: ``state_dict()``, then ``load_state_dict(state)`` on a new callback before its ``learn``.
    What was not scored when the state was taken (a rollout's or a window's pending errors) is not kept. Loading
    draws no random numbers: the critic it replaces is built under a forked generator."""

    #: The attributes saved by ``state_dict`` (modules and optimizers), besides ``results``
    saved_attributes: tuple[str, ...] = ("critic", "optimizer")

    def __init__(self, verbose: int = 0):
        super().__init__(verbose)
        #: One entry per scored iteration (or window): the four errors, ``timesteps`` and ``n_states``
        self.results: list[dict[str, float]] = []
        self._saved: dict[str, Any] | None = None

    def _build_critic(self) -> None:
        """The conventional critic and its optimizer (as ``saved_attributes`` names them)."""
        raise NotImplementedError

    def _init_callback(self) -> None:
        same = getattr(self, "_model", lambda: None)() is self.model
        if same and self._saved is None:
            return  # another learn() of the same run: its conventional critic goes on
        self._model = weakref.ref(self.model)
        if self._saved is None:
            self._build_critic()
            return
        if not same or not hasattr(self, "critic"):  # a new model (one loaded from a file too): a critic to load into
            with th.random.fork_rng(devices=[]):  # its weights are replaced: the run's random numbers stay the run's
                self._build_critic()
        self._restore()

    def state_dict(self) -> dict[str, Any]:
        """The conventional critic's state, its optimizer's and the results so far (copies)."""
        if self._saved is not None:  # loaded, not applied yet
            return copy.deepcopy(self._saved)
        if not hasattr(self, "critic"):
            raise RuntimeError(f"{type(self).__name__} has no state before its first learn()")
        state = {name: copy.deepcopy(getattr(self, name).state_dict()) for name in self.saved_attributes}
        return {**state, "results": copy.deepcopy(self.results)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Go on from ``state`` (``state_dict()``'s, copied: training does not change it): ``results`` at once, the
        critic and its optimizer when the next ``learn`` starts (whichever model it is)."""
        missing = sorted({*self.saved_attributes, "results"} - set(state))
        if missing:
            raise ValueError(f"{type(self).__name__}'s state needs {', '.join(missing)}; got {', '.join(sorted(state))}")
        self._saved = copy.deepcopy(state)  # optimizer.load_state_dict keeps the given moment tensors, and Adam
        self.results = copy.deepcopy(state["results"])  # updates them in place

    def _restore(self) -> None:
        state, self._saved = self._saved, None
        for name in self.saved_attributes:
            getattr(self, name).load_state_dict(state[name])
        self.results = state["results"]  # a copy already (load_state_dict's)


class LocalGeneralizationCallback(ResumableDiagnostic):
    """Trains a conventional critic V(s) beside a PPOPeVFA run on the same on-policy data and value targets (it never
    feeds the advantages) and logs, at every iteration, the mean squared error of V(s, chi_{pi_t}) and of V(s) against
    the Monte-Carlo returns pi_t actually collected, before and after that iteration's critic update:
    ``pevfa/local_gen/{pevfa_before, pevfa_after, vfa_before, vfa_after}`` (plus ``timesteps`` and ``n_states``).

    The four errors of iteration t are logged together when iteration t+1 starts (the "after" of the PeVFA needs
    the update), so they appear one log row later; ``pevfa/local_gen/timesteps`` says which rollout they belong to.
    ``results`` keeps them too, one entry per iteration. A later ``learn`` of the same model goes on with the same
    conventional critic; ``state_dict`` / ``load_state_dict`` carry it over a checkpoint (``ResumableDiagnostic``).
    Only states whose episode ended inside the rollout are scored. The conventional critic fits the returns as the
    model's critic does: its epochs and minibatches (``rollout_critic_minibatches``: the authors' even split where the
    model has it), its optimizer and settings at the critic's learning rate, and ``weight_init``.

    :param net_arch: Layers of the conventional critic (SB3 PPO's default critic: 64-64, the policy's activation)
    """

    def __init__(self, net_arch: tuple[int, ...] = (64, 64), verbose: int = 0):
        super().__init__(verbose)
        self.net_arch = net_arch
        self._pending: dict | None = None

    def _init_callback(self) -> None:
        if not hasattr(self.model, "history"):
            raise TypeError("LocalGeneralizationCallback needs a PPOPeVFA model")
        super()._init_callback()

    def _build_critic(self) -> None:
        policy = self.model.policy
        layers = create_mlp(state_dim(policy.observation_space), 1, list(self.net_arch), policy.activation_fn)
        critic = nn.Sequential(*layers)
        if policy.weight_init == "normal_fan_in":  # on the CPU, before the move: the CPU generator alone (fork_rng's)
            init_normal_fan_in(critic)
        self.critic = critic.to(self.model.device)
        kwargs = policy.optimizer_kwargs  # the model's optimizer settings (Adam's epsilon), at the critic's rate
        self.optimizer = policy.optimizer_class(self.critic.parameters(), lr=self.model.critic_lr_schedule(1), **kwargs)

    def _on_step(self) -> bool:
        return True

    def _states(self, observations) -> th.Tensor:
        return flatten_observations(obs_as_tensor(observations, self.model.device), self.model.observation_space)

    def _train_critic(self, states: th.Tensor, targets: th.Tensor) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = self.model.critic_lr_schedule(self.model._current_progress_remaining)
        n_epochs, batch_size, used = self.model.rollout_critic_minibatches(len(states))
        for _ in range(n_epochs):
            for index in th.randperm(len(states))[:used].split(batch_size):
                loss = F.mse_loss(self.critic(states[index]).flatten(), targets[index])
                self.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.critic.parameters(), self.model.max_grad_norm)
                self.optimizer.step()

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        returns, complete = monte_carlo_returns(
            buffer.rewards, buffer.episode_starts, self.model._last_episode_starts, self.model.gamma
        )
        n = buffer.buffer_size * buffer.n_envs
        observations = (
            {key: obs.reshape(n, *obs.shape[2:]).copy() for key, obs in buffer.observations.items()}
            if isinstance(buffer.observations, dict)
            else buffer.observations.reshape(n, *buffer.observations.shape[2:]).copy()
        )
        states = self._states(observations)
        mask = th.as_tensor(complete.reshape(-1), device=states.device)
        target = th.as_tensor(returns.reshape(-1), dtype=th.float32, device=states.device)
        with th.no_grad():
            vfa_before = self.critic(states).flatten()
        self._train_critic(states, th.as_tensor(buffer.returns.reshape(-1), device=states.device))
        with th.no_grad():
            vfa_after = self.critic(states).flatten()
        pevfa_before = th.tensor(buffer.values.reshape(-1), device=states.device)
        self._pending = {
            "observations": observations,
            "policy_id": self.model.history.latest_policy_id,
            "mask": mask,
            "target": target,
            "timesteps": self.model.num_timesteps,
            "pevfa_before": pevfa_before,
            "vfa_before": vfa_before,
            "vfa_after": vfa_after,
        }

    def _error(self, prediction: th.Tensor, pending: dict) -> float:
        mask = pending["mask"]
        if not mask.any():
            return float("nan")
        return F.mse_loss(prediction[mask], pending["target"][mask]).item()

    def _flush(self) -> None:
        """Log the errors of the last finished iteration (its critic update is done)."""
        pending, self._pending = self._pending, None
        if pending is None:
            return
        policy, history = self.model.policy, self.model.history
        training = policy.training
        policy.set_training_mode(False)
        with th.no_grad():
            data = PolicyRecord.from_numpy(history.records([pending["policy_id"]]), self.model.device)
            observations = obs_as_tensor(pending["observations"], self.model.device)
            pending["pevfa_after"] = policy.predict_values(observations, policy.embed(data)).flatten()
        policy.set_training_mode(training)
        errors = {key: self._error(pending[key], pending) for key in ERROR_KEYS}
        self.results.append({**errors, "timesteps": pending["timesteps"], "n_states": int(pending["mask"].sum())})
        for key, value in self.results[-1].items():
            self.logger.record(f"pevfa/local_gen/{key}", value)

    def _on_rollout_start(self) -> None:
        self._flush()

    def _on_training_end(self) -> None:
        self._flush()
        self.logger.dump(self.num_timesteps)


def read_scalars(log: str | pathlib.Path) -> dict[str, np.ndarray]:
    """Scalars of an SB3 run: a ``progress.csv`` (or a folder holding one), or a TensorBoard event folder."""
    log = pathlib.Path(log)
    csv_path = log if log.suffix == ".csv" else log / "progress.csv"
    if csv_path.exists():
        with open(csv_path) as handle:
            rows = list(csv.DictReader(handle))
        keys = {key for row in rows for key in row}
        return {key: np.array([float(row[key]) if row.get(key) not in (None, "") else np.nan for row in rows]) for key in keys}
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    except ImportError as error:
        raise FileNotFoundError(f"No progress.csv in {log}, and tensorboard is not installed to read events") from error
    events = list(log.rglob("events.out.tfevents.*"))
    if not events:
        raise FileNotFoundError(f"Neither progress.csv nor TensorBoard events in {log}")
    accumulator = EventAccumulator(str(events[0].parent))
    accumulator.Reload()

    # One row per dump, as in progress.csv: two dumps at the same step (the last iteration's and the one at the end
    # of training) are two rows, the k-th event of a tag at a step going to that step's k-th row.
    def keyed(tag: str) -> list[tuple[tuple[int, int], float]]:
        seen: dict[int, int] = {}
        rows = []
        for event in sorted(accumulator.Scalars(tag), key=lambda event: event.wall_time):
            seen[event.step] = seen.get(event.step, -1) + 1
            rows.append(((event.step, seen[event.step]), event.value))
        return rows

    tags = {tag: keyed(tag) for tag in accumulator.Tags()["scalars"]}
    keys = sorted({key for rows in tags.values() for key, _ in rows})
    position = {key: i for i, key in enumerate(keys)}
    scalars = {"time/total_timesteps": np.array([step for step, _ in keys], dtype=float)}
    for tag, rows in tags.items():
        values = np.full(len(keys), np.nan)
        for key, value in rows:
            values[position[key]] = value
        scalars[tag] = values
    return scalars


def plot_local_generalization(log: str | pathlib.Path, png: str | pathlib.Path, title: str = "") -> pathlib.Path:
    """The paper's Fig. 3b / 8 from a run's logs: the four error curves (log scale) and the return curve."""
    plt = pyplot()

    scalars = read_scalars(log)
    if "pevfa/local_gen/pevfa_before" not in scalars:
        raise ValueError(f"{log} has no pevfa/local_gen/* logs: train with LocalGeneralizationCallback")
    steps = scalars.get("pevfa/local_gen/timesteps", scalars["time/total_timesteps"])
    fig, ax = plt.subplots(figsize=(7, 4))
    styles = {
        "pevfa_before": ("tab:blue", "-", "PeVFA V(s, chi) before update"),
        "pevfa_after": ("tab:blue", "--", "PeVFA after update"),
        "vfa_before": ("tab:red", "-", "conventional V(s) before update"),
        "vfa_after": ("tab:red", "--", "conventional V(s) after update"),
    }
    for key, (color, style, label) in styles.items():
        values = scalars[f"pevfa/local_gen/{key}"]
        keep = np.isfinite(values) & np.isfinite(steps)
        ax.plot(steps[keep], values[keep], style, color=color, label=label)
    ax.set(yscale="log", xlabel="environment steps", ylabel="MSE to collected returns", title=title)
    if "rollout/ep_rew_mean" in scalars:
        twin = ax.twinx()
        keep = np.isfinite(scalars["rollout/ep_rew_mean"])
        twin.plot(
            scalars["time/total_timesteps"][keep], scalars["rollout/ep_rew_mean"][keep], color="tab:green", label="return"
        )
        twin.set_ylabel("average episode return", color="tab:green")
    ax.legend(loc="upper left", fontsize=8)
    return save_figure(fig, png)
