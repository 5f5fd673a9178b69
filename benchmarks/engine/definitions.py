"""What the campaigns are: the protocols and their variants (each variant's constructor arguments), a campaign's grid
(``Campaign``) and this repository's campaigns (``CAMPAIGNS``). A stored campaign's definition and its checkpoint folder
derive from what this file says: a variant that a stored campaign uses never changes (start another campaign)."""

import dataclasses
import hashlib
import json
import os
import pathlib
from typing import Any

from stable_baselines3 import SAC

from sb3_pevfa import SACPeVFA
from sb3_pevfa.pevfa.arguments import PAPER_SCHEDULE
from sb3_pevfa.protocols import authors_protocol, make_authors_env, paper_protocol

ROOT = pathlib.Path(__file__).resolve().parents[2]
CAMPAIGN_DIR = ROOT / "benchmarks" / "campaigns"
#: The six tasks of the paper's Table 1 in today's versions (the paper: -v1 tasks of gym 0.9.1, LunarLander-v2)
TABLE1_TASKS = (
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "InvertedDoublePendulum-v5",
    "LunarLanderContinuous-v3",
)
#: Where a running trial keeps its checkpoint: outside the work tree, which a new session may lay anew
CHECKPOINT_DIR = pathlib.Path(os.environ.get("SB3_PEVFA_CHECKPOINTS", pathlib.Path.home() / ".cache" / "sb3-pevfa"))
#: Today's cheaper schedule of historical updates (PPOPeVFA's defaults): 256 samples of 8 policies per 40 steps
DEFAULT_SCHEDULE = dict(history_batch_size=256, history_batch_policies=8, history_train_freq=40, rollout_encoder_gradient=None)
#: The shared rl-zoo3 hyperparameters of each base algorithm of the zoo protocol (a campaign's ``conf`` replaces them)
CONFS = {
    "ppo": ROOT / "benchmarks" / "hyperparams" / "learning.yml",
    "a2c": ROOT / "benchmarks" / "hyperparams" / "learning_a2c.yml",
}

#: The zoo protocol's variants (``learning.py``'s): each one's PeVFA options (rl-zoo3 ``--hyperparams``); "ppo" is
#: SB3's PPO. "pevfa-opr" is PPOPeVFA's defaults (results recorded before the cheaper schedule hold what
#: "pevfa-opr-paper-schedule" gives today). Variants named "a2c..." train A2C / A2CPeVFA instead.
ZOO_VARIANTS: dict[str, dict | None] = {
    "ppo": None,
    "pevfa-none": dict(representation="none"),
    "pevfa-random": dict(representation="random"),
    "pevfa-opr": {},
    "pevfa-spr": dict(representation="spr"),
    "pevfa-fingerprint": dict(representation="fingerprint"),
    "pevfa-opr-critic-first": dict(update_order="critic_first"),
    # CL on the historical updates' cadence (the default since CL's train_freq=None; every 10 env steps before)
    "pevfa-opr-cl": dict(representation_objectives=("cl",)),
    "pevfa-opr-cl-paper-cadence": dict(representation_objectives=("cl",), objective_kwargs={"cl": {"train_freq": 10}}),
    "pevfa-spr-aux": dict(representation="spr", representation_objectives=("aux",)),
    "pevfa-opr-paper": dict(
        update_order="critic_first", value_target_lambda=1.0, learning_rate=1e-4, critic_learning_rate=1e-3, **PAPER_SCHEDULE
    ),
    # the paper's historical updates (64 uniform samples per 10 steps, the encoder also trained on the rollout)
    "pevfa-opr-paper-schedule": dict(PAPER_SCHEDULE),
    # the critic's embedding stream (issue: chi saturated a Tanh stream), each spelled out: the paper's ReLU, a
    # layer-normalised chi, both (the default since the 300k ablation), and the earlier default (the actor's Tanh)
    "pevfa-opr-relu": dict(policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='none')"),
    "pevfa-opr-relu-layernorm": dict(policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='layernorm')"),
    "pevfa-opr-layernorm": dict(policy_kwargs="dict(critic_activation_fn=None, chi_normalization='layernorm')"),
    "pevfa-opr-tanh": dict(policy_kwargs="dict(critic_activation_fn=None, chi_normalization='none')"),
    "pevfa-opr-relu-layernorm-recomputed": dict(
        policy_kwargs="dict(critic_activation_fn=nn.ReLU, chi_normalization='layernorm')", history_targets="recomputed"
    ),
    # targets of the historical samples: recomputed with the current critic, or the paper's Monte-Carlo returns
    "pevfa-opr-recomputed": dict(history_targets="recomputed"),
    "pevfa-opr-mc": dict(value_target_lambda=1.0),
    # chi without the historical updates (the encoder then learns from the rollout's value loss)
    "pevfa-opr-no-history": dict(history_train_freq=0),
    # under VecNormalize: the history as its rollouts saw it (before the history was re-expressed in today's statistics)
    "pevfa-opr-stale-normalization": dict(history_normalization="rollout"),
    # the critic and encoder at 10x the config's learning rate (the paper's ratio: actor 1e-4, critic 1e-3), and
    # its control: the same critic and rate without chi and without historical updates
    "pevfa-opr-critic-lr-x10": dict(critic_learning_rate_scale=10),
    "pevfa-none-no-history-critic-lr-x10": dict(representation="none", history_train_freq=0, critic_learning_rate_scale=10),
    # an embedding stream whose units cannot die (ELU: a gradient at every input), where ReLU units went flat
    "pevfa-opr-elu": dict(policy_kwargs="dict(critic_activation_fn=nn.ELU)"),
    # a quarter of the historical updates (one per 160 env steps): less of the mixture of old policies in the critic
    "pevfa-opr-history-freq-160": dict(history_train_freq=160),
    # a fifth of the history (40k samples: the last ~20 policies of 2048 steps, where 200k holds ~98): younger data
    "pevfa-opr-history-40k": dict(history_buffer_size=40_000),
    "a2c": None,
    "a2c-pevfa-opr": {},
}


