"""Learning benchmark: SB3 PPO (A2C) vs PPOPeVFA (A2CPeVFA) variants through rl-zoo3, at identical hyperparameters.

Every (env, variant, seed) is one rl-zoo3 training (``python -m sb3_pevfa.train --algo ppo|ppo_pevfa|a2c|a2c_pevfa``)
reading the same config file per base algorithm (``benchmarks/hyperparams/learning.yml``: SB3's PPO defaults;
``learning_a2c.yml``: SB3's A2C defaults); PeVFA variants add only their PeVFA options (``--hyperparams``).
rl-zoo3's EvalCallback evaluates every ``--eval-freq`` steps (``--eval-episodes`` deterministic episodes); its
``evaluations.npz`` becomes one JSON file per run. The runs are scheduled by the campaign engine (``campaign.py``,
protocol ``zoo``): one Optuna study per invocation in ``<out>/campaign.journal``, ``--workers`` processes with one torch
thread each, an interrupted sweep resumed by the same command (the runs of dead workers enqueued again); the
finished runs are written to ``<out>`` as JSON, and tasks, variants and seeds whose runs all have one are skipped
(runs of other steps or evaluation settings in ``<out>`` are refused: give another ``--out``).

    # SB3's defaults (docs/results-ppo-settings.md): Hopper-v5 and Walker2d-v5, 300k steps, 5 seeds
    python benchmarks/learning.py --env Hopper-v5 Walker2d-v5 --variants ppo pevfa-opr --seeds 0 1 2 3 4
    # the report only: Table-1 style markdown with rliable bootstrap CIs, and the learning curves
    python benchmarks/learning.py --report --out runs/learning --plot runs/learning.png
    # runs of several invocations on machines of different speeds: per-second views against each seed's PPO run
    python benchmarks/learning.py --report --paired --out docs/results/zoo-tuned/shipped-entries
    # A2C vs A2CPeVFA (SB3's A2C defaults), Hopper-v5, 100k steps, 5 seeds
    python benchmarks/learning.py --env Hopper-v5 --variants a2c a2c-pevfa-opr --timesteps 100000 --eval-freq 10000 \
        --out docs/results/notes/a2c-pevfa/learning_a2c --baseline a2c --plot docs/results/notes/a2c-pevfa/learning_a2c.png
"""

from engine.commands import learning_main

if __name__ == "__main__":
    learning_main(description=__doc__)
