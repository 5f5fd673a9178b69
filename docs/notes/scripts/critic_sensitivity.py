"""Can the critic tell policies apart? Saturation of the embedding stream and ||dV/dchi|| at the end of a run.

Trains PPOPeVFA (the README's CartPole-v1 run, 30k steps, seed 0) with each embedding-stream setting and reports,
at the behaviour policy: the fraction of embedding-stream units whose activation has a slope below 0.1
(``pevfa/embedding_saturated_fraction``), the mean ``||dV/dchi||`` over rollout states (``pevfa/value_chi_gradient``)
and the norm of chi. Also: the values of the first and the last recorded policy at the same states (how far V moves
with chi across the whole run).

    python docs/notes/scripts/critic_sensitivity.py --out docs/results/notes/critic-stream-pilot/critic_sensitivity.json
"""

import argparse
import json
import pathlib

import numpy as np
import torch as th
from torch import nn

from sb3_pevfa import PolicyRecord, PPOPeVFA

#: Each embedding stream, spelled out (the defaults changed: ReLU + layer-normalised chi since the 300k ablation)
SETTINGS = {
    "tanh (the actor's; the earlier default)": dict(critic_activation_fn=None, chi_normalization="none"),
    "relu (paper)": dict(critic_activation_fn=nn.ReLU, chi_normalization="none"),
    "tanh + layernorm chi": dict(critic_activation_fn=None, chi_normalization="layernorm"),
    "relu + layernorm chi (default)": dict(critic_activation_fn=nn.ReLU, chi_normalization="layernorm"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("--timesteps", type=int, default=30_000)
    parser.add_argument("--out", type=pathlib.Path, default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    rows = []
    for name, policy_kwargs in SETTINGS.items():
        model = PPOPeVFA("MlpPolicy", args.env, policy_kwargs=policy_kwargs, seed=0).learn(args.timesteps)
        policy, history = model.policy, model.history
        policy.set_training_mode(False)
        chi = policy.behaviour_embedding()
        obs = th.as_tensor(history.samples()[0][-256:])
        with th.no_grad():
            ends = [
                policy.embed(PolicyRecord.from_numpy(history.records([i])))
                for i in (history.policy_ids[0], history.latest_policy_id)
            ]
            first, last = (policy.predict_values(obs, e).numpy().ravel() for e in ends)
        row = {
            "setting": name,
            "saturated_fraction": policy.value_net.saturated_fraction(chi),
            "value_chi_gradient": model.value_chi_gradient(),
            "chi_norm": chi.norm().item(),
            "first_vs_last_policy_value_gap": float(np.abs(first - last).mean()),
        }
        rows.append(row)
        print(", ".join(f"{k}: {v:.3f}" if isinstance(v, float) else f"{k}: {v}" for k, v in row.items()), flush=True)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"env": args.env, "timesteps": args.timesteps, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