def base_algorithm(variant: str) -> str:
    """The SB3 algorithm that a zoo variant builds on: A2C for the variants named "a2c...", else PPO."""
    return "a2c" if variant.startswith("a2c") else "ppo"


#: protocol -> variant -> PPOPeVFA constructor arguments (None: SB3's PPO with its defaults)
VARIANTS: dict[str, dict[str, dict[str, Any] | None]] = {
    "paper": {
        "ppo": paper_protocol("ppo"),
        "opr-e2e": paper_protocol("ppo_pevfa"),
        "opr-e2e-default-schedule": paper_protocol("ppo_pevfa", **DEFAULT_SCHEDULE),
        "random": paper_protocol("ppo_pevfa", representation="random"),
        "opr-cl": paper_protocol("ppo_pevfa", representation_objectives=("cl",)),
        "spr-e2e": paper_protocol("ppo_pevfa", representation="spr"),
        "fingerprint-e2e": paper_protocol("ppo_pevfa", representation="fingerprint"),
        # OPR-E2E with the local-generalization diagnostic (paper Fig. 3b / 8): a conventional critic of the paper's
        # PPO (2x128 ReLU, its learning rate) trained beside it; the diagnostic's critic counts in its CPU time
        "opr-e2e+local-generalization": paper_protocol("ppo_pevfa"),
    },
    # the authors' code's training loop (sb3_pevfa.protocols.authors_protocol), on make_authors_env's envs
    "authors": {
        "ppo": authors_protocol("ppo"),
        "opr-e2e": authors_protocol("ppo_pevfa"),
        # the paper's control: a fixed random code per policy in place of a learned representation (Ran PR)
        "random": authors_protocol("ppo_pevfa", representation="random"),
        # OPR-E2E with the local-generalization diagnostic: a conventional critic of their PPO (2x128 ReLU, trained as
        # its critic is) beside it; the diagnostic's critic counts in its CPU time
        "opr-e2e+local-generalization": authors_protocol("ppo_pevfa"),
    },
    # the zoo variants (learning.py's), trained through rl-zoo3's entry point on one hyperparameter file (the conf)
    "zoo": dict(ZOO_VARIANTS),
    # SAC and SACPeVFA in rl-zoo3's SAC settings (OFF_POLICY): OPR, and a random code per snapshot as its control
    "sac": {
        "sac": None,
        "opr": {},
        "random": dict(representation="random"),
        # OPR with the local-generalization diagnostic adapted to Q: a conventional twin critic beside it (SB3's, on
        # the same replay with SB3's targets); the diagnostic's critic counts in its CPU time
        "opr+local-generalization": {},
    },
    "sb3": {
        "ppo": None,
        "opr": {},
        "spr": dict(representation="spr"),
        "fingerprint": dict(representation="fingerprint"),
    },
}


#: Protocols of off-policy algorithms: protocol -> (SB3's algorithm, its PeVFA class, the arguments both take); the
#: others train SB3's PPO (a variant of None) and PPOPeVFA
OFF_POLICY: dict[str, tuple[type, type, dict[str, Any]]] = {
    # rl-zoo3's SAC entries of Hopper and HalfCheetah: SB3's SAC defaults with 10k random steps first
    "sac": (SAC, SACPeVFA, dict(learning_starts=10_000)),
}

