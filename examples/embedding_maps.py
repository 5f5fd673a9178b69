"""Embedding maps (paper Fig. 5, 18, 19): t-SNE and PCA of every recorded policy's embedding, coloured by return
and by iteration, from a saved model and its history (or a fresh short run).

    python examples/embedding_maps.py --model runs/example/model.zip --history runs/example/history.npz
    python examples/embedding_maps.py --env CartPole-v1 --timesteps 50000      # train, then map
    python examples/embedding_maps.py --tiny

Needs the diagnostics extra: pip install -e ".[diagnostics]"
"""

from sb3_pevfa.extras import exit_without_extra

exit_without_extra("diagnostics", "examples/embedding_maps.py")

import argparse
import pathlib

import torch as th

from sb3_pevfa import PPOPeVFA
from sb3_pevfa.diagnostics import plot_embedding_maps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=pathlib.Path, default=None)
    parser.add_argument("--history", type=pathlib.Path, default=None)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--timesteps", type=int, default=50_000)
    parser.add_argument("--representation", default="opr")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/embedding_maps"))
    parser.add_argument("--tiny", action="store_true", help="a 1k-step CartPole run (a smoke test)")
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.model is not None:
        if args.history is None:
            parser.error("--model needs --history (the embeddings are of the policies recorded in it)")
        model = PPOPeVFA.load(args.model)
        model.load_history(args.history)
    else:
        kwargs = dict(n_steps=64, batch_size=32, history_learning_starts=0) if args.tiny else {}
        model = PPOPeVFA("MlpPolicy", args.env, representation=args.representation, seed=0, **kwargs)
        model.learn(1024 if args.tiny else args.timesteps)
    png = plot_embedding_maps(model, args.out / "embedding_maps.png")
    print(f"{model.history.n_policies} policies mapped: {png}")


if __name__ == "__main__":
    main()
