"""Watch / evaluate a trained agent with rl-zoo3's `enjoy` (every flag of it).

python -m sb3_pevfa.enjoy --algo ppo_pevfa --env Hopper-v5 -f logs/
"""

from sb3_pevfa.extras import exit_without_extra
from sb3_pevfa.rl_zoo import run_zoo_script


def main(argv: list[str] | None = None) -> None:
    exit_without_extra("zoo", "python -m sb3_pevfa.enjoy")
    from rl_zoo3.enjoy import enjoy as script

    run_zoo_script(script, argv, default_config=False, watch=True)


if __name__ == "__main__":
    main()