#: Protocols for Box action spaces alone (SAC; the authors' clipped and scaled Gaussian actions)
BOX_ACTIONS = {*OFF_POLICY, "authors"}
#: Protocols whose evaluation samples actions (the authors' code); the others evaluate the deterministic policy
STOCHASTIC_EVALUATION = {"authors"}
#: Protocols whose envs are not Gymnasium's as made (task, seed) -> VecEnv
ENV_MAKERS = {"authors": make_authors_env}

#: Variants that run a diagnostic beside their training: variant -> the callback's constructor arguments (the
#: on-policy LocalGeneralizationCallback, or QLocalGeneralizationCallback in the protocols of OFF_POLICY)
LOCAL_GENERALIZATION = {"opr-e2e+local-generalization": dict(net_arch=(128, 128)), "opr+local-generalization": {}}


def is_diagnostic(variant: str) -> bool:
    """Whether a variant (or its report label, ``protocol:variant``) runs a diagnostic (``LOCAL_GENERALIZATION``)."""
    return variant.rpartition(":")[2] in LOCAL_GENERALIZATION


@dataclasses.dataclass(frozen=True)
class Campaign:
    """A grid of trainings: every task x variant x seed, ``timesteps`` each, evaluated every ``eval_freq`` steps
    over ``eval_episodes`` episodes (deterministic, except in the protocols of ``STOCHASTIC_EVALUATION``)."""

    protocol: str
    tasks: tuple[str, ...]
    variants: tuple[str, ...]
    seeds: tuple[int, ...]
    timesteps: int
    eval_freq: int = 20_000
    eval_episodes: int = 10
    #: protocol "zoo": the rl-zoo3 hyperparameter file of every variant (relative to the repository); None: the
    #: default file of each variant's base algorithm (``CONFS``)
    conf: str | None = None

    def __post_init__(self) -> None:
        if self.protocol not in VARIANTS:
            raise ValueError(f"Unknown protocol {self.protocol!r}, valid choices: {sorted(VARIANTS)}")
        unknown = sorted(set(self.variants) - set(VARIANTS[self.protocol]))
        if unknown:
            raise ValueError(
                f"Unknown variants {unknown} of protocol {self.protocol!r}, valid: {sorted(VARIANTS[self.protocol])}"
            )
        if not (self.tasks and self.variants and self.seeds):
            raise ValueError("A campaign needs at least one task, one variant and one seed")
        if self.protocol != "zoo" and self.conf is not None:
            raise ValueError("only protocol 'zoo' takes a conf (an rl-zoo3 hyperparameter file)")
        if self.conf is not None and not (ROOT / self.conf).is_file():
            raise ValueError(f"No hyperparameter file {self.conf!r} in the repository")
        if min(self.timesteps, self.eval_freq, self.eval_episodes) <= 0 or self.eval_freq > self.timesteps:
            raise ValueError("timesteps, eval_freq and eval_episodes must be positive, eval_freq at most timesteps")

    def check_new(self) -> None:
        """What a new definition must also meet (a stored one is read as it was): no task, variant or seed twice, and
        more steps than the protocol's random steps before its first update (SAC's ``learning_starts``)."""
        for name in ("tasks", "variants", "seeds"):
            values = list(getattr(self, name))
            if len(set(values)) < len(values):
                raise ValueError(f"{name} {sorted({v for v in values if values.count(v) > 1})} given twice")
        starts = OFF_POLICY[self.protocol][2].get("learning_starts", 0) if self.protocol in OFF_POLICY else 0
        if self.timesteps <= starts:
            raise ValueError(f"protocol {self.protocol!r} trains from step {starts:,} on: give more timesteps")

    @property
    def search_space(self) -> dict[str, list]:
        return {"task": list(self.tasks), "variant": list(self.variants), "seed": list(self.seeds)}

    @property
    def grid(self) -> list[tuple[str, str, int]]:
        return [(t, v, s) for t in self.tasks for v in self.variants for s in self.seeds]

    def definition(self) -> dict[str, Any]:
        """What the study stores: the grid and, per variant, its constructor arguments as text."""
        settings = {variant: repr(VARIANTS[self.protocol][variant]) for variant in self.variants}
        definition = {**dataclasses.asdict(self), "tasks": list(self.tasks), "variants": list(self.variants),
                      "seeds": list(self.seeds), "settings": settings}  # fmt: skip
        if self.conf is None:
            del definition["conf"]  # as campaigns stored it before the zoo protocol
        for variant in self.variants if self.protocol == "zoo" else ():  # the files' contents too
            settings[f"{variant} conf"] = hashlib.sha1(self.conf_of(variant).read_bytes()).hexdigest()
        return definition

    def conf_of(self, variant: str) -> pathlib.Path:
        """Protocol zoo: the hyperparameter file ``variant`` trains with."""
        return ROOT / self.conf if self.conf else CONFS[base_algorithm(variant)]

    def checkpoint_folder(self, name: str, point: tuple[str, str, int] | None = None) -> pathlib.Path:
        """Where the running trials of this campaign (under this study name) keep their checkpoints; with ``point``
        (task, variant, seed), that grid point's."""
        digest = hashlib.sha1(json.dumps(self.definition(), sort_keys=True).encode()).hexdigest()[:10]
        folder = CHECKPOINT_DIR / f"{name}-{digest}"
        return folder / "{}_{}_seed{}".format(*point) if point else folder

    @classmethod
    def from_definition(cls, definition: dict[str, Any]) -> "Campaign":
        fields = {f.name for f in dataclasses.fields(cls)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in definition.items() if k in fields}
        return cls(**values)


