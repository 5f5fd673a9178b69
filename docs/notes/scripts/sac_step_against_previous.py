"""CPU time of SB3's gradient step for SAC, for SACPeVFA and for SACPeVFA with the critic head's first layer of a
previous version of ``sb3_pevfa/pevfa/q_critics.py`` (``--previous``, a copy of that file: its ``SplitLinear``) and
without the target critic's shared flat copy of the actor, interleaved rounds of ``--steps`` calls (one torch thread,
denormals flushed), after 1000 env steps of each model. Probes the step alone, not whole runs.

    git show ff68d6f:sb3_pevfa/pevfa/q_critics.py > /tmp/previous_q_critics.py
    python docs/notes/scripts/sac_step_against_previous.py --previous /tmp/previous_q_critics.py
"""

import argparse
import importlib.util
import statistics
import time

import torch as th
from stable_baselines3 import SAC

from sb3_pevfa import SACPeVFA
from sb3_pevfa.pevfa import q_critics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--previous", required=True, help="a copy of a previous q_critics.py")
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--steps", type=int, default=100)
    args = parser.parse_args()
    spec = importlib.util.spec_from_file_location("previous_q_critics", args.previous)
    previous = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(previous)
    th.set_num_threads(1)
    th.set_flush_denormal(True)
    layers = {False: q_critics.SplitLinear.__dict__.copy(), True: previous.SplitLinear.__dict__}

    def use(old: bool) -> None:
        for name in ("forward", "backward"):
            setattr(q_critics.SplitLinear, name, layers[old][name])

    kwargs = dict(learning_starts=500, seed=0)
    models = {"SAC": (SAC("MlpPolicy", args.env, **kwargs).learn(1000), False)}
    for name, old in (("SACPeVFA, previous", True), ("SACPeVFA", False)):
        model = SACPeVFA("MlpPolicy", args.env, history_train_freq=0, flush_denormal=False, **kwargs).learn(1000)
        if old:
            model.policy.critic_target._actor_cache = {}  # its own flat copy of the actor, as before
        models[name] = (model, old)
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.rounds):
        for name, (model, old) in models.items():
            use(old)
            start = time.process_time()
            for _ in range(args.steps):
                SAC.train(model, 1, model.batch_size)
            times[name].append(1000 * (time.process_time() - start) / args.steps)
    use(False)
    print("| model | ms per gradient step, median [range] | to SAC's, median of rounds |\n|---|---|---|")
    for name, values in times.items():
        ratio = statistics.median(v / s for v, s in zip(values, times["SAC"]))
        print(f"| {name} | {statistics.median(values):.2f} [{min(values):.2f}, {max(values):.2f}] | {ratio:.2f}x |")


if __name__ == "__main__":
    main()
