"""Train with rl-zoo3: every rl-zoo3 `train.py` flag, plus `--search-space {full,small}` for `--optimize`.

python -m sb3_pevfa.train --algo ppo_pevfa --env Hopper-v5
"""

from sb3_pevfa.extras import exit_without_extra
from sb3_pevfa.rl_zoo import run_zoo_script


def main(argv: list[str] | None = None) -> None:
    exit_without_extra("zoo", "python -m sb3_pevfa.train")
    from rl_zoo3.train import train as script

    run_zoo_script(script, argv, default_config=True)


if __name__ == "__main__":
    main()
