"""Record a video of a trained agent with rl-zoo3's ``record_video`` (every flag of it).

python -m sb3_pevfa.record_video --algo ppo_pevfa --env Hopper-v5 -f logs/ -n 1000
"""

import runpy

from sb3_pevfa.extras import exit_without_extra
from sb3_pevfa.rl_zoo import run_zoo_script


def main(argv: list[str] | None = None) -> None:
    exit_without_extra("zoo", "python -m sb3_pevfa.record_video")
    # rl-zoo3's record_video is a script (its code runs under `if __name__ == "__main__"`)
    run_zoo_script(lambda: runpy.run_module("rl_zoo3.record_video", run_name="__main__"), argv, watch=True)


if __name__ == "__main__":
    main()
