"""Run one of rl-zoo3's plot scripts and save every figure it draws as a PNG (they only open windows).

    python -m sb3_pevfa.rl_zoo.save_plots runs/zoo/plot_train rl_zoo3.plots.plot_train -a ppo_pevfa -e CartPole-v1 -f runs/zoo/
    python -m sb3_pevfa.rl_zoo.save_plots runs/zoo/all_plots rl_zoo3.plots.all_plots -a ppo ppo_pevfa -e CartPole-v1 \
        -f runs/zoo --no-display

The first argument is the PNG prefix (``<prefix>_<n>.png``), the second the rl-zoo3 module, the rest its flags.
"""

import pathlib
import runpy
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def main() -> None:
    prefix, module, *flags = sys.argv[1:]
    plt.show = lambda *args, **kwargs: None  # the scripts end with a window: keep their figures open instead
    sys.argv = [module, *flags]
    runpy.run_module(module, run_name="__main__")
    pathlib.Path(prefix).parent.mkdir(parents=True, exist_ok=True)
    for number in plt.get_fignums():
        path = f"{prefix}_{number}.png"
        plt.figure(number).savefig(path, dpi=100)
        print(f"saved {path}")


if __name__ == "__main__":
    main()
