"""CPU time of SACPeVFA's gradient step and of its parts, beside SB3 SAC's step, on ``--env`` (one torch thread).

Both models learn ``--warmup`` env steps first (SACPeVFA with a snapshot every 50 gradient steps, so that its
updates draw 8 distinct snapshots); then each part is timed over ``--steps`` calls after 10 untimed ones: SB3's
``train`` of one gradient step for SAC and for SACPeVFA (its critics reading chi of the live actor, without the
snapshots' update), and one snapshots' update (``OffPolicyPeVFA._train_on_snapshots``) split into its stages.
``--sizes`` times whole snapshots' updates of other sizes instead of the stages: ``BATCH/POLICIES`` each (fewer
snapshots where fewer exist; the table names what was drawn). The process's denormal setting applies throughout
(``--flush-denormals``: as ``train`` runs by default).

    python docs/notes/scripts/sac_step_parts.py --env Hopper-v5
    python docs/notes/scripts/sac_step_parts.py --env Hopper-v5 --flush-denormals   # for the whole process
    python docs/notes/scripts/sac_step_parts.py --flush-denormals --sizes 64/8 128/4 256/4 256/8 512/8 1024/8 256/16
"""

import argparse
import time
from collections.abc import Callable

import torch as th
from stable_baselines3 import SAC
from torch.nn import functional as F

from sb3_pevfa import SACPeVFA
from sb3_pevfa.pevfa.records import PolicyRecord


def ms_per_call(function: Callable[[], object], n: int) -> float:
    for _ in range(10):
        function()
    start = time.process_time()
    for _ in range(n):
        function()
    return 1000 * (time.process_time() - start) / n


def snapshot_update_stages(model: SACPeVFA, n: int) -> dict[str, float]:
    """``_train_on_snapshots`` with a clock between its stages: ms per update of each."""
    spent: dict[str, float] = {}
    critic, target = model.policy.critic, model.policy.critic_target

    def lap(name: str, since: float) -> float:
        now = time.process_time()
        spent[name] = spent.get(name, 0.0) + now - since
        return now

    def update() -> None:
        clock = time.process_time()
        ids = model.history.sample_policy_ids(model.history_batch_policies)
        per_policy = model.history_batch_size // model.history_batch_policies
        data = model.replay_buffer.sample(per_policy * len(ids))
        clock = lap("replay sample", clock)
        records = PolicyRecord.from_numpy(model.history.records(ids), model.device)
        pairing = th.arange(len(ids)).repeat_interleave(per_policy)
        clock = lap("snapshot records", clock)
        with th.no_grad():
            features = model.actor.extract_features(data.next_observations, model.actor.features_extractor)
            actions, log_prob = model._snapshot_actions(records, features.reshape(len(ids), per_policy, -1))
            clock = lap("snapshots' next actions", clock)
            target_chi = target.representation(records)
            clock = lap("target encoder, 8 snapshots", clock)
            targets = model.td_targets(data, target(data.next_observations, actions, target_chi, pairing), log_prob)
            clock = lap("target critics", clock)
        chi = critic.representation(records)
        clock = lap("encoder with gradient, 8 snapshots", clock)
        values = critic(data.observations, data.actions, chi, pairing)
        loss = model.critic_loss_scale * sum(F.mse_loss(value, targets) for value in values)
        clock = lap("critics", clock)
        critic.optimizer.zero_grad()
        loss.backward()
        clock = lap("backward", clock)
        critic.optimizer.step()
        lap("Adam step", clock)

    for _ in range(10):
        update()
    spent.clear()
    start = time.process_time()
    for _ in range(n):
        update()
    spent["whole update"] = time.process_time() - start
    return {name: 1000 * seconds / n for name, seconds in spent.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--warmup", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--flush-denormals", action="store_true", help="torch.set_flush_denormal(True) from the start")
    parser.add_argument("--sizes", nargs="*", default=[], help="BATCH/POLICIES of whole snapshots' updates to time")
    args = parser.parse_args()
    sizes = [tuple(int(n) for n in size.split("/")) for size in args.sizes]
    if any(batch % policies for batch, policies in sizes):
        parser.error(f"--sizes {args.sizes}: each BATCH must be a multiple of its POLICIES")
    th.set_num_threads(1)
    th.set_flush_denormal(args.flush_denormals)
    sac = SAC("MlpPolicy", args.env, learning_starts=500, seed=0).learn(args.warmup)
    pevfa = SACPeVFA(  # flush_denormal=False: the process's setting throughout
        "MlpPolicy", args.env, learning_starts=500, seed=0, history_train_freq=0, snapshot_freq=50, flush_denormal=False
    )
    pevfa.learn(args.warmup)
    print(f"| part | ms per call ({args.steps} calls) |\n|---|---|")
    print(f"| SB3 SAC: one gradient step | {ms_per_call(lambda: sac.train(1, sac.batch_size), args.steps):.2f} |")
    step = ms_per_call(lambda: SAC.train(pevfa, 1, pevfa.batch_size), args.steps)
    print(f"| SACPeVFA: SB3's gradient step (critics on the live actor's chi) | {step:.2f} |")
    for batch, policies in sizes:
        pevfa.history_batch_size, pevfa.history_batch_policies = batch, policies
        drawn = min(policies, pevfa.history.n_policies)  # all snapshots where fewer exist, batch / policies each
        ms = ms_per_call(pevfa._train_on_snapshots, args.steps)
        print(f"| SACPeVFA: snapshots' update of {batch // policies * drawn} transitions, {drawn} snapshots | {ms:.2f} |")
    if not sizes:
        for name, ms in snapshot_update_stages(pevfa, args.steps).items():
            print(f"| SACPeVFA: snapshots' update, {name} | {ms:.2f} |")


if __name__ == "__main__":
    main()
