#!/usr/bin/env bash
# rl-zoo3 with PPOPeVFA: train PPO and PPOPeVFA on one config, watch, plot their evaluations, run a small search.
#
#   bash examples/zoo_commands.sh                   # CartPole-v1, 100k steps, 20 trials
#   TINY=1 bash examples/zoo_commands.sh            # a tiny budget (CI): about 25 s, most of it Python start-ups
#   ENV=Hopper-v5 LOGS=runs/zoo_hopper bash examples/zoo_commands.sh
#
# Needs the zoo extra: pip install -e ".[zoo]"
set -euo pipefail
python -c "from sb3_pevfa.extras import exit_without_extra; exit_without_extra('zoo', 'examples/zoo_commands.sh')"
ENV=${ENV:-CartPole-v1}
LOGS=${LOGS:-runs/zoo}
# TINY searches PeVFA's small space (small rollouts and networks): rl-zoo3's full PPO space can draw 2048-step
# rollouts on 8 envs, whose first update alone takes minutes
# (and smooths its training curve over 5 episodes, not rl-zoo3's 100: a tiny run has a few dozen)
if [ "${TINY:-0}" = 1 ]; then N=512; TRIALS=2; EVAL=256; SPACE=small; WINDOW=5; else N=100000; TRIALS=20; EVAL=10000; SPACE=full; WINDOW=100; fi
export MPLBACKEND=Agg

# 1. PPO and PPOPeVFA, same seed, rl-zoo3's EvalCallback every $EVAL steps (hyperparams/ppo_pevfa.yml holds the
#    same PPO settings as rl-zoo3's ppo.yml, plus the PeVFA ones)
for ALGO in ppo ppo_pevfa; do
  python -m sb3_pevfa.train --algo $ALGO --env "$ENV" -f "$LOGS" -n $N --seed 0 \
      --eval-freq $EVAL --eval-episodes 5 --num-threads 1
done

# 2. watch the trained PPOPeVFA agent (headless here; drop --no-render to see it)
python -m sb3_pevfa.enjoy --algo ppo_pevfa --env "$ENV" -f "$LOGS" -n 500 --no-render

# 3. rl-zoo3's plots and table of the evaluations (PPO vs PPOPeVFA), saved as PNGs (rl-zoo3 only opens windows)
python -m sb3_pevfa.rl_zoo.save_plots "$LOGS/plots/evaluations" rl_zoo3.plots.all_plots -a ppo ppo_pevfa -e "$ENV" \
    -f "$LOGS" -o "$LOGS/results" --no-display
python -m sb3_pevfa.rl_zoo.save_plots "$LOGS/plots/training" rl_zoo3.plots.plot_train -a ppo_pevfa -e "$ENV" -f "$LOGS/" \
    -w $WINDOW

# 4. a hyperparameter search with rl-zoo3's Optuna integration (PPO's space plus PeVFA's), journal storage; the
#    report (best parameters, all trials) is written under $LOGS/ppo_pevfa/
python -m sb3_pevfa.train --algo ppo_pevfa --env "$ENV" -f "$LOGS" -n $N -optimize --n-trials $TRIALS --n-jobs 1 \
    --sampler tpe --pruner median --n-evaluations 2 --eval-episodes 3 \
    --storage "$LOGS/study.log" --study-name "pevfa-$ENV" --num-threads 1 --seed 0 --search-space $SPACE
echo "zoo example done: logs and plots under $LOGS"
