"""Cost of each policy representation: parameters, and the time of one forward + backward pass over P policies.

A historical critic update encodes the distinct policies of its batch: at most ``history_batch_policies`` (8) by
default; with the paper's uniform 64-sample batches about 47 once the history holds its default 200k samples of ~98
policies on a 2048-step task. The on-policy update encodes one (the behaviour policy) per update, or per minibatch
with ``rollout_encoder_gradient=True``. One torch thread, the actor of SB3's default MlpPolicy on the task.

    python benchmarks/encoder_cost.py --env Hopper-v5 --out docs/results/encoder-cost/encoder_cost_hopper.json

``--update`` also times one whole historical critic update whose batch (``history_batch_size``, 256) spreads over the
P policies: the encoder, the critic, the backward pass and the optimizer step (``_critic_step``). ``--clock cpu``
measures the process's CPU time (``time.process_time``) instead of wall-clock time, for a machine that is busy:

    python benchmarks/encoder_cost.py --env Hopper-v5 --representations opr fingerprint --policies 1 50 200 --update \
        --clock cpu --repeats 50
"""

import argparse
import json
import pathlib
import time
from collections.abc import Callable

import numpy as np
import torch as th
from torch.nn import functional as F

from sb3_pevfa import REPRESENTATIONS, PPOPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord

#: Clocks of ``--clock``
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def seconds_per_call(fn: Callable[[], None], repeats: int, clock: Callable[[], float] = time.perf_counter) -> float:
    for _ in range(10):
        fn()
    start = clock()
    for _ in range(repeats):
        fn()
    return (clock() - start) / repeats


def historical_update(model: PPOPeVFA, data: PolicyRecord) -> Callable[[], None]:
    """One historical critic update (as ``_train_on_history``'s) on random observations of the P policies of ``data``."""
    policy = model.policy
    n_samples = model.history_batch_size
    observations = th.as_tensor(np.stack([model.observation_space.sample() for _ in range(n_samples)]))
    owners = th.arange(n_samples) % len(data.params)
    targets = th.randn(n_samples)

    def call() -> None:
        values = policy.predict_values(observations, policy.embed(data)[owners])
        model._critic_step(F.mse_loss(values.flatten(), targets), "historical value loss")

    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--policies", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--repeats", type=int, default=300)
    parser.add_argument("--representations", nargs="+", default=list(REPRESENTATIONS), choices=REPRESENTATIONS)
    parser.add_argument("--update", action="store_true", help="also time one whole historical critic update")
    parser.add_argument("--clock", default="wall", choices=sorted(CLOCKS))
    parser.add_argument("--out", type=pathlib.Path, default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    clock = CLOCKS[args.clock]
    rows = []
    for name in args.representations:
        model = PPOPeVFA("MlpPolicy", args.env, representation=name, seed=0)
        policy = model.policy
        encoder = policy.representation
        row = {"representation": name, "parameters": sum(p.numel() for p in encoder.parameters()), "ms": {}}
        for n in args.policies:
            pairs = n * policy.n_recorded_pairs
            action_dim = policy.behaviour_actions.shape[1]
            actions = np.array([model.action_space.sample() for _ in range(pairs)], np.float32).reshape(pairs, action_dim)
            data = PolicyRecord(
                th.randn(n, policy.layout.n_params),
                th.randn(n, policy.n_recorded_pairs, policy.behaviour_states.shape[1]),
                th.as_tensor(actions).reshape(n, policy.n_recorded_pairs, action_dim),
                th.rand(n, policy.code_dim),
            )
            trainable = any(p.requires_grad for p in encoder.parameters())

            def call(data=data, trainable=trainable, encoder=encoder):
                out = encoder(data)
                if trainable:
                    out.sum().backward()

            row["ms"][n] = 1e3 * seconds_per_call(call, args.repeats, clock)
            if args.update:
                update = historical_update(model, data)
                row.setdefault("update_ms", {})[n] = 1e3 * seconds_per_call(update, args.repeats, clock)
        rows.append(row)
        times = ", ".join(f"P={n}: {ms:.2f} ms" for n, ms in row["ms"].items())
        updates = ", ".join(f"P={n}: {ms:.2f} ms" for n, ms in row.get("update_ms", {}).items())
        updates = f"; historical update {updates}" if updates else ""
        print(f"{name:>11}: {row['parameters']:>6} parameters, {times}{updates}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"env": args.env, "clock": args.clock, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
