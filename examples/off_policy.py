"""SACPeVFA (or TD3PeVFA): train with the critic's error on each next snapshot logged, save the model and its replay
buffer with the snapshots, load both, and go on training where it stopped.

python examples/off_policy.py                      # SACPeVFA on InvertedPendulum-v5, 2 x 10k steps
python examples/off_policy.py --algo td3_pevfa     # TD3PeVFA
python examples/off_policy.py --tiny               # seconds (CI)

Needs the diagnostics extra, and for the default env the mujoco one: pip install -e ".[diagnostics,mujoco]"
"""

from sb3_pevfa.extras import exit_without_env_extra, exit_without_extra

exit_without_extra("diagnostics", "examples/off_policy.py")

import argparse
import pathlib

import torch as th
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_pevfa import SACPeVFA, TD3PeVFA
from sb3_pevfa.diagnostics.q_local_generalization import QLocalGeneralizationCallback

ALGORITHMS = {"sac_pevfa": SACPeVFA, "td3_pevfa": TD3PeVFA}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=sorted(ALGORITHMS), default="sac_pevfa")
    # an env whose episodes terminate: a transition's return is scored once its episode ended, or went on 459 steps
    # (gamma 0.99), which Pendulum's 200-step time limit never allows
    parser.add_argument("--env", default="InvertedPendulum-v5")
    parser.add_argument("--timesteps", type=int, default=10_000, help="env steps before and after the reload")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/off_policy"))
    parser.add_argument("--tiny", action="store_true", help="2 x 600 steps, small networks (a smoke test)")
    args = parser.parse_args()
    exit_without_env_extra(args.env, f"examples/off_policy.py --env {args.env}")
    th.set_num_threads(1)  # one thread is faster for small networks on CPU
    algorithm = ALGORITHMS[args.algo]
    small = dict(learning_starts=200, batch_size=32, snapshot_freq=100, policy_kwargs=dict(net_arch=[32, 32]))
    timesteps = 600 if args.tiny else args.timesteps
    args.out.mkdir(parents=True, exist_ok=True)

    # a snapshot of the actor every snapshot_freq gradient steps; the callback scores each window between two of
    # them: the PeVFA's error on the returns of the next snapshot's transitions against a conventional critic's
    model = algorithm("MlpPolicy", args.env, seed=0, **(small if args.tiny else {}))
    diagnostic = QLocalGeneralizationCallback()
    model.learn(timesteps, callback=diagnostic)
    model.save(args.out / "model")
    model.save_replay_buffer(args.out / "replay_buffer")  # the snapshots beside it: replay_buffer.snapshots.npz
    th.save(diagnostic.state_dict(), args.out / "diagnostic.pt")  # its conventional critic and its results

    # the same env without a reset, the RNG states, the buffer and the snapshots: learning goes on as if never stopped
    model = algorithm.load(args.out / "model", env=model.get_env(), force_reset=False, restore_rng_state=True)
    model.load_replay_buffer(args.out / "replay_buffer")
    diagnostic = QLocalGeneralizationCallback()  # goes on with the conventional critic (its windows from the next snapshot)
    diagnostic.load_state_dict(th.load(args.out / "diagnostic.pt"))
    model.learn(timesteps, callback=diagnostic, reset_num_timesteps=False)
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=3 if args.tiny else 10)
    print(f"{args.env}, {args.algo}: {model.num_timesteps} steps, {model.history.n_policies} snapshots, "
          f"return {mean:.1f} +- {std:.1f}")  # fmt: skip
    for window in diagnostic.results[-3:]:  # errors before the window's updates: PeVFA's and the conventional critic's
        print(f"  snapshot {window['policy_id']} at {window['timesteps']} steps: PeVFA {window['pevfa_before']:.1f}, "
              f"conventional {window['vfa_before']:.1f} ({window['n_states']} transitions)")  # fmt: skip


if __name__ == "__main__":
    main()
