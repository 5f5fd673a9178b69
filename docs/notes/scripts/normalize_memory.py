"""Peak memory of re-expressing a whole history in today's VecNormalize statistics at once vs in chunks.

``VecNormalize.normalize_obs`` copies its input and computes in float64; recomputed targets normalise every
historical observation at each refresh. This measures the peak (``tracemalloc``, which sees numpy's allocations) for
a 200k-sample history of Humanoid-sized observations (348 floats), at once and in chunks of
``sb3_pevfa.pevfa.history.NORMALIZE_CHUNK`` rows.

    python docs/notes/scripts/normalize_memory.py
"""

import argparse
import tracemalloc

import numpy as np
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecNormalize

from sb3_pevfa.pevfa.history import NORMALIZE_CHUNK


def peak_mib(env: VecNormalize, observations: np.ndarray, chunk: int) -> float:
    tracemalloc.start()
    for start in range(0, len(observations), chunk):
        env.normalize_obs(observations[start : start + chunk])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--obs-dim", type=int, default=348)
    args = parser.parse_args()
    env = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1))
    env.obs_rms = RunningMeanStd(shape=(args.obs_dim,))
    observations = np.random.default_rng(0).standard_normal((args.samples, args.obs_dim)).astype(np.float32)
    for chunk in (args.samples, NORMALIZE_CHUNK):
        peak = peak_mib(env, observations, chunk)
        print(f"{args.samples} x {args.obs_dim} observations, chunks of {chunk}: peak {peak:.0f} MiB")


if __name__ == "__main__":
    main()