#: The campaigns of this repository, in the order the Table-1 reproduction runs them
CAMPAIGNS: dict[str, Campaign] = {
    # (a) the paper's PPO vs PPO-PeVFA OPR-E2E with the paper's schedule of historical updates
    "table1": Campaign("paper", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5)), 1_000_000),
    # (b) PPO-PeVFA with today's default schedule of historical updates, in the same protocol
    "table1-default-schedule": Campaign("paper", TABLE1_TASKS, ("opr-e2e-default-schedule",), tuple(range(5)), 1_000_000),
    # (c) the other representations and objectives, then five more seeds
    "table1-variants": Campaign("paper", TABLE1_TASKS, ("random", "opr-cl", "spr-e2e"), tuple(range(5)), 1_000_000),
    "table1-seeds5-9": Campaign("paper", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5, 10)), 1_000_000),
    # the learned probe-state fingerprint in the same protocol, once the Table-1 grid is done
    "table1-fingerprint": Campaign("paper", TABLE1_TASKS, ("fingerprint-e2e",), tuple(range(5)), 1_000_000),
    # Table 1 as the authors' code trains (2M steps on every task, Ant too), ahead of the grids above that still run
    "table1-authors": Campaign("authors", TABLE1_TASKS, ("ppo", "opr-e2e"), tuple(range(5)), 2_000_000),
    # then the paper's Ran PR control in the same protocol: a fixed random code per policy in place of OPR
    "table1-authors-random": Campaign("authors", TABLE1_TASKS, ("random",), tuple(range(5)), 2_000_000),
    # the local-generalization diagnostic in the same protocol, where its Table 1 misses the paper's direction: the
    # tasks of the paper protocol's diagnostic (table1-local-generalization), so that the two protocols compare
    "table1-authors-local-generalization": Campaign(
        "authors", ("Hopper-v5", "Walker2d-v5"), ("opr-e2e+local-generalization",), tuple(range(3)), 2_000_000
    ),
    # SAC against SACPeVFA (OPR, and a random code per snapshot) in rl-zoo3's SAC settings, after the authors' grids
    "sac-pevfa": Campaign("sac", ("Hopper-v5", "HalfCheetah-v5"), ("sac", "opr", "random"), tuple(range(5)), 200_000),
    # the local-generalization diagnostic adapted to Q (the critic's error on each next snapshot's returns), for the
    # report of sac-pevfa where SACPeVFA misses its target
    "sac-local-generalization": Campaign(
        "sac", ("Hopper-v5", "HalfCheetah-v5"), ("opr+local-generalization",), tuple(range(3)), 200_000
    ),
    # the pilot of table1-authors: one task and seed, to check that its PPO lands near the paper's before the grid runs
    "table1-authors-pilot": Campaign("authors", ("Hopper-v5",), ("ppo", "opr-e2e"), (0,), 2_000_000),
    # the local-generalization diagnostic (paper Fig. 3b / 8) where grid (a)'s direction differs from the paper's
    "table1-local-generalization": Campaign(
        "paper", ("Walker2d-v5", "Hopper-v5"), ("opr-e2e+local-generalization",), tuple(range(3)), 1_000_000
    ),
    # the representations at SB3's PPO defaults through rl-zoo3 (as docs/results-ppo-settings.md), 300k steps
    "representations-300k": Campaign(
        "zoo",
        ("Hopper-v5", "Walker2d-v5"),
        ("ppo", "pevfa-opr", "pevfa-spr", "pevfa-fingerprint"),
        tuple(range(5)),
        300_000,
        conf="benchmarks/hyperparams/learning.yml",
    ),
}
