"""Embedding maps (paper Fig. 5, 18, 19): t-SNE and PCA of every recorded policy's embedding, coloured by return
and by iteration, from a saved model and its history (or a fresh short run).

    python examples/embedding_maps.py --model runs/example/model.zip --history runs/example/history.npz
    python examples/embedding_maps.py --env CartPole-v1 --timesteps 50000      # train, then map
    python examples/embedding_maps.py --tiny
    python examples/embedding_maps.py --algo sac_pevfa --env Pendulum-v1 --timesteps 20000  # SACPeVFA's snapshots

Needs the diagnostics extra: pip install -e ".[diagnostics]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("diagnostics", "examples/embedding_maps.py")

import argparse
import pathlib

import torch as th

from sb3_pevfa.diagnostics import plot_embedding_maps
from sb3_pevfa.rl_zoo import ALGORITHMS, OFF_POLICY_ALGORITHMS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=sorted(ALGORITHMS), default="ppo_pevfa", help="the model's algorithm")
    parser.add_argument("--model", type=pathlib.Path, default=None)
    parser.add_argument("--history", type=pathlib.Path, default=None, help="its history (snapshots: save_history's file)")
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--timesteps", type=int, default=50_000)
    parser.add_argument("--representation", default="opr")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/embedding_maps"))
    parser.add_argument("--tiny", action="store_true", help="a 1k-step run (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.model is not None:
        if args.history is None:
            parser.error("--model needs --history (the embeddings are of the policies recorded in it)")
        watch = dict(buffer_size=1) if args.algo in OFF_POLICY_ALGORITHMS else {}  # the map reads no replay buffer
        model = ALGORITHMS[args.algo].load(args.model, **watch)
        model.load_history(args.history)
    else:
        tiny = dict(learning_starts=100, snapshot_freq=100) if args.algo in OFF_POLICY_ALGORITHMS else dict(n_steps=64)
        kwargs = dict(batch_size=32, history_learning_starts=0, **tiny) if args.tiny else {}
        model = ALGORITHMS[args.algo]("MlpPolicy", args.env, representation=args.representation, seed=0, **kwargs)
        model.learn(1024 if args.tiny else args.timesteps)
    png = plot_embedding_maps(model, args.out / "embedding_maps.png")
    print(f"{model.history.n_policies} policies mapped: {png}")


if __name__ == "__main__":
    main()
