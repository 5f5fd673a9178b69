"""What the training logs of a learning benchmark say after the peak: why a return falls once it has peaked.

Reads the SB3 log tables that every run of ``benchmarks/learning.py`` printed (``<out>/runs/<run>/output.log``,
one table per iteration), keeps them compactly as ``<out>/logs/<run>.json`` (the run folders are not kept), and
for one env reports per variant, mean over seeds:

- the evaluation curve's peak (max average return), the final return (mean of the last three evaluations) and the
  drop between them, and where the peak came; the same drop from the best mean of three consecutive evaluations
  (a maximum over an oscillating curve is biased upwards: this drop is the sustained part), and how far one
  evaluation swings from the next late in the run against one evaluation's standard error (the policy's change
  against the evaluation's noise);
- training signals before and after the peak: the on-policy critic's explained variance and value loss, the
  critic's loss on historical samples, the policy's KL per update, its std, and what tells whether the critic can
  tell policies apart (saturated embedding units, ``||dV/dchi||``);
- with ``--windows``, the same signals per window of env steps (the same steps for every run, so that runs which
  peak early and late are compared at equal training). A window ``(low, high]`` averages the runs that reached
  ``high`` (its ``seeds`` column counts them); steps after the last edge are not reported. SB3 dumps an update's
  ``train/*`` values with the next rollout's table, so they are dated up to one rollout (``n_steps``) late.

    python benchmarks/training_logs.py --out docs/results/sb3-defaults/ablation --env Hopper-v5 \
        --plot docs/results/sb3-defaults/ablation_logs.png
"""

from engine.commands import training_logs_main

if __name__ == "__main__":
    training_logs_main(description=__doc__)
