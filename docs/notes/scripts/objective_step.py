"""CPU time of one step of the contrastive objective (CL), by policies per batch, and what its cadence costs.

A PPOPeVFA model with CL on ``--env`` gets a history of ``--policies`` recorded policies
(:func:`history_step.history_model`); each ``batch_policies`` setting times ``--steps`` CL steps
(``PeVFAAlgorithm._train_objectives``: sample policies, encode two augmentations, InfoNCE, Adam, momentum update)
after 5 untimed ones. One 2048-step rollout costs ``2048 / train_freq`` steps: the paper's cadence (10 env steps)
and PPOPeVFA's default (its historical updates' 40) are tabulated.

    python docs/notes/scripts/objective_step.py --env Hopper-v5
"""

from history_step import cpu_ms_per_step, history_model, parse_arguments

from sb3_pevfa import PPOPeVFA

#: policies per CL batch timed (the paper's: 32)
BATCH_POLICIES = [32, 64, 128]
#: env steps per CL step tabulated: the paper's, and PPOPeVFA's default (its historical updates' cadence)
CADENCES = [10, 40]


def time_steps(model: PPOPeVFA, batch_policies: int, steps: int) -> float:
    """CPU milliseconds per CL step."""
    objective = model.policy.objectives["cl"]
    objective.batch_policies = batch_policies
    train_freq = model.objective_train_freq(objective)

    def run(n: int) -> int:
        model._objective_credit["cl"] = n * train_freq - model.n_steps * model.n_envs  # exactly n steps
        return len(model._train_objectives()["cl_updates"])

    return cpu_ms_per_step(model, run, steps)


def main() -> None:
    args = parse_arguments(__doc__, 146, "policies in the history (a 300k-step run: ~146)")
    model = history_model(args.env, args.arch, args.policies, representation_objectives=("cl",),
                          objective_kwargs={"cl": {"learning_starts": 0}})  # fmt: skip
    cadences = " | ".join(f"ms per 2048 env steps, every {freq}" for freq in CADENCES)
    print(f"| {args.env}, actor {args.arch}, {args.policies} policies | ms per CL step | {cadences} |")
    print("|---|---|" + "---|" * len(CADENCES))
    for batch_policies in BATCH_POLICIES:
        ms = time_steps(model, batch_policies, args.steps)
        per_rollout = " | ".join(f"{ms * 2048 / freq:.0f}" for freq in CADENCES)
        print(f"| {batch_policies} policies | {ms:.2f} | {per_rollout} |", flush=True)


if __name__ == "__main__":
    main()
